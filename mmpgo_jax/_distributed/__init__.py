"""Robots sharded over devices and processes: collectives, plans, sharded solve, reports, launcher."""
