"""One module per ``mmpgo`` command. Each has ``register(subparsers)``, which adds the command's
parser with ``set_defaults(run=...)``; :mod:`mmpgo_jax.cli.app` builds the program's parser from
them. A module imports only what its parser needs: the rest of a command is imported inside its
``run``, so that building the parser for one command loads none of the others' code."""
