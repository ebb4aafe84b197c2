"""Recordings: demonstrations written as LeRobot v3.0 datasets (format, video, time grid,
episodes under the data folder)."""
