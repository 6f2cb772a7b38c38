"""The FILE argument of a command: which file it names, the graph read from it, and that graph
made ready to solve (:class:`LoadedInput`: component, FIX poses, frame, robots, start), with the
solver's keyword arguments of ``mmpgo solve``'s options. Shared by the commands and the sharded
solve, so it imports none of them.

FILE is a path when it has a directory part, starts with ``~`` or ``.``, or exists; a path is
never replaced by a benchmark of the same name. Only a bare name (``MITb``, ``city``, a file name
absent from the working directory) is looked up in the data folder, and the command then prints
``using PATH (benchmark NAME)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import CLIError
from .options import pcm_prefilter
from .robots import read_input, robot_split

SOLVE_STARTS = ("chordal", "distributed-chordal", "distributed-robust", "gnc-chordal", "vertices", "odometry")
OPTIMUM_STARTS = ("chordal", "vertices", "odometry")
#: what ``--distributed`` refuses: the option and value, and why it is centralized
CENTRALIZED_OPTIONS = {
    ("init", "chordal"): "the start 'chordal' gathers the whole graph in one place; use --init distributed-chordal",
    ("init", "gnc-chordal"): "the start 'gnc-chordal' gathers the whole graph in one place; use --init "
                             "distributed-robust (each robot's own GNC, then the frames between robots)",
    ("init", "odometry"): "the start 'odometry' composes a spanning tree of the whole graph in one place; use --init "
                          "distributed-chordal",
    ("certify", True): "--certify checks the dual certificate of the whole graph in one place",
    ("robots_from", "metis"): "--robots-from metis partitions the whole graph in one place; use blocks or the "
                              "robots of the data (symbols, labels, files)",
    ("readmit", True): "--readmit re-solves the kept edges with Newton of the whole graph in one place",
}


def resolve_file(name: str, data: str | None, *, announce: bool = True) -> Path:
    """The g2o file of a FILE argument (see :func:`~mmpgo_jax.find_benchmark`: a path
    is only a path; a bare name is looked up in the data folder). ``announce``: print ``using
    PATH (benchmark NAME)`` when the data folder supplied the file."""
    from .._io.datasets import benchmark_info, find_benchmark, names_a_path
    from .._io.multi_robot import robot_files

    folder = Path(name).expanduser()
    if names_a_path(name) and folder.is_dir() and robot_files(folder):
        return folder  # one g2o file per robot
    path = find_benchmark(name, data)
    if announce and not names_a_path(name):
        info = benchmark_info(name)
        print(f"using {path} ({f'benchmark {info.name}' if info is not None else 'from the data folder'})", flush=True)
    return path


def describe_components(graph, vertex_ids=None) -> tuple[list[np.ndarray], str]:
    """The connected components of ``graph`` (largest first) and a line saying how it is connected."""
    from .._core.pose_graph import connected_components

    comps = connected_components(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))
    if len(comps) == 1:
        return comps, "connected"
    ids = np.arange(graph.num_poses) if vertex_ids is None else np.asarray(vertex_ids)
    parts = ", ".join(f"{len(c)} poses (vertex ids {ids[c[0]]}..{ids[c[-1]]})" for c in comps[:5])
    more = f", and {len(comps) - 5} more" if len(comps) > 5 else ""
    return comps, f"NOT connected: {len(comps)} components: {parts}{more}"


@dataclass(frozen=True, eq=False)
class LoadedInput:
    """The FILE of ``solve`` / ``optimum``, ready to solve: the graph (its largest component with
    --largest-component), the original ids and information, the VERTEX estimates, the FIX poses and
    the frame results are written in (the FIX pose, else the first pose at its VERTEX value)."""

    path: Path
    g2o: object  # the G2OFile as read
    keep: np.ndarray | None  # the poses kept (--largest-component), None: all
    graph: object
    vertex_ids: np.ndarray
    information: np.ndarray
    initial: object
    fixed: object  # FixedPoses | None
    frame: object  # FixedPoses
    components: list
    robot_of_pose: np.ndarray | None = None  # the split the options ask for (None: not resolved)
    robot_names: list | None = None
    robots_label: str = ""

    @property
    def fixed_mask(self) -> np.ndarray:
        return np.zeros(self.graph.num_poses, bool) if self.fixed is None else self.fixed.mask(self.graph.num_poses)

    def poses_file(self, file, what: str):
        """Poses of a --init / --ground-truth file, matched to this graph by vertex id."""
        from .._core.pose_graph import Poses
        from .._init.chordal import load_poses

        full = load_poses(self.g2o.graph, file, vertex_ids=self.g2o.vertex_ids, what=what)
        return full if self.keep is None else Poses(full.R[self.keep], full.t[self.keep])

    def start(self, init: str | None, methods: tuple[str, ...]):
        """``init`` for the solver: a method name, several joined by commas (a run from each, the
        lowest objective kept), the poses of a file, or None (the solver's default)."""
        if init is None or init in methods:
            return init
        names = init.split(",")
        if len(names) > 1 and not Path(init).is_file():
            unknown = [name for name in names if name not in methods]
            if unknown:
                raise CLIError(f"--init {init!r}: {unknown[0]!r} is not a known start ({', '.join(methods)})")
            return tuple(names)
        if not Path(init).is_file():
            raise CLIError(f"--init {init!r}: not a known method ({', '.join(methods)}) nor a file")
        return self.poses_file(init, "--init file")


def _team_checked(init, robust: dict):
    """``--team-check``: the distributed robust start among the starts, with its check
    (``NamedStart("distributed-robust", {"team_check": True})``); by default (no --init) with a robust
    loss the default's two starts, or the distributed robust start alone with --distributed (where the
    check is on by default; ``--no-team-check`` turns it off there)."""
    from .._solve.build import ROBUST_STARTS, NamedStart

    if "loss" not in robust:
        raise CLIError("--team-check checks the distributed robust start of a robust --loss: give one "
                       "(e.g. --loss tls)")
    if init is None:
        init = "distributed-robust" if robust.get("distributed") else ROBUST_STARTS
    names = (init,) if isinstance(init, str) else init
    if not isinstance(names, tuple) or "distributed-robust" not in names:
        raise CLIError("--team-check applies to the distributed robust start: give --init distributed-robust "
                       "(or --distributed, or no --init)")
    checked = tuple(NamedStart(n, {"team_check": True}) if n == "distributed-robust" else n for n in names)
    return checked[0] if len(checked) == 1 else checked


def _largest_component(g2o, comp: np.ndarray):
    """A G2OFile's graph, information and VERTEX estimates restricted to the poses ``comp``."""
    from .._core.pose_graph import PoseGraph, Poses

    g = g2o.graph
    new_index = np.full(g.num_poses, -1)
    new_index[comp] = np.arange(len(comp))
    keep = new_index[np.asarray(g.i)] >= 0
    sub = PoseGraph.from_arrays(
        new_index[np.asarray(g.i)[keep]],
        new_index[np.asarray(g.j)[keep]],
        np.asarray(g.R)[keep],
        np.asarray(g.t)[keep],
        np.asarray(g.kappa)[keep],
        np.asarray(g.tau)[keep],
        len(comp),
        dtype=np.asarray(g.kappa).dtype,
    )
    initial = None
    if g2o.initial is not None:
        initial = Poses(g2o.initial.R[comp], g2o.initial.t[comp])
    return sub, g2o.information[keep], initial


def load_for_solve(args, *, announce: bool = True) -> LoadedInput:
    """The :class:`LoadedInput` of ``args.file``; refuses a disconnected graph unless
    ``--largest-component``. ``announce``: print the component note."""
    from .._core.gauge import FixedPoses

    path = resolve_file(args.file, args.data, announce=False)
    g2o = read_input(path, args)
    comps, conn = describe_components(g2o.graph, g2o.vertex_ids)
    splits = hasattr(args, "robots_from")  # solve: the robots; optimum: one robot
    if len(comps) == 1:
        robots = robot_split(args, g2o) if splits else (None, None, "")
        return LoadedInput(path, g2o, None, g2o.graph, g2o.vertex_ids, g2o.information, g2o.initial,
                           g2o.fixed_poses, g2o.frame, comps, *robots)
    if not args.largest_component:
        raise CLIError(
            f"{path}: the pose graph is {conn}. Each component is only determined up to its own "
            "rigid transform, so the problem is ill-posed; pass --largest-component to solve the "
            "largest one (the others are left out of the result)."
        )
    keep = np.asarray(comps[0])
    graph, information, initial = _largest_component(g2o, keep)
    fixed = None if g2o.fixed_poses is None else g2o.fixed_poses.restrict(keep)
    frame = fixed or FixedPoses([0], g2o.vertex_R[keep[:1]], g2o.vertex_t[keep[:1]])
    if announce:
        from .progress import write_line

        write_line(f"note: solving the largest component only ({graph.num_poses} of {g2o.graph.num_poses} poses)")
    robots = robot_split(args, g2o, graph, keep) if splits else (None, None, "")
    return LoadedInput(path, g2o, keep, graph, g2o.vertex_ids[keep], information, initial, fixed, frame, comps,
                       *robots)


def reference_fstar(data: LoadedInput):
    """The f* that gaps of a solve of ``data`` are measured against (the registry's
    :attr:`~mmpgo_jax.BenchmarkInfo.fstar_reference`: certified where it can be), or None for a
    file that is not a benchmark or a problem it does not describe (a part of the graph)."""
    from .._io.datasets import benchmark_info

    info = benchmark_info(data.path.name)
    if info is None or data.keep is not None or info.num_poses != data.graph.num_poses:
        return None
    return info.fstar_reference


def check_solve_flags(args) -> None:
    """Refuse, before anything is read, the option combinations that cannot run: ``--xi`` /
    ``--restart`` / a robust ``--loss`` with a method that does not take them, and of ``--pcm`` and
    ``--distributed``: a centralized step under ``--distributed`` (one line naming the option)."""
    check_method_flags(args)
    pcm_prefilter(args)  # --pcm-confidence without --pcm: one line
    if not getattr(args, "distributed", False):
        return
    for (attr, value), why in CENTRALIZED_OPTIONS.items():
        given = getattr(args, attr, None)
        if value in (given.split(",") if attr == "init" and isinstance(given, str) else [given]):
            raise CLIError(f"--distributed: {why}")


def check_method_flags(args) -> None:
    """``--xi`` (mm, amm), ``--restart`` (amm) and a robust ``--loss`` (mm, amm) refused, in one line,
    with a ``--method`` that does not take them."""
    from .._solve.methods import MAJORIZATION

    method = getattr(args, "method", "amm")
    if getattr(args, "xi", None) is not None and method not in MAJORIZATION:
        raise CLIError(f"--xi applies to --method mm and amm, not {method} (a proximal term of MM)")
    if getattr(args, "restart", None) is not None and method != "amm":
        raise CLIError(f"--restart applies to --method amm, not {method} (a restart rule of AMM's momentum)")
    loss = getattr(args, "loss", "l2")
    if loss != "l2" and method not in MAJORIZATION:
        raise CLIError(f"--loss {loss}: --method {method} minimises the least-squares F only (robust losses run "
                       "with --method mm or amm)")


def solve_options(args, data: LoadedInput) -> dict:
    """The keyword arguments of ``solve`` / ``solve_sharded`` from ``mmpgo solve``'s options (the
    start resolved, FIX poses and the input's frame; the robots are ``data.robot_of_pose``)."""
    from .._mm.robust import GNCConfig
    from .devices import checkpoint_options

    robust = {} if getattr(args, "loss", "l2") == "l2" else dict(loss=args.loss, loss_scale=args.loss_scale)
    if robust and getattr(args, "gnc", False):
        robust["gnc"] = GNCConfig()
    # the methods' own defaults where not given (--xi and --restart only with the methods that take them)
    shortcuts = {k: getattr(args, k) for k in ("xi", "restart") if getattr(args, k) is not None}
    check_solve_flags(args)
    if (prefilter := pcm_prefilter(args)) is not None:
        robust["prefilter"] = prefilter
    if getattr(args, "distributed", False):
        robust["distributed"] = True
    if getattr(args, "readmit", False):
        if "loss" not in robust:
            raise CLIError("--readmit re-admits loop closures a robust --loss rejected: give one (e.g. --loss tls)")
        robust["readmit"] = True
    init = data.start(args.init, SOLVE_STARTS)
    team_check = getattr(args, "team_check", None)
    if team_check:
        init = _team_checked(init, robust)
    elif team_check is False and init is None and robust.get("distributed") and "loss" in robust:
        init = "distributed-robust"  # --distributed's default start, without its check
    return dict(method=args.method, iterations=args.iterations, init=init,
                initial=data.initial, chunk_size=args.chunk, grad_tol=args.grad_tol,
                stop_when_stalled=not args.all_iterations, fixed=data.fixed, frame=data.frame, **shortcuts,
                **robust, **checkpoint_options(args))
