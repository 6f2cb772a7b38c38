"""``mmpgo demo``: MM-PGO vs AMM-PGO on a generated Cube dataset (no download needed).

Generates a Cube dataset (the paper's Section VIII.A model, :func:`~mmpgo_jax.cube_dataset`)
with a lattice sized so that the walk fills it, computes the reference optimum f* with the
centralized solver (:func:`~mmpgo_jax.centralized_optimum`), runs MM-PGO and AMM-PGO from
the centralized chordal initialization, prints a summary and writes into ``--out-dir``:

* ``demo_trajectory.png``: the AMM-PGO estimate coloured by robot, and its convergence;
* ``demo_convergence.png``: MM-PGO vs AMM-PGO, f − f* and (f − f*)/f*;
* ``demo_result.g2o``: the AMM-PGO estimate (VERTEX lines) with the generated edges;
* ``demo_history.csv``: f and ||grad F|| per iteration for both methods.

The absolute trajectory error (ATE) is the RMSE of the positions after the rigid transform
(rotation + translation, no scale) that best aligns the estimate with the ground truth
(:func:`~mmpgo_jax.trajectory_accuracy`; the estimate is only determined up to a global rigid transform).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from .progress import progress_bar

__all__ = ["demo_grid", "run_demo"]

_TOLS = (1e-2, 1e-3, 1e-4)
# cap on the centralized reference solve (it usually stops at its gradient tolerance far earlier)
_FSTAR_MAX_ITERATIONS = 1000


def demo_grid(num_poses: int) -> int:
    """Lattice size so that a walk of ``num_poses`` poses fills the cube: about 3 poses per vertex.

    (grid + 1)^3 ≈ n / 3 → 6 for 1000 poses, 4 for 300, 10 for 3600 (the paper uses 12 for 3600,
    a sparser cube).
    """
    return max(1, round((num_poses / 3.0) ** (1.0 / 3.0)) - 1)


def _iters_to(history, fstar: float, tol: float):
    return history.first_below(fstar + tol * abs(fstar))


def _fmt_iters(k) -> str:
    return "—" if k is None else str(k)


def run_demo(args) -> int:
    from .. import centralized_optimum, solve
    from .._core.metrics import align_poses, trajectory_accuracy
    from .._core.pose_graph import cost
    from .._core.precision import float64_enabled
    from .._experiments.certificate import certify
    from .._experiments.plots import save_convergence_figure, save_solve_figure
    from .._experiments.synthetic import cube_dataset
    from .._init.start import initialize
    from .._io.atomic import atomic_write
    from .._io.datasets import FStarReference
    from .._io.g2o import write_g2o

    n, A, iters = int(args.poses), int(args.robots), int(args.iterations)
    if n < 2:
        raise ValueError(f"--poses must be at least 2, got {n}")
    if not 1 <= A <= n:
        raise ValueError(f"--robots must be between 1 and --poses ({n}), got {A}")
    if iters < 0:
        raise ValueError(f"--iterations must be >= 0, got {iters}")
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    no_progress = bool(getattr(args, "no_progress", False))
    t_start = time.perf_counter()

    grid = demo_grid(n)
    ds = cube_dataset(int(args.seed), num_poses=n, grid=grid)
    graph = ds.graph
    f_gt = float(cost(graph, ds.ground_truth))
    print(f"Cube dataset   seed {args.seed}: {n} poses on a {grid}x{grid}x{grid} lattice of 1 m cells, "
          f"{graph.num_edges} edges ({graph.num_edges - (n - 1)} loop closures)")
    print(f"noise          sigma_t = {ds.sigma_t:g} m, sigma_R = {ds.sigma_R:.4g} rad "
          f"(kappa = {ds.kappa:.6g}, tau = {ds.tau:.6g}); precision {graph.kappa.dtype}")
    print(f"ground truth   f = {f_gt:.6g} at the true poses (its expected value under the noise model the "
          f"data were drawn from: {ds.expected_ground_truth_cost():.6g})", flush=True)

    t = time.perf_counter()
    X0 = initialize(graph, "chordal")
    f0 = float(cost(graph, X0))
    t_init = time.perf_counter() - t
    print(f"chordal init   f = {f0:.6g} ({t_init:.1f} s)", flush=True)

    with progress_bar("f* (1 robot)", None, disable=no_progress, leave=False, show_gradient=True) as bar:
        ref = centralized_optimum(graph, init=X0, max_iterations=_FSTAR_MAX_ITERATIONS, monitor=bar)
    fstar = ref.f
    converged = ref.stop_reason == "grad_tol"
    t_ref = ref.init_seconds + ref.compile_seconds + ref.solve_seconds
    capped = "" if converged else (f"  (stopped at the {_FSTAR_MAX_ITERATIONS}-iteration cap before "
                                   "||grad F|| <= 1e-6: gaps are relative to this value)")
    print(f"f*             {fstar:.10g} ({ref.iterations} iterations, ||grad F|| = {ref.history.grad_norm[-1]:.1e}, "
          f"{t_ref:.1f} s){capped}", flush=True)
    certificate = certify(graph, ref.poses) if converged and float64_enabled() else None
    if certificate is not None:
        print(f"certificate    {certificate.summary()}", flush=True)
    reference = FStarReference(fstar, "certified" if certificate is not None and certificate.certified
                               else "uncertified")

    results = {}
    for method in ("mm", "amm"):
        label = f"{method.upper()}-PGO"
        with progress_bar(f"{label} ({A} robots)", iters, disable=no_progress) as bar:
            results[label] = solve(graph, A, method=method, iterations=iters, init=X0,  # same-length
                                   chunk_size=25, monitor=bar, stop_when_stalled=False)  # histories side by side

    # summary ------------------------------------------------------------------------------
    accuracy = {label: trajectory_accuracy(est, ds.ground_truth)
                for label, est in [("chordal init", X0), ("f* solution", ref.poses),
                                   *((k, r.poses) for k, r in results.items())]}

    print()
    print(f"{iters} iterations, {A} robots, centralized chordal initialization; gaps relative to the "
          f"{reference.label} = {fstar:.10g}")
    hdr = (f"{'method':<9} {'f':>13} {'(f-f*)/f*':>10} {'|grad F|':>9} {'ms/it':>7} {'compile s':>9} "
           f"{'it→1e-2':>7} {'it→1e-3':>7} {'it→1e-4':>7}")
    print(hdr)
    print("-" * len(hdr))
    for label, r in results.items():
        h = r.history
        gap = (h.f[-1] - fstar) / abs(fstar)
        its = [_fmt_iters(_iters_to(h, fstar, tol)) for tol in _TOLS]
        print(f"{label:<9} {h.f[-1]:>13.8g} {gap:>10.2e} {h.grad_norm[-1]:>9.2e} {r.ms_per_iteration:>7.2f} "
              f"{r.compile_seconds:>9.2f} {its[0]:>7} {its[1]:>7} {its[2]:>7}")
    print("(it→tol: first iteration with (f - f*)/f* <= tol; — = not reached. compile s: each method is its own "
          "program, traced and compiled or, on a later run, loaded from the compilation cache: similar times "
          "for both are two programs of one size, not one program counted twice)")
    print()
    print("error vs ground truth after rigid alignment (rotation + translation, no scale):")
    print(f"{'estimate':<14} {'ATE RMSE [m]':>12} {'max [m]':>8} {'rot RMSE [deg]':>14} {'RPE [m]':>8} "
          f"{'RPE [deg]':>9}")
    for label, acc in accuracy.items():
        print(f"{label:<14} {acc.ate:>12.4f} {acc.ate_max:>8.4f} {acc.rotation_deg:>14.3f} "
              f"{acc.rpe_translation:>8.4f} {acc.rpe_rotation_deg:>9.3f}")
    if any(r.f < fstar for r in results.values()):
        print("note: a distributed run ended below the centralized f* (within its tolerance); "
              "its gap is shown as negative / at the floor of the plots")

    # outputs -------------------------------------------------------------------------------
    amm = results["AMM-PGO"]
    title = f"Cube dataset (seed {args.seed}, {n} poses, {graph.num_edges} edges), {A} robots"
    p_traj = out / "demo_trajectory.png"
    # plot the estimate in the ground truth's frame (it is only determined up to a rigid motion)
    shown = dataclasses.replace(amm, poses=align_poses(amm.poses, ds.ground_truth))
    save_solve_figure(p_traj, graph, shown, fstar=fstar, fstar_label=reference.label,
                      title=title + " — estimate aligned to the ground truth")
    p_conv = out / "demo_convergence.png"
    save_convergence_figure(p_conv, {k: r.history for k, r in results.items()}, fstar, title,
                            fstar_label=f"{reference.label} = {fstar:.10g}"
                                        + ("" if converged else " (centralized solve not converged)"))
    p_g2o = out / "demo_result.g2o"
    write_g2o(p_g2o, graph, amm.poses)
    p_csv = out / "demo_history.csv"
    mm_h, amm_h = results["MM-PGO"].history, amm.history
    with atomic_write(p_csv) as fh:
        fh.write("iteration,f_mm,grad_norm_mm,rel_gap_mm,f_amm,grad_norm_amm,rel_gap_amm,amm_restarts\n")
        for k in range(len(mm_h.f)):
            row = (mm_h.f[k], mm_h.grad_norm[k], (mm_h.f[k] - fstar) / abs(fstar),
                   amm_h.f[k], amm_h.grad_norm[k], (amm_h.f[k] - fstar) / abs(fstar))
            fh.write(f"{k}," + ",".join(repr(float(v)) for v in row)
                     + f",{int(np.asarray(amm_h.restarts[k]).sum())}\n")
    print()
    for p in (p_traj, p_conv, p_g2o, p_csv):
        print(f"wrote {p}")
    print(f"total {time.perf_counter() - t_start:.1f} s")
    return 0
