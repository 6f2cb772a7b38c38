"""The centralized chordal initialization with each sparse backend, side by side.

For Cube graphs of several sizes (the paper's density, as in ``scaling.py``) and, optionally, the
benchmark files: ``chordal_initialization(graph, backend=B)`` for SuperLU (in METIS
nested-dissection order, the order included in its time) and MKL PARDISO (its own order), each in
a fresh subprocess so that the peak resident memory is that backend's; the largest difference of
the two starts is printed. Run::

    nice -n 5 python benchmarks/sparse_backends.py --poses 20000 50000 100000 300000
    nice -n 5 python benchmarks/sparse_backends.py --poses 1000000 --backends pardiso
    nice -n 5 python benchmarks/sparse_backends.py --files   # the benchmark files ($MMPGO_DATA)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def one(source: str, backend: str, out: str) -> None:
    """Child process: build or read the graph, time the chordal start, save it to ``out``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import mmpgo_jax as mm

    if source.isdigit():
        sys.path.insert(0, str(HERE))
        from scaling import default_grid

        from mmpgo_jax._experiments.synthetic import cube_dataset

        poses = int(source)
        graph = cube_dataset(0, num_poses=poses, grid=default_grid(poses)).graph
    else:
        graph = mm.read_g2o(source).graph
    start = time.perf_counter()
    X = mm.chordal_initialization(graph, backend=backend)
    seconds = time.perf_counter() - start
    np.savez(out, R=np.asarray(X.R), t=np.asarray(X.t))
    print(json.dumps({"seconds": seconds, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "poses": graph.num_poses, "edges": graph.num_edges}))


def run(source: str, backends: list[str], timeout: float) -> dict:
    import numpy as np

    row: dict = {"source": source}
    starts = {}
    with tempfile.TemporaryDirectory() as tmp:
        for backend in backends:
            out = os.path.join(tmp, f"{backend}.npz")
            try:
                proc = subprocess.run([sys.executable, __file__, "--one", source, backend, out],
                                      capture_output=True, text=True, timeout=timeout)
            except subprocess.TimeoutExpired:
                row[backend] = f"> {timeout:.0f} s (stopped)"
                continue
            if proc.returncode != 0:
                row[backend] = "failed: " + (proc.stderr.strip().splitlines() or ["?"])[-1]
                continue
            result = json.loads(proc.stdout.strip().splitlines()[-1])
            row.update(poses=result["poses"], edges=result["edges"])
            row[backend] = f"{result['seconds']:.2f} s, {result['maxrss_mb']:.0f} MB"
            with np.load(out) as z:
                starts[backend] = (z["R"], z["t"])
    if len(starts) == 2:
        (Ra, ta), (Rb, tb) = starts.values()
        row["max |difference|"] = f"R {np.abs(Ra - Rb).max():.1e}, t {np.abs(ta - tb).max():.1e}"
    return row


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        one(*sys.argv[2:5])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, nargs="*", default=[])
    parser.add_argument("--files", action="store_true", help="also the benchmark files in $MMPGO_DATA")
    parser.add_argument("--backends", nargs="+", default=["superlu", "pardiso"])
    parser.add_argument("--timeout", type=float, default=1200.0)
    args = parser.parse_args()
    sources = [str(p) for p in args.poses]
    if args.files:
        from mmpgo_jax._io.datasets import data_dir

        data = data_dir()
        sources += [str(data / f) for f in ("MIT.g2o", "intel.g2o", "M3500.g2o", "city10000.g2o",
                                             "sphere2500.g2o", "torus3D.g2o", "parking-garage.g2o")]
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()[0]:.2f}, "
          f"command: python benchmarks/sparse_backends.py {' '.join(sys.argv[1:])}")
    header = ["source", "poses", "edges", *args.backends, "max |difference|"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for source in sources:
        row = run(source, args.backends, args.timeout)
        row["source"] = Path(source).name
        print("| " + " | ".join(str(row.get(k, "")) for k in header) + " |", flush=True)
    print(f"# load at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
