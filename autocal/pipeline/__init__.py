"""The calibration stage: files to a :class:`~autocal.fit.solution.Solution` and products.

:func:`autocal.pipeline.calibrate.calibrate` is the one function the CLI, the job service
and nightly runs call. Its steps, in order: :mod:`.config` (the settings),
:mod:`.sources` (the inputs and their Tsky), :mod:`.partials` (one file's normal sums, the
unit of work), :mod:`.passes` (the files' sums per pass, here or on Dask workers through
:mod:`.scaleout`), :mod:`.systematics` (the reference comparison's alternative fits) and
:mod:`.products` (the files written).
"""
