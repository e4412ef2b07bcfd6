"""EDGES receiver calibration: noise-wave parameters and the three-position switch."""
