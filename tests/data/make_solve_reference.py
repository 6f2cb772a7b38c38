"""Write ``solve_reference.json``: f histories and final poses of ``solve`` on benchmark files.

tests/test_solve_reference.py checks that the current code reproduces them: bit for bit from a start
that every version of the set-up builds the same way (rotations exactly I, the file's VERTEX
translations), and to rounding from the chordal start (whose linear solves may be reordered).
Regenerate (``PYTHONPATH=. python tests/data/make_solve_reference.py``) only when the solver's
arithmetic changes on purpose, and say so in the commit message.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import mmpgo_jax as mm  # noqa: E402

HERE = Path(__file__).resolve().parent
CASES = [  # (benchmark file, robots, method, iterations)
    ("MIT.g2o", 10, "amm", 100),
    ("MIT.g2o", 10, "mm", 100),
    ("sphere2500.g2o", 10, "amm", 60),
]


def unit_start(g2o) -> mm.Poses:
    """Rotations exactly I (every SO(d) projection returns them bit for bit), VERTEX translations."""
    n, d = g2o.num_poses, g2o.dim
    return mm.Poses(np.broadcast_to(np.eye(d), (n, d, d)).copy(), np.asarray(g2o.vertex_t, np.float64))


def poses_digest(poses) -> str:
    R = np.ascontiguousarray(np.asarray(poses.R, np.float64))
    t = np.ascontiguousarray(np.asarray(poses.t, np.float64))
    return hashlib.sha256(R.tobytes() + t.tobytes()).hexdigest()


def run(path, robots, method, iterations, init):
    g2o = mm.read_g2o(path)
    start = unit_start(g2o) if init == "unit" else init
    res = mm.solve(g2o.graph, robots, method=method, iterations=iterations, init=start)
    return {"f": [float(v).hex() for v in res.history.f], "poses_sha256": poses_digest(res.poses)}


def main(data: Path) -> None:
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=HERE).stdout.strip()
    out = {"commit": commit, "cases": []}
    for name, robots, method, iterations in CASES:
        for init in ("unit", "chordal"):
            r = run(data / name, robots, method, iterations, init)
            out["cases"].append({"file": name, "robots": robots, "method": method, "iterations": iterations,
                                 "init": init, **r})
            print(name, method, init, float.fromhex(r["f"][-1]), flush=True)
    (HERE / "solve_reference.json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parents[2] / "shared" / "datasets")
