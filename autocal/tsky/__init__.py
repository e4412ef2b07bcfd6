"""The beam-weighted sky temperature Tsky(t, nu): the engine and its cache."""
