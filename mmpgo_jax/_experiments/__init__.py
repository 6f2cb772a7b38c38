"""Experiments on top of the solvers: sweeps, accuracy metrics, synthetic data, certificate, plots."""
