"""The host's resources that size batches and refuse work that cannot fit."""

from __future__ import annotations

__all__ = ["available_memory_bytes"]


def available_memory_bytes(default: int = 16 << 30) -> int:
    """MemAvailable from ``/proc/meminfo`` (what the kernel can hand out without swapping), or
    ``default`` where that file is missing (macOS, Windows)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return default
