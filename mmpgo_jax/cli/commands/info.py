"""``mmpgo info FILE``: describe a pose graph and its split among robots."""

from __future__ import annotations

from ..options import ROBOTS, add_common, add_strict
from ..robots import FILE_HELP, add_robots_from


def register(sub) -> None:
    p = sub.add_parser("info", help="describe a pose graph and its partition among robots")
    p.add_argument("file", help=FILE_HELP)
    p.add_argument("--robots", "-A", type=ROBOTS, default=None,
                   help="also describe the split among A robots (1 .. number of poses)")
    add_robots_from(p)
    add_strict(p)
    add_common(p)
    p.set_defaults(run=run)


def run(args) -> int:
    import numpy as np

    from ..errors import CLIError
    from ..inputs import describe_components, resolve_file
    from ..robots import DEFAULT_ROBOTS, print_robot_table, print_symbol_hint, read_input, robot_split

    path = resolve_file(args.file, args.data)
    g2o = read_input(path, args)
    g = g2o.graph
    if args.robots is not None and not 1 <= args.robots <= g.num_poses:
        raise CLIError(f"--robots must be between 1 and the number of poses ({g.num_poses}), got {args.robots}")
    kappa, tau = np.asarray(g.kappa), np.asarray(g.tau)
    _, conn = describe_components(g, g2o.vertex_ids)
    ids = g2o.vertex_ids
    print(f"file        {path}")
    print(f"dimension   d = {g.dim}")
    remapped = "" if ids[-1] == len(ids) - 1 and ids[0] == 0 else f"  (ids {ids[0]}..{ids[-1]}, remapped)"
    print(f"poses       n = {g.num_poses}" + remapped)
    print(f"edges       m = {g.num_edges}")
    print(f"kappa       {kappa.min():.6g} .. {kappa.max():.6g}")
    print(f"tau         {tau.min():.6g} .. {tau.max():.6g}")
    print(f"graph       {conn}")
    print(f"vertices    {int(g2o.has_vertex.sum())} VERTEX lines, {int(g2o.fixed.sum())} fixed")
    dtype = np.float32 if args.precision == "float32" else np.float64
    if args.robots or args.robots_from or args.labels or g2o.robot_names is not None:
        rop, names, label = robot_split(args, g2o)
        print_robot_table(g, rop, names, label, dtype)
    else:  # the split `mmpgo solve FILE` would run, so that info describes what solve does
        print_symbol_hint(g2o)
        if g.num_poses >= DEFAULT_ROBOTS:
            rop, names, label = robot_split(args, g2o)
            print_robot_table(g, rop, names, f"{label}, the default of mmpgo solve", dtype)
    return 0
