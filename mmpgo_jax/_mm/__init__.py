"""The MM / AMM solvers: majorization, the robot subproblem, the outer loop, the driver, solve()."""
