"""The entry points: one solve path over solvers and layouts (``solve``, ``solve_sharded``, ``centralized_optimum``)."""
