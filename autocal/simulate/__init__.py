"""Simulated observations and the reproduction of the paper (Gehlot et al. 2021)."""
