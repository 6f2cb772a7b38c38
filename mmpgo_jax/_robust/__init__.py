"""Outlier rejection before the solve: pairwise consistency maximization (:mod:`.pcm`)."""
