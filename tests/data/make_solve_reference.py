"""Record f histories and final poses of ``solve`` on benchmark files in ``solve_reference.json``.

tests/test_solve_reference.py checks that the current code reproduces them: bit for bit from a start
that every version of the set-up builds the same way (rotations exactly I, the file's VERTEX
translations), and to rounding from the chordal start (whose linear solves may be reordered).

Bit-for-bit equality only holds on the machine that recorded the numbers: XLA compiles for the host
CPU's instruction set (AVX2, AVX-512, FMA change the order and fusion of floating-point operations)
and NumPy's BLAS picks its kernels by CPU as well. So the file holds several recordings, one per
machine fingerprint (``machine_fingerprint``: the CPU's model and SIMD feature flags, an XLA ISA cap
if XLA_FLAGS sets one, jax, jaxlib and NumPy versions); running this script replaces the recording of
this machine's fingerprint and keeps the others. Each recording also stores 64 final poses and the
sums over all poses as numbers, for the tolerance comparison on machines without a recording.

The numbers come from whatever ``mmpgo_jax`` is imported, and the recording names that tree's commit.
To add a machine without changing the numbers' origin, run this script with ``PYTHONPATH`` pointing at
a checkout of the commit the other recordings name, e.g.::

    git worktree add --detach ../old <commit>
    PYTHONPATH=../old python tests/data/make_solve_reference.py [datasets folder]

Record from the current code (``PYTHONPATH=. python tests/data/make_solve_reference.py --replace-all``)
only when the solver's arithmetic changes on purpose, and say so in the commit message.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import mmpgo_jax as mm  # noqa: E402

HERE = Path(__file__).resolve().parent
REFERENCE = HERE / "solve_reference.json"
CASES = [  # (benchmark file, robots, method, iterations)
    ("MIT.g2o", 10, "amm", 100),
    ("MIT.g2o", 10, "mm", 100),
    ("sphere2500.g2o", 10, "amm", 60),
]
# The inner solver's settings the recordings were made with (SubproblemConfig's defaults at commit
# 797e363, before the decrease rule), passed explicitly so that a later change of the defaults
# leaves the recordings valid:
# the recordings guard the arithmetic of the set-up and the solver, not the choice of tolerances.
RECORDED_SUBPROBLEM = mm.SubproblemConfig(gradient_tolerance=0.1, cg_tolerance=1e-2, decrease_tolerance=0.0)
PROBE_POSES = 64  # final poses stored as numbers (besides the digest of all of them) per case

# CPU flags that change the code XLA's CPU backend (LLVM) and NumPy's BLAS generate.
_SIMD_FLAG = re.compile(r"^(sse4_1|sse4_2|ssse3|avx.*|fma|fma4|f16c|amx.*|asimd.*|sve.*|neon)$")


def _cpu() -> tuple[str | None, list[str] | None]:
    """(vendor, family and model; SIMD feature flags, sorted) of the host CPU from Linux's
    /proc/cpuinfo or macOS's sysctl; None for what is unknown. The model decides which CPU LLVM
    tunes XLA's code for (e.g. znver3 vs znver5) even with the same flags."""
    try:
        info = {}
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if not key.strip():
                break  # the first processor's block is enough
            info.setdefault(key.strip(), value.strip())
        flags = info.get("flags", info.get("Features"))
        labels = {"vendor_id": "", "cpu family": "family ", "model": "model ", "CPU implementer": "implementer ",
                  "CPU part": "part "}
        cpu = " ".join(f"{label}{info[k]}" for k, label in labels.items() if k in info)
        return cpu or None, None if flags is None else sorted({f for f in flags.split() if _SIMD_FLAG.match(f)})
    except OSError:
        pass
    if platform.system() == "Darwin":
        def sysctl(*keys):
            return subprocess.run(["sysctl", "-n", *keys], capture_output=True, text=True).stdout.strip()
        flags = {f.lower().replace(".", "_") for f in sysctl("machdep.cpu.features",
                                                             "machdep.cpu.leaf7_features").split()}
        return sysctl("machdep.cpu.brand_string") or None, sorted(f for f in flags if _SIMD_FLAG.match(f)) or None
    return None, None


def _blas_kernels() -> list[str] | None:
    """NumPy's BLAS and the kernel family it runs (threadpoolctl's ``architecture``: OpenBLAS picks
    it per CPU, and OPENBLAS_CORETYPE overrides it: on one AMD Zen 4 machine the SkylakeX and Zen
    kernels give different last bits), sorted; None when threadpoolctl cannot tell."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return None
    blas = [f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')}" for i in threadpool_info()
            if i.get("user_api") == "blas"]
    return sorted(blas) or None


def machine_fingerprint() -> dict:
    """What decides the solver's last bits besides the code: CPU architecture, model and SIMD flags,
    the XLA ISA cap (``--xla_cpu_max_isa`` in XLA_FLAGS, if set), NumPy's BLAS kernels, jax, jaxlib
    and NumPy versions. A recording made before a field existed has it unknown, so it never matches
    exactly (the tolerance comparison applies until this machine is recorded again)."""
    import jaxlib

    cpu, flags = _cpu()
    isa = re.search(r"--xla_cpu_max_isa=(\S+)", os.environ.get("XLA_FLAGS", ""))
    return {"arch": platform.machine(), "cpu": cpu, "cpu_simd": flags,
            "xla_cpu_max_isa": isa.group(1) if isa else "not set", "blas": _blas_kernels(),
            "jax": jax.__version__, "jaxlib": jaxlib.__version__, "numpy": np.__version__}


def fingerprint_distance(a: dict, b: dict) -> float:
    """0 for equal, fully known fingerprints; otherwise 1 per differing or unknown (None) field,
    except the SIMD flags, which add the Jaccard distance of the two flag sets (1 if either is unknown)."""
    d = 0.0
    for key in set(a) | set(b):
        x, y = a.get(key), b.get(key)
        if x is None or y is None:
            d += 1.0
        elif key == "cpu_simd":
            d += 1.0 - len(set(x) & set(y)) / len(set(x) | set(y)) if set(x) | set(y) else 0.0
        elif x != y:
            d += 1.0
    return d


def load_recordings(path: Path = REFERENCE) -> list[dict]:
    return json.loads(path.read_text())["recordings"]


def unit_start(g2o) -> mm.Poses:
    """Rotations exactly I (every SO(d) projection returns them bit for bit), VERTEX translations."""
    n, d = g2o.num_poses, g2o.dim
    return mm.Poses(np.broadcast_to(np.eye(d), (n, d, d)).copy(), np.asarray(g2o.vertex_t, np.float64))


def poses_digest(poses) -> str:
    R = np.ascontiguousarray(np.asarray(poses.R, np.float64))
    t = np.ascontiguousarray(np.asarray(poses.t, np.float64))
    return hashlib.sha256(R.tobytes() + t.tobytes()).hexdigest()


def probe_indices(num_poses: int) -> np.ndarray:
    """Indices of the poses stored as numbers: PROBE_POSES evenly spread, first and last included."""
    return np.unique(np.linspace(0, num_poses - 1, min(PROBE_POSES, num_poses)).round().astype(np.int64))


def _hex_row(values) -> str:
    return " ".join(float(v).hex() for v in values)


def unhex_row(row: str) -> np.ndarray:
    return np.array([float.fromhex(v) for v in row.split()])


def poses_probe(poses) -> dict:
    """The probe poses' indices and their R and t flattened (one line of hex numbers per pose), and
    the sums of R and t over all poses."""
    R = np.asarray(poses.R, np.float64)
    t = np.asarray(poses.t, np.float64)
    idx = probe_indices(len(t))
    rows = np.concatenate([R[idx].reshape(len(idx), -1), t[idx]], axis=1)
    sums = np.concatenate([R.sum(axis=0).ravel(), t.sum(axis=0)])
    return {"index": " ".join(map(str, idx)), "Rt": [_hex_row(row) for row in rows], "sum": _hex_row(sums)}


def probe_arrays(probe: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indices, R and t rows, sums) of a ``poses_probe`` as arrays."""
    return (np.array(probe["index"].split(), np.int64), np.array([unhex_row(r) for r in probe["Rt"]]),
            unhex_row(probe["sum"]))


def run(path, robots, method, iterations, init):
    g2o = mm.read_g2o(path)
    start = unit_start(g2o) if init == "unit" else init
    res = mm.solve(g2o.graph, robots, method=method, iterations=iterations, init=start,
                   subproblem=RECORDED_SUBPROBLEM)
    return {"f": [float(v).hex() for v in res.history.f], "poses_sha256": poses_digest(res.poses),
            "poses_probe": poses_probe(res.poses)}


def library_commit() -> str:
    """Commit of the tree ``mmpgo_jax`` was imported from (with '-dirty' if it has local changes)."""
    root = Path(mm.__file__).resolve().parents[1]
    out = subprocess.run(["git", "describe", "--always", "--abbrev=40", "--dirty", "--match=^$"],
                         capture_output=True, text=True, cwd=root).stdout.strip()
    return out or "unknown"


def main(data: Path, replace_all: bool = False) -> None:
    machine = machine_fingerprint()
    rec = {"machine": machine, "commit": library_commit(), "cases": []}
    print("mmpgo_jax from", Path(mm.__file__).resolve().parent, "at", rec["commit"], flush=True)
    print("machine", json.dumps(machine), flush=True)
    for name, robots, method, iterations in CASES:
        for init in ("unit", "chordal"):
            r = run(data / name, robots, method, iterations, init)
            rec["cases"].append({"file": name, "robots": robots, "method": method, "iterations": iterations,
                                 "init": init, **r})
            print(name, method, init, float.fromhex(r["f"][-1]), flush=True)
    others = [] if replace_all or not REFERENCE.is_file() else load_recordings()
    others = [o for o in others if o["machine"] != machine]
    if others and {o["commit"] for o in others} != {rec["commit"]}:
        print("note: the other recordings name", sorted({o["commit"] for o in others}), flush=True)
    text = json.dumps({"recordings": others + [rec]}, indent=1) + "\n"
    tmp = REFERENCE.with_suffix(".json.tmp")
    tmp.write_text(text)
    os.replace(tmp, REFERENCE)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--replace-all"]
    main(Path(args[0]) if args else HERE.parents[2] / "shared" / "datasets", "--replace-all" in sys.argv[1:])
