"""Shared by tests of dimension-generic code: ``@each_dim`` runs a test once per rotation group,
with its argument ``d`` = 2 (SO(2)) and 3 (SO(3)); ``so(d)`` gives the group's class."""

import pytest

DIMS = (2, 3)

each_dim = pytest.mark.parametrize("d", DIMS, ids=[f"SO{d}" for d in DIMS])
