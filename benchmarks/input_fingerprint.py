"""Cost of fingerprinting a job's inputs at submission (autocal.service.input_check).

Writes a file of ``--size-mib`` random bytes and times, several times each, the whole-file
SHA-256 and the sampled fingerprint (size, modification time and 16 blocks of 1 MiB) that
:func:`autocal.service.input_check.file_fingerprint` uses above
``AUTOCAL_FINGERPRINT_FULL_BYTES``. The file was just written, so it is read from the page
cache: the figures are the hashing cost; a cold read adds the disk's time, which the sampled
fingerprint bounds at 16 MiB per file. Prints one JSON line::

    python benchmarks/input_fingerprint.py --size-mib 1024 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from autocal.service.input_check import file_fingerprint


def _time(path: Path, full_bytes: int, repeats: int) -> float:
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        file_fingerprint(path, full_bytes)
        runs.append(time.perf_counter() - start)
    return statistics.median(runs)


def main() -> None:
    """Run the benchmark and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size-mib", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    size = args.size_mib * 1024**2
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "input.bin"
        with open(path, "wb") as handle:
            for _ in range(args.size_mib):
                handle.write(os.urandom(1024**2))
        full = _time(path, size, args.repeats)
        sampled = _time(path, 0, args.repeats)
    print(
        json.dumps(
            {
                "size_mib": args.size_mib,
                "full_sha256_s": round(full, 3),
                "full_mb_per_s": round(size / full / 1e6),
                "sampled_s": round(sampled, 4),
                "repeats": args.repeats,
                "load": os.getloadavg()[0],
            }
        )
    )


if __name__ == "__main__":
    main()
