"""mmpgo-jax: distributed pose graph optimization by majorization minimization, in JAX.

Public API (the private modules are implementation details):

* data: :class:`PoseGraph`, :class:`Poses`, :func:`read_g2o`, :func:`read_g2o_poses`, :func:`write_g2o`,
  :func:`write_tum`, :func:`find_benchmark`, :data:`BENCHMARKS`, :func:`cube_dataset`, :func:`grid_2d_dataset`
* objective: :func:`cost` (f = 2F), :func:`objective` (F), gradients, :func:`data_matrix`
* gauge: :class:`FixedPoses` (g2o FIX), :func:`express_in_frame`, :func:`output_frame`
* robots: :func:`partition`, :func:`split_robots` (blocks, METIS, random), :func:`contiguous_robots`,
  :func:`metis_robots`, :func:`random_robots`, :func:`partition_stats`
* multi-robot files: :func:`robots_from_symbols` (GTSAM symbol keys), :func:`read_robot_labels`,
  :func:`read_robot_folder` / :func:`write_robot_folder` (one g2o per robot), :func:`write_robot_tum`,
  :func:`symbol_keys`; TORO: :func:`read_toro`, :func:`write_toro`
* starts: :func:`initialize`, :func:`chordal_initialization`, :func:`distributed_chordal_initialization`
* robust losses (outlier loop closures): ``solve(..., loss=, loss_scale=, gnc=)``, :class:`RobustLoss`,
  :class:`GNCConfig`, :func:`chi2_scale`, :data:`LOSSES`, the kernels :func:`loss_rho` (rho(s)) and
  :func:`loss_weight` (the edge weight rho'(s)) of a kernel by name (or code, :func:`loss_code`), at scale c
* outlier experiments: :func:`add_outlier_loop_closures` (seeded wrong loop closures, a
  :class:`CorruptedGraph`), :func:`outlier_scores` (precision / recall of rejected edges, :class:`OutlierScores`)
* baselines: :class:`DGS` (distributed Gauss–Seidel, the paper's DGS column, a solver of :func:`solve`) and
  :func:`dgs` (both of its stages, a :class:`DGSResult`); :class:`RBCD` (RBCD / RBCD++, lifted ranks with
  rounding) and :func:`rbcd_poses_sent` (its poses sent per iteration)
* consistency pre-filter: :func:`pcm_filter` (PCM: the maximum pairwise-consistent set of inter-robot loop
  closures per robot pair, a :class:`PCMResult`); :func:`readmit_loop_closures` (rejected loop closures
  re-admitted greedily while the robust objective falls, a :class:`Readmission`; ``solve(..., readmit=True)``),
  :func:`noise_level` (the a-posteriori variance factor: the data's noise against their information, a
  :class:`NoiseLevel`)
* solvers: :func:`solve` (one path: a :class:`Solver` — :class:`AMM`, :class:`MM` —, a start, a
  :class:`Termination`, a layout — :class:`OneDevice`, ``mmpgo_jax.sharding.Sharded``), :func:`centralized_optimum`,
  :func:`certify` (global optimality check), and the jittable core :class:`MMConfig`, :class:`MMProblem`,
  :func:`init_state`, :func:`run`, :func:`step`, :class:`SubproblemConfig`
* sweeps and accuracy: :func:`sweep`, :class:`SweepResult`, :func:`reference_optimum`,
  :func:`trajectory_accuracy`, :func:`absolute_trajectory_error`, :func:`relative_pose_error`,
  :func:`align_poses`
* every CPU core: :func:`use_cpu_cores` (before the first JAX computation; ``solve`` then splits the robots
  of large graphs over the cores)
* sharding over devices and processes: :mod:`mmpgo_jax.sharding` (``solve_sharded``)
* plots (imports matplotlib): :mod:`mmpgo_jax.plotting`
* precision: :func:`enable_float64`; compilation: :func:`enable_compilation_cache` (JAX's persistent cache),
  :func:`set_compile_mode` (fast compile or fastest iterations)
"""

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names, eagerly, for type checkers and IDEs
    from ._baselines.dgs import DGS, DGSResult, dgs
    from ._baselines.rbcd import RBCD, rbcd_poses_sent
    from ._core.compilation_cache import enable_compilation_cache
    from ._core.compile_mode import set_compile_mode
    from ._core.gauge import FixedPoses, express_in_frame
    from ._core.geometry import project_to_so, quaternion_to_rotation, rotation_2d
    from ._core.metrics import (
        RelativePoseError,
        TrajectoryAccuracy,
        absolute_trajectory_error,
        align_poses,
        relative_pose_error,
        rigid_alignment,
        trajectory_accuracy,
    )
    from ._core.noise import NoiseLevel, noise_level
    from ._core.partition import (
        Partition,
        contiguous_robots,
        metis_robots,
        partition,
        partition_stats,
        random_robots,
        split_robots,
    )
    from ._core.pose_graph import (
        PoseGraph,
        Poses,
        connected_components,
        cost,
        data_matrix,
        edge_costs,
        euclidean_gradient,
        matrix_to_poses,
        objective,
        poses_to_matrix,
        riemannian_gradient,
        riemannian_gradient_norm,
    )
    from ._core.precision import default_float_dtype, enable_float64, float64_enabled
    from ._experiments.certificate import OptimalityCertificate, certificate_matrix, certify
    from ._experiments.outliers import CorruptedGraph, OutlierScores, add_outlier_loop_closures, outlier_scores
    from ._experiments.sweep import SweepResult, reference_optimum, sweep
    from ._experiments.synthetic import (
        RobotTeamDataset,
        SyntheticDataset,
        cube_dataset,
        grid_2d_dataset,
        robot_team_dataset,
    )
    from ._init.chordal import (
        chordal_initialization,
        load_poses,
        odometry_initialization,
    )
    from ._init.distributed_chordal import distributed_chordal_initialization
    from ._init.start import initialize
    from ._io.datasets import (
        BENCHMARKS,
        DatasetNotFoundError,
        FStarReference,
        available_benchmarks,
        benchmark_info,
        data_dir,
        find_benchmark,
    )
    from ._io.g2o import (
        G2OFile,
        G2OFormatError,
        G2OPoses,
        G2OWarning,
        read_g2o,
        read_g2o_poses,
        read_toro,
        write_g2o,
        write_toro,
        write_tum,
    )
    from ._io.multi_robot import (
        read_robot_folder,
        read_robot_labels,
        robots_from_symbols,
        symbol_keys,
        write_robot_folder,
        write_robot_tum,
    )
    from ._mm.driver import RESULTS, History, Monitor, NonFiniteError, Termination
    from ._mm.layouts import OneDevice
    from ._mm.outer import MMConfig, MMProblem, MMState, init_state, run, step
    from ._mm.robust import LOSSES, GNCConfig, RobustLoss, chi2_scale, loss_code, loss_rho, loss_weight
    from ._mm.solvers import AMM, MM, Solver
    from ._mm.subproblem import SubproblemConfig
    from ._robust.pcm import PCMResult, pcm_filter
    from ._robust.readmit import Readmission, readmit_loop_closures
    from ._solve.build import NamedStart
    from ._solve.devices import use_cpu_cores
    from ._solve.prefilter import PCM
    from ._solve.result import SolveResult, output_frame
    from ._solve.solve import centralized_optimum, solve

_LAZY = {  # public name -> the private module that defines it (imported on first use)
    "enable_compilation_cache": "._core.compilation_cache",
    "set_compile_mode": "._core.compile_mode",
    "FixedPoses": "._core.gauge",
    "NoiseLevel": "._core.noise",
    "noise_level": "._core.noise",
    "express_in_frame": "._core.gauge",
    "project_to_so": "._core.geometry",
    "quaternion_to_rotation": "._core.geometry",
    "rotation_2d": "._core.geometry",
    "Partition": "._core.partition",
    "contiguous_robots": "._core.partition",
    "metis_robots": "._core.partition",
    "partition": "._core.partition",
    "partition_stats": "._core.partition",
    "random_robots": "._core.partition",
    "split_robots": "._core.partition",
    "PoseGraph": "._core.pose_graph",
    "Poses": "._core.pose_graph",
    "connected_components": "._core.pose_graph",
    "cost": "._core.pose_graph",
    "data_matrix": "._core.pose_graph",
    "edge_costs": "._core.pose_graph",
    "euclidean_gradient": "._core.pose_graph",
    "matrix_to_poses": "._core.pose_graph",
    "objective": "._core.pose_graph",
    "poses_to_matrix": "._core.pose_graph",
    "riemannian_gradient": "._core.pose_graph",
    "riemannian_gradient_norm": "._core.pose_graph",
    "default_float_dtype": "._core.precision",
    "enable_float64": "._core.precision",
    "float64_enabled": "._core.precision",
    "OptimalityCertificate": "._experiments.certificate",
    "certificate_matrix": "._experiments.certificate",
    "certify": "._experiments.certificate",
    "RelativePoseError": "._core.metrics",
    "TrajectoryAccuracy": "._core.metrics",
    "absolute_trajectory_error": "._core.metrics",
    "align_poses": "._core.metrics",
    "relative_pose_error": "._core.metrics",
    "rigid_alignment": "._core.metrics",
    "trajectory_accuracy": "._core.metrics",
    "CorruptedGraph": "._experiments.outliers",
    "OutlierScores": "._experiments.outliers",
    "PCMResult": "._robust.pcm",
    "Readmission": "._robust.readmit",
    "readmit_loop_closures": "._robust.readmit",
    "DGS": "._baselines.dgs",
    "DGSResult": "._baselines.dgs",
    "dgs": "._baselines.dgs",
    "RBCD": "._baselines.rbcd",
    "rbcd_poses_sent": "._baselines.rbcd",
    "pcm_filter": "._robust.pcm",
    "add_outlier_loop_closures": "._experiments.outliers",
    "outlier_scores": "._experiments.outliers",
    "SweepResult": "._experiments.sweep",
    "reference_optimum": "._experiments.sweep",
    "sweep": "._experiments.sweep",
    "SyntheticDataset": "._experiments.synthetic",
    "cube_dataset": "._experiments.synthetic",
    "robot_team_dataset": "._experiments.synthetic",
    "RobotTeamDataset": "._experiments.synthetic",
    "PCM": "._solve.prefilter",
    "NamedStart": "._solve.build",
    "grid_2d_dataset": "._experiments.synthetic",
    "chordal_initialization": "._init.chordal",
    "initialize": "._init.start",
    "load_poses": "._init.chordal",
    "odometry_initialization": "._init.chordal",
    "distributed_chordal_initialization": "._init.distributed_chordal",
    "BENCHMARKS": "._io.datasets",
    "DatasetNotFoundError": "._io.datasets",
    "FStarReference": "._io.datasets",
    "available_benchmarks": "._io.datasets",
    "benchmark_info": "._io.datasets",
    "data_dir": "._io.datasets",
    "find_benchmark": "._io.datasets",
    "G2OFile": "._io.g2o",
    "G2OFormatError": "._io.g2o",
    "G2OPoses": "._io.g2o",
    "G2OWarning": "._io.g2o",
    "read_g2o": "._io.g2o",
    "read_g2o_poses": "._io.g2o",
    "read_toro": "._io.g2o",
    "write_g2o": "._io.g2o",
    "write_toro": "._io.g2o",
    "write_tum": "._io.g2o",
    "read_robot_folder": "._io.multi_robot",
    "read_robot_labels": "._io.multi_robot",
    "robots_from_symbols": "._io.multi_robot",
    "symbol_keys": "._io.multi_robot",
    "write_robot_folder": "._io.multi_robot",
    "write_robot_tum": "._io.multi_robot",
    "Monitor": "._mm.driver",
    "RESULTS": "._mm.driver",
    "Termination": "._mm.driver",
    "MMConfig": "._mm.outer",
    "MMProblem": "._mm.outer",
    "MMState": "._mm.outer",
    "init_state": "._mm.outer",
    "run": "._mm.outer",
    "step": "._mm.outer",
    "GNCConfig": "._mm.robust",
    "LOSSES": "._mm.robust",
    "RobustLoss": "._mm.robust",
    "chi2_scale": "._mm.robust",
    "loss_code": "._mm.robust",
    "loss_rho": "._mm.robust",
    "loss_weight": "._mm.robust",
    "OneDevice": "._mm.layouts",
    "AMM": "._mm.solvers",
    "MM": "._mm.solvers",
    "Solver": "._mm.solvers",
    "History": "._mm.driver",
    "NonFiniteError": "._mm.driver",
    "SolveResult": "._solve.result",
    "output_frame": "._solve.result",
    "centralized_optimum": "._solve.solve",
    "solve": "._solve.solve",
    "use_cpu_cores": "._solve.devices",
    "SubproblemConfig": "._mm.subproblem",
}


def __getattr__(name: str):
    """The public names are imported on first use: ``import mmpgo_jax`` loads no module of the package
    (and hence neither JAX nor SciPy) until one is asked for, so that a program, e.g. ``mmpgo solve``,
    pays only for the modules it uses."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value  # the next look-up is an ordinary attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__version__ = "0.1.0"

__all__ = [
    "AMM",
    "BENCHMARKS",
    "DGS",
    "LOSSES",
    "MM",
    "PCM",
    "RBCD",
    "RESULTS",
    "CorruptedGraph",
    "DGSResult",
    "DatasetNotFoundError",
    "FStarReference",
    "FixedPoses",
    "G2OFile",
    "G2OFormatError",
    "G2OPoses",
    "G2OWarning",
    "GNCConfig",
    "History",
    "MMConfig",
    "MMProblem",
    "MMState",
    "Monitor",
    "NamedStart",
    "NoiseLevel",
    "NonFiniteError",
    "OneDevice",
    "OptimalityCertificate",
    "OutlierScores",
    "PCMResult",
    "Partition",
    "PoseGraph",
    "Poses",
    "Readmission",
    "RelativePoseError",
    "RobotTeamDataset",
    "RobustLoss",
    "SolveResult",
    "Solver",
    "SubproblemConfig",
    "SweepResult",
    "SyntheticDataset",
    "Termination",
    "TrajectoryAccuracy",
    "absolute_trajectory_error",
    "add_outlier_loop_closures",
    "align_poses",
    "available_benchmarks",
    "benchmark_info",
    "centralized_optimum",
    "certificate_matrix",
    "certify",
    "chi2_scale",
    "chordal_initialization",
    "connected_components",
    "contiguous_robots",
    "cost",
    "cube_dataset",
    "data_dir",
    "data_matrix",
    "default_float_dtype",
    "dgs",
    "distributed_chordal_initialization",
    "edge_costs",
    "enable_compilation_cache",
    "enable_float64",
    "euclidean_gradient",
    "express_in_frame",
    "find_benchmark",
    "float64_enabled",
    "grid_2d_dataset",
    "init_state",
    "initialize",
    "load_poses",
    "loss_code",
    "loss_rho",
    "loss_weight",
    "matrix_to_poses",
    "metis_robots",
    "noise_level",
    "objective",
    "odometry_initialization",
    "outlier_scores",
    "output_frame",
    "partition",
    "partition_stats",
    "pcm_filter",
    "poses_to_matrix",
    "project_to_so",
    "quaternion_to_rotation",
    "random_robots",
    "rbcd_poses_sent",
    "read_g2o",
    "read_g2o_poses",
    "read_robot_folder",
    "read_robot_labels",
    "read_toro",
    "readmit_loop_closures",
    "reference_optimum",
    "relative_pose_error",
    "riemannian_gradient",
    "riemannian_gradient_norm",
    "rigid_alignment",
    "robot_team_dataset",
    "robots_from_symbols",
    "rotation_2d",
    "run",
    "set_compile_mode",
    "solve",
    "split_robots",
    "step",
    "sweep",
    "symbol_keys",
    "trajectory_accuracy",
    "use_cpu_cores",
    "write_g2o",
    "write_robot_folder",
    "write_robot_tum",
    "write_toro",
    "write_tum",
]
