"""``python -m mmpgo_jax.cli``: the ``mmpgo`` command."""

import sys

from . import main

sys.exit(main())
