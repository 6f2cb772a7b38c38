"""The host's resources that size batches and refuse work that cannot fit."""

from __future__ import annotations

__all__ = ["available_memory_bytes", "last_level_cache_bytes"]


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


def last_level_cache_bytes(default: int = 32 << 20) -> int:
    """The largest CPU cache of this host (Linux sysfs: the size of cpu0's highest-level data or
    unified cache), or ``default`` where it cannot be read."""
    from pathlib import Path

    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    best = 0
    for index in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*"):
        try:
            if (index / "type").read_text().strip() == "Instruction":
                continue
            size = (index / "size").read_text().strip()
            best = max(best, int(size[:-1]) * units[size[-1]] if size[-1] in units else int(size))
        except (OSError, ValueError):
            continue
    return best or default
