"""The repository's scripts (benchmarks/, notebooks/) loaded as modules, for the tests of their
helper functions (they are not part of the package, so they are loaded by path)."""

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load_script(relative: str):
    """The module of the script at ``relative`` (a path from the repository's root), executed fresh."""
    path = REPO / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
