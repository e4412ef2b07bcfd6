"""The diagnosis: which physical effect the calibration model misses.

The candidate effects (:mod:`.effects`, listed by :mod:`.catalogue`); the extended fit
(:mod:`.extended_fit`, its normal equations :mod:`.normal_equations`, streamed through
:mod:`.chunks`); the step search (:mod:`.stepwise`: each step fits the candidates,
:mod:`.candidate_fits`, ranks their :mod:`.trials`, checks them, :mod:`.consistency`,
:mod:`.jitter`, and accepts the best, :mod:`.acceptance`, in the state of
:mod:`.search_state`; large observations are screened, :mod:`.screening`), with the bandpass
domain (:mod:`.bandpass`), the per-antenna gains (:mod:`.feeds`), outlier flagging
(:mod:`.outliers`), the gap (:mod:`.gap`) and the products' impact (:mod:`.impact`); its
result and products (:mod:`.report`); the stage's entry point (:mod:`.run`, reading the data
with :mod:`.reading` and flagging band edges and RFI in it as a calibration does,
:func:`autocal.pipeline.flagging.flag_observation`) and hidden-effect test cases
(:mod:`.hidden`).
"""
