"""Test configuration: float64 everywhere (results are compared with float64 references), and
XLA:CPU's quick code generation for the test processes and the subprocesses they start.

Most tests compile many small programs and run each for a few iterations: with XLA:CPU's older
LLVM IR emitters at LLVM optimization level 0 (the options the library itself uses for small
programs and for programs run once, ``mmpgo_jax._core.compile_mode``, here for every program) the
tests' durations summed to 1196 s instead of 1402 s on a 2-core Intel Xeon (2026-12-07, the same
tests; tests/test_rbcd.py alone 75 s instead of 131 s), every test passing either way; a few that
run many iterations are slower, most are faster. ``MMPGO_TEST_XLA_DEFAULTS=1`` runs the tests with
XLA's own defaults.
"""

import os
from pathlib import Path

QUICK_CODE_GENERATION = "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0"
if os.environ.get("MMPGO_TEST_XLA_DEFAULTS", "") in ("", "0"):
    # before JAX's backend starts; a user's own XLA_FLAGS are kept (later flags win in XLA)
    os.environ["XLA_FLAGS"] = f"{QUICK_CODE_GENERATION} {os.environ.get('XLA_FLAGS', '')}".strip()

import jax  # noqa: E402

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
