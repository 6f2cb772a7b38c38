"""The CLI's persistent compilation cache: on by default, in the folder asked for, reused by a
second run of the same shapes, and off on request (each run a fresh process)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from mmpgo_jax._core.compilation_cache import ENV, default_cache_dir

DATA = Path(__file__).parent / "data"


def _mmpgo(*args, env=None):
    full = {**os.environ, **(env or {})}
    out = subprocess.run([sys.executable, "-m", "mmpgo_jax.cli", *args], capture_output=True, text=True, env=full,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout


def _entries(folder: Path) -> set[str]:
    return {p.name for p in folder.rglob("*") if p.is_file()} if folder.exists() else set()


def _solve(*extra, env=None):
    return _mmpgo("solve", str(DATA / "tiny2d.g2o"), "--robots", "2", "--iterations", "20", "--no-progress",
                  *extra, env=env)


def test_second_run_reuses_the_cache(tmp_path):
    cache = tmp_path / "cache"
    first = _solve("--compilation-cache", str(cache))
    entries = _entries(cache)
    assert entries, "the first run wrote no compiled program"
    second = _solve("--compilation-cache", str(cache))
    assert _entries(cache) == entries  # every program came from the cache: nothing new was written
    # the same result, and the time line names every phase
    f = [re.search(r"f = 2F .* -> (\S+)", out).group(1) for out in (first, second)]
    assert f[0] == f[1]
    line = next(x for x in second.splitlines() if x.startswith("time"))
    for phase in ("read", "initialize", "build", "compile", "iterations", "write"):
        assert f"{phase} " in line, line


def test_environment_variable_moves_or_turns_off_the_cache(tmp_path):
    cache = tmp_path / "env-cache"
    _solve(env={ENV: str(cache)})
    assert _entries(cache)
    off = tmp_path / "unused"
    _solve("--no-compilation-cache", env={ENV: str(off)})
    assert not off.exists()
    _solve(env={ENV: "off", "XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert not (tmp_path / "xdg").exists()


@pytest.mark.parametrize(("value", "expected"), [("off", None), ("0", None), ("", None), ("/x/y", Path("/x/y"))])
def test_default_cache_dir(monkeypatch, value, expected):
    monkeypatch.setenv(ENV, value)
    assert default_cache_dir() == expected


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "mmpgo-jax" / "jax"
