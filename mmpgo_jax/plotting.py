"""Plots of pose graphs and convergence (matplotlib; imported only when this module is).

``import mmpgo_jax.plotting`` gives :func:`plot_trajectory` (trajectories coloured by robot, loop
closures grey, inter-robot edges dashed black, 2D axes (a 3D graph's x-y top view) or 3D axes),
:func:`plot_convergence` (f − f* or (f − f*)/f* against iterations, log scale, the 1e-2 / 1e-3 /
1e-4 levels labelled), :func:`solve_figure` (start and result side by side with the gap) and the
writers used by the CLI, which write the format a file's extension names (:func:`check_figure_path`).
Kept out of ``mmpgo_jax/__init__`` so that importing the solver does not import matplotlib.
"""

from ._experiments.plots import (
    RELATIVE_FLOOR,
    check_figure_path,
    draw_trajectory,
    plot_convergence,
    plot_trajectory,
    robot_colors,
    save_convergence_figure,
    save_figure,
    save_solve_figure,
    solve_figure,
    solve_start,
)

__all__ = [
    "RELATIVE_FLOOR",
    "check_figure_path",
    "draw_trajectory",
    "plot_convergence",
    "plot_trajectory",
    "robot_colors",
    "save_convergence_figure",
    "save_figure",
    "save_solve_figure",
    "solve_figure",
    "solve_start",
]
