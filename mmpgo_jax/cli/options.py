"""The options several commands share, and the argparse types that check every number when it is
parsed (range in the message, exit status 2): :func:`finite_float` is the library's
(:mod:`mmpgo_jax._core.validate`), so that the command line and the Python API word a range alike."""

from __future__ import annotations

import argparse

from .._core.validate import finite_float, int_in

__all__ = ["INT_MAX", "ITERATIONS", "ROBOTS", "add_common", "add_strict", "finite_float", "host_port", "int_in"]

INT_MAX = 2**31 - 1  # iteration counts end up in int32 arrays in float32 mode


def host_port(text: str) -> str:
    """argparse ``type``: ``HOST:PORT`` with a port between 1 and 65535."""
    host, sep, port = text.rpartition(":")
    ok = bool(sep and host.strip("[]") and port.isdigit() and 1 <= int(port) <= 65535)
    if not ok:
        raise argparse.ArgumentTypeError(f"must be HOST:PORT with PORT between 1 and 65535, got {text!r}")
    return text


ROBOTS = int_in(1)
ITERATIONS = int_in(0, INT_MAX)


def add_common(p: argparse.ArgumentParser) -> None:
    """--data, --precision and the compilation cache: every command has them (``main`` acts on them
    before the command runs)."""
    p.add_argument("--data", help="folder with benchmark g2o files (default: $MMPGO_DATA, else ../shared/datasets)")
    p.add_argument(
        "--precision",
        choices=("float64", "float32"),
        default="float64",
        help="floating-point precision (default float64, as the paper and SE-Sync)",
    )
    cache = p.add_mutually_exclusive_group()
    cache.add_argument("--compilation-cache", metavar="DIR",
                       help="folder of JAX's persistent compilation cache (default: $MMPGO_COMPILATION_CACHE, "
                            "else ~/.cache/mmpgo-jax/jax): a second run of the same shapes skips compilation")
    cache.add_argument("--no-compilation-cache", action="store_true",
                       help="compile afresh, write no cache (also: MMPGO_COMPILATION_CACHE=off)")
    p.add_argument("--compile-mode", choices=("auto", "fast", "optimized"), default=None,
                   help="XLA:CPU code generation: fast (compiles in ~0.7 s less, iterations 0-12%% slower), "
                        "optimized (XLA's default), auto (fast for programs of at most 20 000 padded pose "
                        "slots; the default, also set by $MMPGO_COMPILE_MODE)")


def add_pcm_options(group, what: str) -> None:
    """--pcm (``what``: the sentence after "remove the inter-robot loop closures that PCM finds
    inconsistent"), --pcm-confidence and --pcm-ties, of ``mmpgo solve`` and ``mmpgo sweep``."""
    group.add_argument("--pcm", action="store_true",
                       help="remove the inter-robot loop closures that PCM (pairwise consistency maximization) "
                            f"finds inconsistent {what}")
    group.add_argument("--pcm-confidence", metavar="Q", type=finite_float(0.0, strict=True, below=1.0),
                       default=None, help="chi-square quantile of PCM's pairwise test, in (0, 1) (default 0.99)")
    group.add_argument("--pcm-ties", choices=("break", "keep"), default=None,
                       help="where several largest consistent sets of a robot pair disagree: keep one (break, "
                            "the default, PCM as published) or the closures of each, for the solver to decide (keep)")


def pcm_prefilter(args):
    """The ``prefilter`` of ``--pcm`` / ``--pcm-confidence`` / ``--pcm-ties``: None without ``--pcm``
    (then a given ``--pcm-confidence`` or ``--pcm-ties`` is a one-line error), else a :class:`~mmpgo_jax.PCM`."""
    from .errors import CLIError

    given = {"confidence": getattr(args, "pcm_confidence", None), "ties": getattr(args, "pcm_ties", None)}
    given = {k: v for k, v in given.items() if v is not None}
    if not getattr(args, "pcm", False):
        if given:
            raise CLIError(f"--pcm-{next(iter(given))} applies with --pcm")
        return None
    from .._solve.prefilter import PCM

    return PCM(**given)


def add_strict(p: argparse.ArgumentParser) -> None:
    p.add_argument("--strict-information", action="store_true",
                   help="refuse information matrices that are not positive definite (default: warn and use "
                        "SE-Sync's isotropic weights)")
