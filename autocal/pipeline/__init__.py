"""The calibration stage: files to a :class:`~autocal.fit.lsq.Solution` and products.

:func:`autocal.pipeline.calibrate.calibrate` is the one function the CLI, the job service
and nightly runs call; :mod:`.scaleout` spreads it over Dask workers.
"""
