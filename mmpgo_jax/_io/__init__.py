"""Input and output: g2o files, atomic writes, the benchmark registry."""
