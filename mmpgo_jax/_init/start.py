"""One entry point for every kind of start: :func:`initialize` (a method name, ``Poses`` or a file).

The methods live in :mod:`~mmpgo_jax._init.chordal` (chordal, odometry, pose files),
:mod:`~mmpgo_jax._init.distributed_chordal` (§VII, distributed: CG or Algorithm 3), :mod:`~mmpgo_jax._init.robust_start`
(the GNC-chordal start of robust losses) and :mod:`~mmpgo_jax._init.robust_distributed` (the
distributed robust start: each robot's own GNC, then the robots' frames from their closures).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from .._core.gauge import FixedPoses, express_in_frame
from .._core.pose_graph import HostPoses, PoseGraph, Poses
from .chordal import chordal_initialization, load_poses, odometry_initialization, poses_from_arrays

__all__ = ["INITIALIZATION_METHODS", "initialize", "initialize_with_weights"]

INITIALIZATION_METHODS = ("chordal", "distributed-chordal", "distributed-robust", "gnc-chordal", "odometry",
                          "vertices")
#: the methods that take keyword options
_WITH_OPTIONS = ("distributed-chordal", "distributed-robust", "gnc-chordal")


def initialize(
    graph: PoseGraph,
    method="chordal",
    *,
    initial: Poses | None = None,
    robots=None,
    fixed: FixedPoses | None = None,
    host: bool = False,
    **options,
) -> Poses:
    """Initial poses for ``graph``; the ``fixed`` poses (if any) are at their values in every case.

    ``method`` is one of

    * ``"chordal"`` -- :func:`chordal_initialization` (the paper's start, docs/conventions.md §5);
    * ``"distributed-chordal"`` -- :func:`~mmpgo_jax._init.distributed_chordal.distributed_chordal_initialization`
      with ``robots`` (a count, an (n,) robot-of-pose array or a ``Partition``; default
      min(10, n) contiguous robots) and ``options`` passed through;
    * ``"gnc-chordal"`` -- :func:`~mmpgo_jax._init.robust_start.gnc_chordal_initialization`: a start
      that outlier loop closures do not bend (GNC-TLS whose stages are chordal solves refined by
      Newton), the default start of robust losses; ``options``: ``scale``, ``trust_odometry``;
    * ``"distributed-robust"`` -- :func:`~mmpgo_jax._init.robust_distributed.distributed_robust_initialization`
      with ``robots`` (as for distributed-chordal; default min(10, n) contiguous robots): every
      robot's own GNC-chordal start, then the robots' frames from a robust solve of the frame
      hypotheses of their inter-robot closures (Kimera-Multi / dpgo's robust initialization);
      ``options``: ``scale``, ``quantile``, ``min_inliers``, ``frames``, ``map_sigma``, ``trust_odometry``;
    * ``"odometry"`` -- :func:`odometry_initialization`;
    * ``"vertices"`` -- the file's VERTEX estimates, given as ``initial``;
    * a :class:`Poses` -- used as given (shapes checked, rotations projected to SO(d));
    * a path (``str`` or ``os.PathLike``) to a ``.g2o`` file (its VERTEX lines) or an ``.npz``
      file with arrays ``R`` (n, d, d) and ``t`` (n, d), matched by vertex id (:func:`load_poses`;
      the graph's poses are taken to carry ids 0..n-1: pass ``Poses`` from :func:`load_poses` with
      ``vertex_ids`` otherwise).

    The chordal, odometry and distributed-chordal starts hold the fixed poses during their solves;
    the others get them set afterwards. ``host=True`` returns the poses as NumPy arrays (a
    :class:`~mmpgo_jax._core.pose_graph.HostPoses`), for host-side solvers: a given start is then
    checked without a round trip through the device.
    """
    return initialize_with_weights(graph, method, initial=initial, robots=robots, fixed=fixed, host=host,
                                   **options)[0]


def initialize_with_weights(graph: PoseGraph, method="chordal", *, initial: Poses | None = None, robots=None,
                            fixed: FixedPoses | None = None, host: bool = False, **options):
    """(poses, weights) of :func:`initialize`: ``weights`` (m,) in [0, 1] in the graph's edge order is
    the start's classification of the edges where it makes one (``"distributed-robust"``: the robots'
    own GNC on their edges, 1 on odometry, its acceptance of each inter-robot closure), None otherwise.
    A robust solve holds them as its first stage (:func:`~mmpgo_jax._mm.robust.next_weights`)."""
    poses, weights, _ = initial_classified(graph, method, initial=initial, robots=robots, fixed=fixed, host=host,
                                           **options)
    return poses, weights


def initial_classified(graph: PoseGraph, method="chordal", *, initial: Poses | None = None, robots=None,
                       fixed: FixedPoses | None = None, host: bool = False, **options):
    """(poses, weights, info) of :func:`initialize_with_weights`: for the distributed robust start
    ``info`` = dict(variance_factor=the local maps' variance factor); None for the other starts."""
    if fixed is not None:
        fixed.check(graph.num_poses, graph.dim)
    poses, weights, info = _initial_poses(graph, method, initial, robots, fixed, options, host)
    if host and not isinstance(poses, HostPoses):
        poses = HostPoses(np.asarray(poses.R), np.asarray(poses.t))
    return (poses if fixed is None else fixed.apply(poses)), weights, info


def _initial_poses(graph, method, initial, robots, fixed, options, host=False):
    """(poses, weights or None, info or None): only the distributed robust start classifies the
    edges (info: its maps' ``variance_factor``, and with its team check ``team_check``: the closures
    dropped, the rounds, and the check's chordal solves and their CG iterations); the distributed
    chordal start reports its stages
    (info: ``distributed_chordal``, CG iterations per stage and how Gamma was applied)."""
    if isinstance(method, str) and method == "distributed-robust":
        from .robust_distributed import distributed_robust_initialization

        start = distributed_robust_initialization(
            graph, min(10, graph.num_poses) if robots is None else robots, **options)
        if start.unplaced_robots.size:
            warnings.warn(f"distributed-robust start: robots {start.unplaced_robots.tolist()} share no accepted "
                          "inter-robot loop closure with robot 0's map; they stay in their own frames",
                          stacklevel=5)
        poses = start.poses if fixed is None else express_in_frame(start.poses, fixed)  # gauge: 1st fixed pose
        info = dict(variance_factor=start.variance_factor)
        if start.team_check is not None:
            check = start.team_check
            rotation, translation = check.cg_iterations.sum(axis=0).tolist()
            info["team_check"] = dict(removed=check.removed.tolist(), rounds=len(check.objective) - 1,
                                      solves=len(check.cg_iterations), rotation_iterations=rotation,
                                      translation_iterations=translation)
        return poses_from_arrays(graph, poses.R, poses.t, host=host), start.weights, info
    poses, info = _start_poses(graph, method, initial, robots, fixed, options, host)
    return poses, None, info


def _start_poses(graph, method, initial, robots, fixed, options, host=False):
    """(poses, info or None) of every start but the distributed robust one."""
    if isinstance(method, Poses):
        return poses_from_arrays(graph, method.R, method.t, host=host), None
    if isinstance(method, str) and method in INITIALIZATION_METHODS:
        if options and method not in _WITH_OPTIONS:
            raise ValueError(f"options {sorted(options)} only apply to {', '.join(map(repr, _WITH_OPTIONS))}")
        if method == "gnc-chordal":
            from .robust_start import gnc_chordal_initialization

            start = gnc_chordal_initialization(graph, fixed=fixed, **options)
            return poses_from_arrays(graph, start.poses.R, start.poses.t), None
        if method == "chordal":
            return chordal_initialization(graph, fixed), None
        if method == "odometry":
            return odometry_initialization(graph, fixed), None
        if method == "vertices":
            if initial is None:
                raise ValueError(
                    "method 'vertices' needs the file's VERTEX estimates (initial=...), but none were given"
                )
            return poses_from_arrays(graph, initial.R, initial.t, what="VERTEX estimates", host=host), None
        from .distributed_chordal import distributed_chordal_initialization

        if robots is None:
            robots = min(10, graph.num_poses)
        poses, info = distributed_chordal_initialization(graph, robots, fixed=fixed, **options)
        return poses, dict(distributed_chordal=dict(rotation_iterations=int(info.rotation_iterations),
                                                    translation_iterations=int(info.translation_iterations),
                                                    factorizations=list(info.factorizations)))
    if isinstance(method, (str, os.PathLike)):
        p = Path(method)
        if p.suffix.lower() in (".g2o", ".npz") or p.exists():
            return load_poses(graph, p), None
        raise ValueError(
            f"unknown initialization {method!r}: expected one of {', '.join(INITIALIZATION_METHODS)}, "
            "a Poses, or a path to a .g2o / .npz file"
        )
    raise ValueError(f"initialization must be a method name, a Poses or a path, got {type(method).__name__}")
