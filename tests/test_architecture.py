"""The package's layers: no import cycles, and the library never imports the CLI, plots or the
launcher (``import mmpgo_jax`` stays light)."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mmpgo_jax"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Package modules imported by ``path`` at module level or inside functions (all of them)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = package.split(".")
            base = base[: len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
            names = [target] if node.module else [f"{target}.{a.name}" for a in node.names]
            out.update(names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("mmpgo_jax"))
    modules = {_module_name(p) for p in PACKAGE.rglob("*.py")}
    return {m for m in out if m in modules and m != name}


def _graph():
    return {_module_name(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def test_no_import_cycles():
    graph = _graph()
    # a module's package __init__ is imported first; importing a parent package is not a cycle
    graph = {m: {d for d in deps if not m.startswith(d + ".")} for m, deps in graph.items()}
    state, stack = {}, []

    def visit(m):
        state[m] = "active"
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == "active":
                raise AssertionError("import cycle: " + " -> ".join([*stack[stack.index(d):], d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_library_does_not_import_the_cli():
    graph = _graph()
    for m, deps in graph.items():
        if m.startswith("mmpgo_jax.cli"):
            continue
        if m == "mmpgo_jax.sharding":  # only its lazy __getattr__ / __main__ hand over to mmpgo_jax.cli.sharded
            deps = {d for d in deps if not d.startswith("mmpgo_jax.cli")}
        assert not any(d.startswith("mmpgo_jax.cli") for d in deps), (m, sorted(deps))


def test_import_is_light():
    code = ("import sys, mmpgo_jax; print(' '.join(sorted(m for m in sys.modules "
            "if m.startswith(('mmpgo_jax', 'matplotlib', 'tqdm')))))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert not [m for m in loaded if m.startswith(("mmpgo_jax.cli", "matplotlib", "tqdm"))], loaded
    assert "mmpgo_jax._experiments.plots" not in loaded and "mmpgo_jax._distributed.launcher" not in loaded
    assert "mmpgo_jax.sharding" not in loaded
