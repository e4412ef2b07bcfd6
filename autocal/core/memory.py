"""How much memory this process can still allocate (for refusing work before it starts)."""

from __future__ import annotations

from pathlib import Path


def available_memory() -> float | None:
    """Return the bytes this process can still allocate, or ``None`` when unknown.

    ``MemAvailable`` of ``/proc/meminfo``, lowered to what a cgroup v2 memory limit leaves
    (containers, systemd units with ``MemoryMax``).
    """
    avail: float | None = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = float(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = float(Path("/sys/fs/cgroup/memory.current").read_text().strip())
        if limit != "max" and avail is not None:
            avail = min(avail, float(limit) - used)
    except (OSError, ValueError):
        pass
    return avail
