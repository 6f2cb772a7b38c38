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


def test_traced_program_is_kept_and_reused(tmp_path, monkeypatch):
    """With the cache on, a compiled chunk's traced program is serialized (jax.export) beside the
    compiled code; a later process deserializes it instead of tracing, with the same results. A
    changed static argument is another program."""
    import jax.numpy as jnp
    import numpy as np

    from mmpgo_jax._core import compilation_cache as cc

    monkeypatch.setattr(cc, "compilation_cache_dir", lambda: tmp_path)  # (JAX's own cache stays as it is)
    traces = []

    def fn(x, scale, y):
        traces.append(scale)
        return {"sum": x * scale + y, "n": jnp.sum(y)}

    x, y = jnp.arange(4.0), jnp.ones(4)
    out = {"sum": 0, "n": 0}
    first = cc.compile_exported(fn, (x, 2.0, y), (1,), out)
    assert traces == [2.0] and list((tmp_path / "exported").glob("*.bin"))
    again = cc.compile_exported(fn, (x, 2.0, y), (1,), out)  # as a new process would: deserialized
    assert traces == [2.0]
    for f in (first, again):
        res = f(x, y)
        np.testing.assert_array_equal(res["sum"], np.arange(4.0) * 2 + 1)
        assert float(res["n"]) == 4.0
    cc.compile_exported(fn, (x, 3.0, y), (1,), out)
    assert traces == [2.0, 3.0] and len(list((tmp_path / "exported").glob("*.bin"))) == 2
    monkeypatch.setattr(cc, "compilation_cache_dir", lambda: None)
    assert cc.compile_exported(fn, (x, 2.0, y), (1,), out) is None  # cache off: the caller compiles


def test_sharded_program_is_kept_and_reused(tmp_path):
    """A shard_map program over two CPU devices (a child process with its own XLA flags) is kept
    too: the second call deserializes it (no trace), takes and returns the same shardings, and gives
    the same numbers; the same shapes laid out otherwise (replicated) are another program."""
    import textwrap

    child = textwrap.dedent(f"""
        import jax, jax.numpy as jnp, numpy as np
        from pathlib import Path
        from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
        from mmpgo_jax._core import compilation_cache as cc
        cc.compilation_cache_dir = lambda: Path({str(tmp_path)!r})
        mesh = Mesh(np.array(jax.devices()), ("r",))
        traces = []
        def chunk(x, y):
            traces.append(1)
            return x * 2 + jax.lax.psum(jnp.sum(x), "r"), y + 1
        fn = jax.jit(jax.shard_map(chunk, mesh=mesh, in_specs=(P("r"), P()), out_specs=(P("r"), P()),
                                   check_vma=False))
        x = jax.device_put(jnp.arange(8.0), NamedSharding(mesh, P("r")))
        y = jax.device_put(jnp.ones(()), NamedSharding(mesh, P()))
        first = cc.compile_exported(fn, (x, y), (), (0, 0))
        again = cc.compile_exported(fn, (x, y), (), (0, 0))
        assert len(traces) == 1, traces
        a, b = first(x, y), again(x, y)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(b[0], np.arange(8.0) * 2 + 28.0)
        assert b[0].sharding.spec == P("r") and b[1].sharding.spec == P()
        c = again(*b)  # outputs feed the next call, as a driven chunk's state does
        np.testing.assert_array_equal(c[0], b[0] * 2 + float(np.sum(b[0])))
        replicated = jax.device_put(jnp.arange(8.0), NamedSharding(mesh, P()))
        other = cc.compile_exported(fn, (replicated, y), (), (0, 0))
        assert len(list(Path({str(tmp_path)!r}, "exported").glob("*.bin"))) == 2
        np.testing.assert_array_equal(other(replicated, y)[0], b[0])
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_solve_keeps_start_state_and_chunk_programs(tmp_path, monkeypatch):
    """``solve`` keeps both of its programs (the state at X^0 and the chunk of iterations) in the
    exported cache; a solve that finds them (in-process cache cleared, as in a new process) gives
    the same result bit for bit."""
    import numpy as np

    import mmpgo_jax as mm
    from mmpgo_jax._core import compilation_cache as cc
    from mmpgo_jax._mm import driver

    monkeypatch.setattr(cc, "compilation_cache_dir", lambda: tmp_path)
    graph = mm.cube_dataset(3, num_poses=60, grid=3).graph
    monkeypatch.setattr(driver, "_COMPILED", {})
    first = mm.solve(graph, 3, iterations=6, chunk_size=3)
    names = sorted(p.name for p in (tmp_path / "exported").glob("*.bin"))
    assert len(names) == 2  # start_state and the chunk
    monkeypatch.setattr(driver, "_COMPILED", {})
    again = mm.solve(graph, 3, iterations=6, chunk_size=3)
    assert sorted(p.name for p in (tmp_path / "exported").glob("*.bin")) == names
    np.testing.assert_array_equal(np.asarray(again.history.f), np.asarray(first.history.f))
    np.testing.assert_array_equal(np.asarray(again.poses.R), np.asarray(first.poses.R))
