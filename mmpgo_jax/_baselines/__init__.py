"""Baselines the paper compares with: ``dgs`` (distributed Gauss–Seidel, Choudhary et al. 2017;
public as :func:`mmpgo_jax.dgs`)."""
