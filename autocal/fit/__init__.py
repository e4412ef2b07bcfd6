"""The fit of the measured power against Tsky: models, normal equations, solutions.

Also the error budget (:mod:`.uncertainty`) and receiver-temperature priors (:mod:`.priors`).
"""
