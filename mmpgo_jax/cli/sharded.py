"""``python -m mmpgo_jax.sharding solve FILE [options]``: one process of a sharded solve (what
``mmpgo solve --processes P`` launches, and what each host of a multi-host run starts).

:mod:`mmpgo_jax.sharding` hands its command-line names over to this module (lazily: the library
never imports the command line), so they stay here: the solve options of :mod:`.devices` and the
sharded solve of :mod:`.sharded_solve`. It sits above :mod:`.app`, whose parser it reuses."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Sequence

from .devices import AUTO_THREAD_POSES, CHECKPOINT_EVERY, HEARTBEAT_TIMEOUT_S, add_cli_options, wants_sharding
from .sharded_solve import cli_solve, launcher_console

__all__ = ["AUTO_THREAD_POSES", "CHECKPOINT_EVERY", "HEARTBEAT_TIMEOUT_S", "add_cli_options", "build_parser",
           "cli_solve", "main", "wants_sharding"]


def build_parser():
    """``mmpgo``'s parser with the sharding options on ``solve`` (used by ``python -m``)."""
    from .app import build_parser as base

    parser = base()
    solve_parser = next(a for a in parser._subparsers._group_actions if hasattr(a, "choices")).choices["solve"]
    if not any(o in solve_parser._option_string_actions for o in ("--processes", "--coordinator")):
        add_cli_options(solve_parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m mmpgo_jax.sharding solve FILE [options]``: one process of a sharded solve."""
    from .errors import cli_warnings, exit_status, run_reported

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] != "solve":
        argv = ["solve", *argv]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, or a bad option (reported in one line)
        return exit_status(exc)
    if args.precision == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    from .._distributed.launcher import die_with_launcher

    die_with_launcher()
    console = launcher_console()

    def command():
        if console is None:
            return cli_solve(args, argv)
        # the progress bar and warnings on the launcher's terminal; errors (reported after this
        # block) and the runtime's messages stay in the stderr the launcher captures
        with contextlib.redirect_stderr(console):
            return cli_solve(args, argv)

    with cli_warnings():
        return run_reported(command)


if __name__ == "__main__":
    sys.exit(main())
