"""Robots sharded over devices (one host or several): ``solve_sharded``, traffic reports, launchers.

The robot axis of :class:`~mmpgo_jax.MMProblem` and :class:`~mmpgo_jax.MMState` is split over a
1-D device mesh with axis name ``"robots"``: device k holds a contiguous block of A / D robots.
The outer loop (``lax.scan`` over :func:`mmpgo_jax.step`) runs inside ``jax.shard_map``, so every
device runs the ``vmap``-ped subproblems of its own robots only, and the only communication of an
iteration is in :class:`MeshCollectives`:

* ``gather_poses``: by default (``exchange="halo"``) one ``all_to_all`` in which every device
  sends each other device exactly the poses that device's robots read (the ends of their
  cross-device edges), padded to a common halo size H (:func:`halo_plan`); with
  ``exchange="all_gather"`` every device receives ALL poses, padded slots included (see
  :func:`communication_report` for both volumes);
* ``sum``: ``psum`` of the robots' objective shares and gradient norms (two scalars);
* the per-robot restart flags of a chunk are ``all_gather``-ed once at its end (booleans).

Restart decisions of AMM (and the ``lax.cond`` that skips the MM fallback when no robot needs it)
stay per device. Per-robot arithmetic is unchanged, so a sharded run is the same MM / AMM run as
:func:`solve`, up to rounding: sums across devices are ordered differently, and XLA rounds a robot's
reductions differently when a device vmaps over fewer robots. The default truncated-CG subproblem
solver amplifies such 1e-16 differences (to ~1e-5 relative in f on the Cube data); with a
well-conditioned subproblem (large ``xi``) runs agree to ~1e-15 (``tests/test_sharding.py``).

Robots are assigned to devices in contiguous blocks of the robot index. For contiguous blocks of
poses (``robots=<count>``) the natural order already keeps neighbours together; for a user
robot-of-pose array the robots are renumbered (reverse Cuthill-McKee on the robot adjacency graph,
kept only if it lowers the cross-device edge count) and the result is mapped back. The robot
count is padded with empty robots to a multiple of the device count.

Several processes (one host or several): call :func:`initialize_distributed` first in every
process, then :func:`solve_sharded` with the same arguments everywhere: the mesh spans all
processes' devices, each process materializes only its own robots' arrays, and every process gets
the gathered result (write files from process 0 only). :func:`run_multiprocess` launches P local
CPU processes on a loopback coordinator; ``python -m mmpgo_jax.sharding <mmpgo solve arguments>
--coordinator HOST:PORT --num-processes P --process-id I`` is one process of such a run on any host.

A process that dies ends the run: :func:`run_multiprocess` stops the others as soon as one exits
with an error or a signal and says which one and how in one line (``ProcessRun.failure``); on
several hosts a process whose peer is gone fails in its next collective, and JAX's heartbeat
(``initialize_distributed(heartbeat_timeout_s=30)``) ends the others when a host stops answering
(docs/scaling.md). ``solve_sharded(..., checkpoint=FILE, resume=FILE)`` saves and continues long
runs as :func:`mmpgo_jax.solve` does.
"""


from ._distributed.collectives import AXIS, HaloCollectives, MeshCollectives, halo_plan
from ._distributed.launcher import (
    ProcessRun,
    free_port,
    initialize_distributed,
    run_multiprocess,
)
from ._distributed.layout import Sharded
from ._distributed.plan import ShardPlan, make_mesh, plan_shards
from ._distributed.report import CommunicationReport, communication_report
from ._solve.solve import solve_sharded

__all__ = [
    "AXIS",
    "CommunicationReport",
    "HaloCollectives",
    "MeshCollectives",
    "ProcessRun",
    "ShardPlan",
    "Sharded",
    "communication_report",
    "free_port",
    "halo_plan",
    "initialize_distributed",
    "make_mesh",
    "plan_shards",
    "run_multiprocess",
    "solve_sharded",
]

# The sharded command line lives in mmpgo_jax.cli.sharded; these names stay reachable here without
# importing the CLI when the library is imported.
_CLI_NAMES = ("add_cli_options", "build_parser", "cli_solve", "main", "wants_sharding")


def __getattr__(name):
    if name in _CLI_NAMES:
        from .cli import sharded

        return getattr(sharded, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if __name__ == "__main__":  # python -m mmpgo_jax.sharding solve FILE ... (one process of a sharded run)
    import sys

    from .cli.sharded import main

    sys.exit(main())
