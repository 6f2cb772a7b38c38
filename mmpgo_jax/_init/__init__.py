"""Initializations: centralized chordal and odometry, distributed chordal (Algorithm 3)."""
