"""The fit of the measured power against Tsky: models, normal equations, solutions.

Also the error budget (:mod:`.total_uncertainty`) and receiver-temperature priors (:mod:`.priors`).

Modules, each importing only those before it: :mod:`.model` (the time model, design,
weights), :mod:`.moments` and :mod:`.kernels` (the numpy and numba engines of the moment
sums), :mod:`.sums` (normal sums and their accumulation), :mod:`.solve` (the batched solve),
:mod:`.blocks` (sums per time block), :mod:`.separation` (how well gain and noise separate),
:mod:`.total_uncertainty`, :mod:`.solution` (the result), :mod:`.priors` and :mod:`.passes`
(the weighting passes and :func:`~autocal.fit.passes.fit`, the in-memory fit).
"""
