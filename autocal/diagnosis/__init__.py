"""The diagnosis: which physical effect the calibration model misses.

The effect catalogue (:mod:`.effects`), the search (:mod:`.search`), the stage's entry point
(:mod:`.run`) and hidden-effect test cases (:mod:`.hidden`).
"""
