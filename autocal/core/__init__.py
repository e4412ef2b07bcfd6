"""Core types and helpers every stage shares.

The observation (:mod:`.observation`), sites and coordinates, short reprs, file helpers,
the offline configuration and the user cache.
"""
