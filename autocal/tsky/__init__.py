"""The beam-weighted sky temperature Tsky(t, nu): the engine and its cache.

:mod:`~autocal.tsky.compute` holds the entry point, :func:`~autocal.tsky.compute.compute_tsky`;
:mod:`~autocal.tsky.result` the records (a table, the LST harmonics);
:mod:`~autocal.tsky.ringfft` the ring-FFT engine, built on :mod:`~autocal.tsky.horizon`
(soft horizon, beam frame), :mod:`~autocal.tsky.rings` (HEALPix ring transforms) and
:mod:`~autocal.tsky.synthesis` (harmonics to LSTs); :mod:`~autocal.tsky.brute` the
references it is checked against; :mod:`~autocal.tsky.cache` the on-disk cache.
"""
