"""EDGES receiver calibration: noise-wave parameters and the three-position switch.

:mod:`~autocal.edges.solutions` holds the receiver solutions and their readers,
:mod:`~autocal.edges.noise_waves` the calibration equations. The lab spectra and
thermistor logs of the data folder (:mod:`~autocal.edges.lab_files`) check the calibration
(:mod:`~autocal.edges.lab_checks`); :mod:`~autocal.edges.simulated_day` simulates an
EDGES-like day through a real receiver solution into raw ACQ files, which
:mod:`~autocal.edges.day_fit` calibrates back with the auto-correlation fit.
"""
