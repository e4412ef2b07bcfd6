"""File formats and data locations for autocal (imported as ``autocal.io``).

One module per format, pyuvdata-style:

* data locations: :mod:`~autocal.io.datasets` (where data files live, offline caches);
* beams: :mod:`~autocal.io.feko` (EDGES FEKO beam text files), :mod:`~autocal.io.beamfits`
  (UVBeam files through pyuvdata);
* Tsky tables: :mod:`~autocal.io.tskyfile` (HDF5);
* auto-correlations in UVH5 files: :mod:`~autocal.io.uvh5` (read and written whole via
  pyuvdata), :mod:`~autocal.io.uvh5_meta` (header scan, selections),
  :mod:`~autocal.io.uvh5_uvdata` (the UVData the writers build),
  :mod:`~autocal.io.uvh5_writer` (a file written in parts), :mod:`~autocal.io.uvh5_blocks`
  and :mod:`~autocal.io.uvh5_chunks` (a file read block by block); Miriad data sets:
  :mod:`~autocal.io.miriad`;
* EDGES spectra: :mod:`~autocal.io.edges_spectra` (the container),
  :mod:`~autocal.io.edges_acq` (ACQ files), :mod:`~autocal.io.edges_hdf5` (autocal's
  HDF5 layout), :mod:`~autocal.io.edges_time` (timestamps, LSTs),
  :mod:`~autocal.io.edges_read` (either format, by content);
* calibration solutions as UVCal files: :mod:`~autocal.io.calsol_files` (format check,
  one file), :mod:`~autocal.io.calsol_read` (reference gains),
  :mod:`~autocal.io.calsol_uvcal` (a solution as a UVCal), :mod:`~autocal.io.calsol_write`
  (calh5/calfits);
* autocal's own products: :mod:`~autocal.io.products` (the solution HDF5),
  :mod:`~autocal.io.simtruth` (simulation truth).
"""
