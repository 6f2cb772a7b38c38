"""The package's layers: each layer imports only the layers below it, no import cycles, and the
library never imports the CLI, plots or the launcher (``import mmpgo_jax`` stays light)."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mmpgo_jax"

# The layers, bottom to top (docs/architecture.md): a module imports only its own layer and those below.
TOP_LEVEL = ("mmpgo_jax", "mmpgo_jax.sharding", "mmpgo_jax.plotting")  # the public modules
LAYERS = ("_core", "_io", "_mm", "_init", "_robust", "_baselines", "_distributed", "_solve", "_experiments",
          "top-level", "cli")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Package modules imported by ``path`` at module level or inside functions (all of them).
    ``from P import a`` imports the module ``P.a`` when there is one, else (a name P defines, e.g.
    ``from .. import solve``, a lazy public name of the package's ``__init__``) P itself. A module's
    parent packages are imported before it; that alone is no edge."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    modules = {_module_name(p) for p in PACKAGE.rglob("*.py")}
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif (node.module or "").split(".")[0] == "mmpgo_jax":
                target = node.module
            else:
                continue
            submodules = {f"{target}.{a.name}" for a in node.names} & modules
            out.update(submodules)
            if len(submodules) < len(node.names):  # names of P itself, not only its submodules
                out.add(target)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("mmpgo_jax"))
    return {m for m in out if m in modules and m != name}


def _graph():
    return {_module_name(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def _layer(module: str) -> str:
    if module in TOP_LEVEL:
        return "top-level"
    part = module.split(".")[1]
    return part if part in LAYERS else f"unlisted ({part})"


# Documented exception: mmpgo_jax.sharding hands its command-line names (lazy __getattr__) and
# ``python -m mmpgo_jax.sharding`` (its __main__ block) over to mmpgo_jax.cli.sharded.
_ALLOWED_UPWARD = {("mmpgo_jax.sharding", "mmpgo_jax.cli.sharded")}


def test_layers_import_only_layers_below():
    rank = {layer: k for k, layer in enumerate(LAYERS)}
    violations, unlisted = [], set()
    for m, deps in sorted(_graph().items()):
        for d in sorted(deps):
            lm, ld = _layer(m), _layer(d)
            unlisted.update(x for x in (lm, ld) if x not in rank)
            if lm in rank and ld in rank and rank[ld] > rank[lm] and (m, d) not in _ALLOWED_UPWARD:
                violations.append(f"{m} -> {d} ({lm} imports {ld})")
    assert not unlisted, f"modules outside the documented layers: {sorted(unlisted)}"
    assert not violations, f"{len(violations)} imports of a higher layer:\n" + "\n".join(violations)


def test_no_import_cycles():
    """Explicit imports only (a module's parent package is imported before it, which is no edge);
    a module that imports names from its package's ``__init__`` which imports it back IS a cycle.
    The documented hand-over (``_ALLOWED_UPWARD``: lazy, only when its names are asked for) is left
    out, as it is of the layers: the command line uses ``mmpgo_jax.sharding`` like any library user."""
    graph = {m: {d for d in deps if (m, d) not in _ALLOWED_UPWARD} for m, deps in _graph().items()}
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
    "mmpgo_jax._init.distributed_chordal", "mmpgo_jax.cli.bench", "mmpgo_jax.cli.demo", "mmpgo_jax.cli.sharded",
    "mmpgo_jax.cli.sharded_solve",
)


def _defining_module(name: str) -> str:
    """The module that defines the public name ``mmpgo_jax.<name>`` (wherever the library keeps it)."""
    import mmpgo_jax

    return "mmpgo_jax" + mmpgo_jax._LAZY[name]


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
    not_for_solve = _NOT_FOR_SOLVE + tuple({_defining_module("sweep")} - {_defining_module("solve")})
    unwanted = [m for m in loaded if m.startswith(not_for_solve)]
    assert not unwanted, unwanted
    # ... while the modules it does use are there (the check above is not vacuous)
    for m in ("jax", "scipy.sparse", _defining_module("solve"), "mmpgo_jax._init.chordal",
              _defining_module("read_g2o"), "mmpgo_jax.cli.commands.solve"):
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
            "import importlib\n"
            "s2 = importlib.import_module(mmpgo_jax._LAZY['solve'], 'mmpgo_jax').solve\n"
            "assert solve is s2 and names['solve'] is s2 and PoseGraph.__module__.endswith('pose_graph')\n"
            "assert set(mmpgo_jax.__all__) <= set(dir(mmpgo_jax))\n"
            "print(' '.join(before))\n")
    before = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert before == [], before
