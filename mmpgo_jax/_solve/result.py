"""A solve's outcome (:class:`SolveResult`) and the frame results are reported in (:func:`output_frame`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .._core.gauge import FixedPoses, express_in_frame
from .._core.metrics import TrajectoryAccuracy
from .._core.partition import Partition
from .._core.pose_graph import Poses
from .._mm.driver import RESULTS, History, Termination
from .._mm.outer import MMConfig
from .._mm.robust import RobustLoss
from .._mm.solvers import Solver

__all__ = ["SolveResult", "output_frame"]


@dataclass(frozen=True)
class SolveResult:
    """A solve's outcome, in the spirit of optimistix's ``Solution(value, result, stats)``: the
    final poses (global order, in the requested frame), the history, why it stopped (``result``, a
    :class:`RESULTS`; ``stop_reason`` is its short name) and ``stats`` (timings in seconds:
    ``initialize_seconds`` (partition and start), ``build_seconds`` (Gamma, preconditioner, state at
    X^0), ``init_seconds`` (their sum), ``compile_seconds``, ``solve_seconds`` = the compiled
    iterations alone, whatever the layout; a sharded run adds its mesh size, plan and exchange). ``partition`` is the
    split the run used (one robot for the centralized Newton solver, built when first read)."""

    poses: Poses
    history: History
    _partition: Partition | Callable[[], Partition] = field(repr=False)
    config: MMConfig | None  # the MM/AMM settings (``solver.config``); None for the centralized Newton solver
    result: RESULTS
    stats: dict = field(default_factory=dict)
    accuracy: TrajectoryAccuracy | None = None  # against ``ground_truth`` when one was given
    termination: Termination | None = None
    loss: RobustLoss | None = None  # the robust loss (its numbers filled in), None for least squares
    weights: np.ndarray | None = None  # (m,) final edge weights (robust losses), graph edge order
    # (m,) bool: final residual within the scale (robust losses), False on ``prefiltered`` edges; with a
    # pre-filter and least squares it is ~prefiltered (None for least squares without one)
    inliers: np.ndarray | None = None
    start: Poses | None = None  # the start X^0 in the frame of ``poses`` (None for the centralized solver)
    solver: Solver | None = None  # the solver that ran (None for the centralized Newton solver)
    prefiltered: np.ndarray | None = None  # (m,) bool: edges a pre-filter (PCM) removed before the solve
    # (m,) the weights a robust run held as its first stage (given, or its start's classification of the
    # edges: the distributed robust start), graph edge order; None when it held none
    start_weights: np.ndarray | None = None

    @property
    def partition(self) -> Partition:
        if not isinstance(self._partition, Partition):  # built on first use
            object.__setattr__(self, "_partition", self._partition())
        return self._partition

    @property
    def f(self) -> float:
        return float(self.history.f[-1])

    @property
    def iterations(self) -> int:
        return self.history.iterations

    @property
    def stop_reason(self) -> str:
        return self.result.value

    @property
    def stop_description(self) -> str:
        """Why the run stopped, in words (e.g. "budget of 1000 iterations reached")."""
        return self.result.describe(self.termination) if self.termination is not None else self.result.value

    @property
    def init_seconds(self) -> float:
        return float(self.stats.get("init_seconds", 0.0))

    @property
    def initialize_seconds(self) -> float:
        return float(self.stats.get("initialize_seconds", 0.0))

    @property
    def build_seconds(self) -> float:
        return float(self.stats.get("build_seconds", 0.0))

    @property
    def compile_seconds(self) -> float:
        return float(self.stats.get("compile_seconds", 0.0))

    @property
    def solve_seconds(self) -> float:
        return float(self.stats.get("solve_seconds", 0.0))

    @property
    def extra(self) -> dict:
        """``stats`` (the name of earlier versions)."""
        return self.stats

    @property
    def ms_per_iteration(self) -> float:
        return 1e3 * self.solve_seconds / max(self.iterations, 1)

    @property
    def outliers(self) -> np.ndarray | None:
        """(m,) bool: the edges a robust run rejects (``~inliers``); None for least squares."""
        return None if self.inliers is None else ~self.inliers


def output_frame(poses: Poses, fixed: FixedPoses | None, frame) -> Poses:
    """The frame a result is reported in (see :func:`solve`)."""
    if isinstance(frame, str):
        if frame != "raw":
            raise ValueError(f"frame must be a FixedPoses, 'raw' or None, got {frame!r}")
        return poses
    if frame is None:
        if fixed is not None:
            return poses  # the fixed poses hold the gauge
        frame = FixedPoses.identity([0], poses.R.shape[-1])
    return express_in_frame(poses, frame)
