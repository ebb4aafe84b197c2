"""Joint calibration: the zero of each joint the hardware does not know, declared and stored
under the hardware's identity, and the fit of the gravity torques on the joints."""
