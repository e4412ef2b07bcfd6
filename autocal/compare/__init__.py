"""Comparison of autocal's gains with cross-correlation gains, and delay spectra."""
