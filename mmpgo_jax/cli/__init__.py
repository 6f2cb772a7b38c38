"""The ``mmpgo`` command line: ``info``, ``solve``, ``optimum``, ``demo``, ``bench`` and ``sweep``.

:mod:`.app` is the program (parser, ``main``); :mod:`.commands` holds one module per command;
:mod:`.errors`, :mod:`.options`, :mod:`.inputs`, :mod:`.outputs`, :mod:`.robots`,
:mod:`.devices` and :mod:`.progress` what the commands share. This package re-exports only
``main`` (the ``mmpgo`` script's entry point, ``mmpgo_jax.cli:main``)."""

from .app import main

__all__ = ["main"]
