"""``--robots-from``: how ``mmpgo`` splits a graph among robots, reads multi-robot inputs and
describes the split (README, "Multi-robot inputs"); the ``--tum-dir`` / ``--out-dir`` checks."""

from __future__ import annotations

import argparse
import contextlib
import os

import numpy as np

from .errors import CLIError

FILE_HELP = ("g2o file, TORO .graph file, folder with one g2o file per robot, or a benchmark name "
             "(e.g. MITb, city10000)")
ROBOT_SOURCES = ("blocks", "metis", "random", "symbols", "labels", "files")
DEFAULT_ROBOTS = 10  # --robots when not given


def add_robots_from(p: argparse.ArgumentParser, choices=ROBOT_SOURCES) -> None:
    """``--robots-from`` (and ``--labels``): how the graph is split among robots (README, "Multi-robot inputs")."""
    data = [c for c in choices if c in ("symbols", "labels", "files")]
    p.add_argument("--robots-from", choices=choices, default=None,
                   help="how to split the graph: blocks (contiguous blocks of poses, the paper's; default), metis "
                        "(METIS balanced parts), random (random balanced parts, seed 0) among --robots robots"
                        + ("; or the robots of the data: " + ", ".join(data) + " (GTSAM symbol keys, a --labels "
                           "file, one g2o file per robot in the folder FILE; default for a folder)" if data else ""))
    if "labels" in choices:
        p.add_argument("--labels", metavar="CSV",
                       help="label file, 'vertex_id,robot' per line (implies --robots-from labels)")


def read_input(path, args=None):
    """The graph of the FILE argument (a g2o file, a TORO ``.graph`` file, or a folder with one g2o
    file per robot), refusing indefinite information matrices with ``--strict-information``, with
    the robots of the data for ``--robots-from symbols / labels / files``."""
    from .._io.g2o import read_g2o, read_toro
    from .._io.multi_robot import read_robot_folder, read_robot_labels, robots_from_symbols

    strict = bool(getattr(args, "strict_information", False))
    how = robots_source(args, folder=os.path.isdir(path))
    if os.path.isdir(path):
        g2o = read_robot_folder(path, strict_information=strict)
    elif str(path).lower().endswith(".graph"):
        g2o = read_toro(path, strict_information=strict)
    else:
        g2o = read_g2o(path, strict_information=strict)
    if how == "symbols":
        g2o = robots_from_symbols(g2o)
    elif how == "labels":
        g2o = read_robot_labels(args.labels, g2o)
    elif how == "files" and not os.path.isdir(path):
        raise CLIError(f"--robots-from files: {path} is a file; give a folder with one g2o file per robot")
    return g2o


def robots_source(args, *, folder: bool = False) -> str:
    """``--robots-from``, checked against ``--labels`` and ``--robots``; the default is ``blocks``,
    ``files`` for a folder."""
    how = getattr(args, "robots_from", None)
    labels = getattr(args, "labels", None)
    if labels is not None and how not in (None, "labels"):
        raise CLIError(f"--labels goes with --robots-from labels, not --robots-from {how}")
    how = how or ("labels" if labels is not None else "files" if folder else "blocks")
    if how == "labels" and labels is None:
        raise CLIError("--robots-from labels needs --labels CSV (lines 'vertex_id,robot')")
    if how in ("symbols", "labels", "files") and getattr(args, "robots", None) is not None:
        raise CLIError(f"--robots applies to --robots-from blocks, metis or random; with --robots-from {how} "
                       "the robots come from the data")
    return how


def robot_split(args, g2o, graph=None, keep=None):
    """(robot of each pose, robot names, description) of the split ``args`` ask for, on ``graph``
    (default ``g2o.graph``; ``keep``: the poses of ``g2o`` that ``graph`` holds)."""
    from .._core.partition import split_robots

    graph = g2o.graph if graph is None else graph
    how = robots_source(args, folder=os.path.isdir(g2o.path or ""))
    if how in ("symbols", "labels", "files"):
        rop = np.asarray(g2o.robot_of_pose)
        names = np.asarray(g2o.robot_names)
        if keep is not None:  # robots without a pose in the kept component are left out
            used, rop = np.unique(rop[keep], return_inverse=True)
            names = names[used]
        return rop.reshape(-1), [str(x) for x in names], f"from {how}"
    A = DEFAULT_ROBOTS if getattr(args, "robots", None) is None else args.robots
    if not 1 <= A <= graph.num_poses:
        raise CLIError(f"--robots must be between 1 and the number of poses ({graph.num_poses}), got {A}")
    label = {"blocks": "contiguous blocks", "metis": "METIS parts", "random": "random balanced parts, seed 0"}[how]
    return split_robots(graph, how, A), [str(a) for a in range(A)], label


_OUTPUT_DIRS = (("tum_dir", "--tum-dir"), ("out_dir", "--out-dir"))


def check_output_dirs(args) -> None:
    """--tum-dir / --out-dir: an existing folder, or one that can be made in an existing, writable
    folder; not the same folder."""
    seen = {}
    for attr, flag in _OUTPUT_DIRS:
        value = getattr(args, attr, None)
        if value is None:
            continue
        if value == "":
            raise CLIError(f"{flag}: empty folder name")
        target = os.path.realpath(os.path.abspath(value))
        if os.path.exists(target) and not os.path.isdir(target):
            raise CLIError(f"{flag} {value}: not a folder")
        parent = target if os.path.isdir(target) else os.path.dirname(target)
        if not os.path.isdir(parent):
            raise CLIError(f"{flag} {value}: folder {os.path.dirname(value) or '.'!r} does not exist")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise CLIError(f"{flag} {value}: folder {parent!r} is not writable")
        if target in seen:
            raise CLIError(f"{seen[target]} and {flag} {value}: the same folder")
        seen[target] = f"{flag} {value}"


def print_robot_table(graph, rop, names, label: str, dtype) -> None:
    """Per robot: name, poses, own and inter-robot edges, poses (bytes) received and sent per
    iteration, neighbours."""
    from .._core.partition import partition_stats

    st = partition_stats(graph, rop)
    A = len(names)
    bpp = st.bytes_per_pose(dtype)
    print(f"\npartition   {A} robots ({label}), {st.total_inter_edges} inter-robot edges; per iteration "
          f"{int(st.sent_poses.sum())} poses exchanged, {int(st.sent_bytes(dtype).sum())} bytes "
          f"({np.dtype(dtype).name}, {bpp} bytes per pose)")
    width = max(5, *(len(x) for x in names))
    print(f"{'robot':>{width}} {'poses':>7} {'own edges':>10} {'inter edges':>12} {'receives':>9} {'bytes':>9} "
          f"{'sends':>7} {'bytes':>9}  neighbours")
    named = np.asarray(names)
    rows = [f"{names[a]:>{width}} {st.poses[a]:>7} {st.own_edges[a]:>10} {st.inter_edges[a]:>12} "
            f"{st.received_poses[a]:>9} {st.received_poses[a] * bpp:>9} {st.sent_poses[a]:>7} "
            f"{st.sent_poses[a] * bpp:>9}  {' '.join(named[st.neighbours[a]].tolist())}" for a in range(A)]
    print("\n".join(rows))


def print_symbol_hint(g2o) -> None:
    """A hint for ``mmpgo info`` when the vertex ids are GTSAM symbol keys."""
    from .._io.multi_robot import robots_from_symbols

    with contextlib.suppress(ValueError):
        names = robots_from_symbols(g2o).robot_names
        print(f"robots      the vertex ids are GTSAM symbol keys of {len(names)} robots ({', '.join(names)}): "
              "--robots-from symbols splits by them")
