"""``python -m mmpgo_jax.cli``: the ``mmpgo`` command."""

import sys

from .app import main

sys.exit(main())
