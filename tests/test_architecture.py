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


# Loaded only by the commands or options that use them: `mmpgo solve` (one device, no --plot,
# --certify, --ground-truth, stderr not a terminal) must not import them.
_NOT_FOR_SOLVE = (
    "matplotlib", "tqdm", "scipy.integrate", "scipy.optimize", "scipy.special", "scipy.stats",
    "mmpgo_jax._distributed", "mmpgo_jax.sharding", "mmpgo_jax.plotting", "mmpgo_jax._experiments.plots",
    "mmpgo_jax._experiments.sweep", "mmpgo_jax._experiments.synthetic", "mmpgo_jax._experiments.certificate",
    "mmpgo_jax._init.distributed_chordal", "mmpgo_jax.cli.bench", "mmpgo_jax.cli.demo",
)


def _modules_after(argv: list[str], tmp_path) -> list[str]:
    """The modules a fresh process has loaded after ``mmpgo ARGV`` ran as the program (main with
    argv None, as the ``mmpgo`` script calls it), with its exit status checked."""
    code = ("import sys; sys.argv = ['mmpgo', *sys.argv[1:]]\n"
            "import mmpgo_jax.cli as cli\n"
            "rc = cli.main()\n"
            "print('MODULES', rc, ' '.join(sorted(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True,
                         cwd=tmp_path, stdin=subprocess.DEVNULL).stdout
    line = next(x for x in out.splitlines() if x.startswith("MODULES"))
    _, rc, *modules = line.split()
    assert rc == "0", out
    return modules


def test_solve_imports_only_the_solve_path(tmp_path):
    data = Path(__file__).parent / "data" / "fix2d.g2o"
    loaded = _modules_after(["solve", str(data), "--robots", "2", "--iterations", "3", "--chunk", "3",
                             "--no-compilation-cache", "--out", str(tmp_path / "out.g2o")], tmp_path)
    assert (tmp_path / "out.g2o").is_file()
    unwanted = [m for m in loaded if m.startswith(_NOT_FOR_SOLVE)]
    assert not unwanted, unwanted
    # ... while the modules it does use are there (the check above is not vacuous)
    for m in ("jax", "scipy.sparse", "mmpgo_jax._mm.solve", "mmpgo_jax._init.chordal", "mmpgo_jax._io.g2o"):
        assert m in loaded, m


def test_plot_option_loads_matplotlib_when_asked(tmp_path):
    """The lazy imports still load what an option needs (here --plot: matplotlib, the plots module)."""
    data = Path(__file__).parent / "data" / "fix2d.g2o"
    loaded = _modules_after(["solve", str(data), "--robots", "2", "--iterations", "3", "--chunk", "3",
                             "--no-compilation-cache", "--plot", str(tmp_path / "p.png")], tmp_path)
    assert (tmp_path / "p.png").stat().st_size > 0
    assert "matplotlib" in loaded and "mmpgo_jax._experiments.plots" in loaded


def test_import_is_lazy_but_complete():
    """``import mmpgo_jax`` loads none of the package's modules (nor JAX); every public name still
    resolves, to the object its module defines."""
    code = ("import sys, mmpgo_jax\n"
            "before = sorted(m for m in sys.modules if m.startswith(('mmpgo_jax.', 'jax', 'scipy')))\n"
            "names = {n: getattr(mmpgo_jax, n) for n in mmpgo_jax.__all__}\n"
            "from mmpgo_jax import solve, PoseGraph\n"
            "from mmpgo_jax._mm.solve import solve as s2\n"
            "assert solve is s2 and names['solve'] is s2 and PoseGraph.__module__.endswith('pose_graph')\n"
            "assert set(mmpgo_jax.__all__) <= set(dir(mmpgo_jax))\n"
            "print(' '.join(before))\n")
    before = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert before == [], before
