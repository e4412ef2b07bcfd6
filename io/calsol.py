"""Temporary re-exports for the layout merge."""

from autocal.io.calsol_files import CalsolFormatError  # noqa: F401
from autocal.io.calsol_read import ReferenceGains, read_reference_gains  # noqa: F401
from autocal.io.calsol_uvcal import config_sources, solution_to_uvcal  # noqa: F401
from autocal.io.calsol_write import write_calfits, write_calh5  # noqa: F401
