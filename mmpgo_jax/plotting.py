"""Plots of pose graphs and convergence (matplotlib; imported only when this module is).

``import mmpgo_jax.plotting`` gives :func:`plot_trajectory` (trajectories coloured by robot,
inter-robot edges dashed, 2D top view or 3D axes), :func:`plot_convergence` (f − f* or
(f − f*)/f* against iterations, log scale) and the PNG writers used by the CLI. Kept out of
``mmpgo_jax/__init__`` so that importing the solver does not import matplotlib.
"""

from ._experiments.plots import (
    RELATIVE_FLOOR,
    plot_convergence,
    plot_trajectory,
    robot_colors,
    save_convergence_figure,
    save_solve_figure,
)

__all__ = [
    "RELATIVE_FLOOR",
    "plot_convergence",
    "plot_trajectory",
    "robot_colors",
    "save_convergence_figure",
    "save_solve_figure",
]
