"""Cameras: each device owned by one thread, its latest frame JPEG-encoded once, colour detection
and the camera-to-table calibration (a homography), for the colour-sorting lab (issue 25)."""
