"""File formats and data locations for autocal (imported as ``autocal.io``).

One module per format: :mod:`~autocal.io.datasets` (where data files live, offline
caches), :mod:`~autocal.io.feko` (EDGES FEKO beam text files), :mod:`~autocal.io.beamfits`
(UVBeam files through pyuvdata), :mod:`~autocal.io.tskyfile` (HDF5 Tsky tables),
:mod:`~autocal.io.uvh5` (auto-correlations in UVH5 files, read and written via pyuvdata).
"""
