"""Test configuration: float64 everywhere (results are compared with float64 references)."""

import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
# The CLI turns JAX's persistent compilation cache on by default; in-process CLI tests must not
# write to the user's cache folder (tests/test_compilation_cache.py checks the cache in subprocesses).
os.environ.setdefault("MMPGO_COMPILATION_CACHE", "off")

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def data_dir() -> Path | None:
    env = os.environ.get("MMPGO_DATA")
    if env:
        return Path(env)
    cand = REPO.parent / "shared" / "datasets"
    return cand if cand.is_dir() else None


@pytest.fixture
def benchmark_file():
    """Path to a benchmark g2o file from MMPGO_DATA, or skip when it is not available."""

    def get(name: str) -> Path:
        d = data_dir()
        if d is None or not (d / name).is_file():
            pytest.skip(f"benchmark file {name} not available (set MMPGO_DATA)")
        return d / name

    return get
