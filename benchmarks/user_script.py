"""What a user would write instead of autocal: pyuvdata + a vectorised numpy least-squares fit.

Reads one UVH5 file with ``UVData.read`` (the autos only, ``ant_str="auto"``: the smallest
read pyuvdata offers), arranges the autos as ``(Nant, Npol, Ntime, Nfreq)`` and fits

    autos = G (Tsky + Trxr) = G Tsky + G Trxr

for every antenna, polarisation and channel by (unweighted) linear least squares over time:
the two normal equations of ``(G, G Trxr)`` per channel are formed with vectorised numpy
reductions over time and solved with one batched ``np.linalg.solve``; flagged samples get
zero weight. Tsky ``(Npol, Ntime, Nfreq)`` is given as a ``.npz`` file (``tsky``, ``jds``,
``pols``), the same array autocal uses (``benchmarks/user_vs_autocal.py`` writes it from
autocal's Tsky cache), so no sky model is computed here. G and Trxr are saved to ``--out``
(``.npz``), as a user would keep them::

    python benchmarks/user_script.py FILE.uvh5 --tsky tsky.npz --out user_fit.npz

This is the comparison of issue 25, item 3; it is a script, not part of autocal.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from pyuvdata import UVData
from pyuvdata.utils import polnum2str


def read_autos(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str], np.ndarray]:
    """Return autos ``(Nant, Npol, Ntime, Nfreq)``, their flags, the JDs, pols and antennas."""
    uvd = UVData()
    uvd.read(path, ant_str="auto")
    times, t_index = np.unique(uvd.time_array, return_inverse=True)
    ants, a_index = np.unique(uvd.ant_1_array, return_inverse=True)
    pols = [
        polnum2str(p, x_orientation=uvd.telescope.x_orientation) for p in uvd.polarization_array
    ]
    shape = (ants.size, times.size, uvd.Nfreqs, len(pols))
    autos = np.zeros(shape)
    flags = np.ones(shape, dtype=bool)
    autos[a_index, t_index] = uvd.data_array.real
    flags[a_index, t_index] = uvd.flag_array
    # (Nant, Ntime, Nfreq, Npol) -> (Nant, Npol, Ntime, Nfreq)
    return (
        autos.transpose(0, 3, 1, 2),
        flags.transpose(0, 3, 1, 2),
        times,
        pols,
        ants,
    )


def fit(autos: np.ndarray, flags: np.ndarray, tsky: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``G`` and ``Trxr`` of ``autos = G (Tsky + Trxr)`` per (ant, pol, chan)."""
    w = (~flags).astype(float)
    t = tsky[None]  # (1, Npol, Ntime, Nfreq)
    s0 = w.sum(axis=2)
    s1 = (w * t).sum(axis=2)
    s2 = (w * t * t).sum(axis=2)
    wy = w * autos
    sy = wy.sum(axis=2)
    sty = (wy * t).sum(axis=2)
    normal = np.stack([np.stack([s2, s1], -1), np.stack([s1, s0], -1)], -2)
    rhs = np.stack([sty, sy], -1)[..., None]
    solvable = np.linalg.det(normal) > 0
    normal[~solvable] = np.eye(2)
    params = np.linalg.solve(normal, rhs)[..., 0]
    gain = np.where(solvable, params[..., 0], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        trxr = np.where(solvable, params[..., 1] / params[..., 0], np.nan)
    return gain, trxr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", help="UVH5 file")
    parser.add_argument(
        "--tsky", required=True, help=".npz with tsky (Npol, Ntime, Nfreq), jds, pols"
    )
    parser.add_argument("--out", required=True, help="where G and Trxr go (.npz)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    autos, flags, jds, pols, ants = read_autos(args.file)
    t_read = time.perf_counter() - t0
    table = np.load(args.tsky)
    if not np.allclose(table["jds"], jds, rtol=0, atol=1e-7):
        raise SystemExit("the Tsky table's JDs are not the file's")
    order = [list(table["pols"]).index(p) for p in pols]
    gain, trxr = fit(autos, flags, table["tsky"][order])
    np.savez(args.out, gain=gain, trxr=trxr, antennas=ants, pols=np.array(pols))
    print(f"read {t_read:.2f} s, fit {time.perf_counter() - t0 - t_read:.2f} s")


if __name__ == "__main__":
    main()
