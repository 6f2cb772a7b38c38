"""Generate the symbol-keyed 3-robot example ``datasets/cube3_symbols.g2o`` (and its ground truth).

    python datasets/make_multi_robot_example.py        # rewrites the two files (deterministic)
    python datasets/make_multi_robot_example.py DIR    # writes them to DIR instead

A Cube graph (:func:`mmpgo_jax.cube_dataset`, seed 0: 300 poses on a 4 x 4 x 4 lattice of 1 m
cells, loop closures between nearby poses with probability 0.1, the paper's noise) is cut into
three robots, ``a``, ``b`` and ``c``, each driving one third of the path. Vertex ids are GTSAM
symbol keys, ``Symbol(robot, index)`` = robot character << 56 | index, the index counting each
robot's own poses from 0. The two odometry edges that joined the thirds are removed (separate
robots share no odometry); the loop closures between poses of different robots are the
inter-robot edges. VERTEX lines hold each robot's odometry estimate (its measurements composed
from its first pose, placed at the ground truth: the robots' starting poses are known, as from a
rendezvous), so ``--init vertices`` starts from dead reckoning. ``cube3_ground_truth.g2o`` holds
the true poses (VERTEX lines only, for ``--ground-truth``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._core.pose_graph import PoseGraph, Poses, connected_components  # noqa: E402
from mmpgo_jax._io.atomic import atomic_group  # noqa: E402
from mmpgo_jax._io.multi_robot import symbol_keys  # noqa: E402

HERE = Path(__file__).resolve().parent
ROBOTS = "abc"
POSES = 300


def odometry_estimate(graph: PoseGraph, rop: np.ndarray, truth: Poses) -> Poses:
    """Each robot's odometry chain composed from its first pose (set to the ground truth)."""
    n = graph.num_poses
    start = np.r_[True, rop[1:] != rop[:-1]]
    fixed = mm.FixedPoses(np.flatnonzero(start), np.asarray(truth.R)[start], np.asarray(truth.t)[start])
    odo = np.flatnonzero(np.asarray(graph.j) == np.asarray(graph.i) + 1)
    chain = PoseGraph.from_arrays(np.asarray(graph.i)[odo], np.asarray(graph.j)[odo], np.asarray(graph.R)[odo],
                                  np.asarray(graph.t)[odo], np.asarray(graph.kappa)[odo], np.asarray(graph.tau)[odo],
                                  num_poses=n, dtype=np.float64)
    return mm.odometry_initialization(chain, fixed=fixed)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    out = Path(args[0]) if args else HERE
    ds = mm.cube_dataset(seed=0, grid=4, num_poses=POSES)
    g = ds.graph
    rop = mm.contiguous_robots(g.num_poses, len(ROBOTS))
    i, j = np.asarray(g.i), np.asarray(g.j)
    keep = ~((j == i + 1) & (rop[i] != rop[j]))  # no odometry between robots
    graph = PoseGraph.from_arrays(i[keep], j[keep], np.asarray(g.R)[keep], np.asarray(g.t)[keep],
                                  np.asarray(g.kappa)[keep], np.asarray(g.tau)[keep], num_poses=g.num_poses,
                                  dtype=np.float64)
    if len(connected_components(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))) != 1:
        raise SystemExit("the robots' graphs are not joined by loop closures; pick another seed")
    first = np.searchsorted(rop, np.arange(len(ROBOTS)))
    keys = symbol_keys(np.array(list(ROBOTS))[rop], np.arange(g.num_poses) - first[rop])
    estimate = odometry_estimate(graph, rop, ds.ground_truth)
    with atomic_group():
        mm.write_g2o(out / "cube3_symbols.g2o", graph, estimate, vertex_ids=keys)
        mm.write_g2o(out / "cube3_ground_truth.g2o", PoseGraph.from_arrays([], [], np.zeros((0, 3, 3)),
                                                                            np.zeros((0, 3)), [], [], g.num_poses),
                     ds.ground_truth, vertex_ids=keys)
    inter = int(np.sum(rop[np.asarray(graph.i)] != rop[np.asarray(graph.j)]))
    print(f"wrote {out / 'cube3_symbols.g2o'}: {graph.num_poses} poses, {graph.num_edges} edges "
          f"({inter} inter-robot), robots {', '.join(ROBOTS)}; and {out / 'cube3_ground_truth.g2o'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
