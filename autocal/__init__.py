"""autocal: calibration of radio-telescope auto-correlations against sky models.

Importing the package configures astropy for offline use (see :mod:`autocal.offline`);
nothing in autocal reaches for the internet at run time.
"""

from importlib.metadata import PackageNotFoundError, version

from autocal.offline import configure_offline

try:
    __version__ = version("autocal")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

configure_offline()

__all__ = ["__version__", "configure_offline"]
