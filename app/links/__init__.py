"""Transports: one byte link per arm (serial: polled on its own thread, or on the loop; HID;
the in-process simulator) and the discovery of devices."""
