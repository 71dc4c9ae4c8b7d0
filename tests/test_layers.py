"""One-way layers: the core (``fr_torch/``) names neither the evaluation harness nor the baselines,
not even in a string; they plug in through entry points (``fr_torch/registry.py``).  Within
fr_torch and within the harness (fr_eval) a module imports only its own layer and those below, and
no modules of the whole tree import each other, directly or through others."""
import functools
import re
import subprocess
import sys
import tomllib

from fr_torch.core import ROOMS
from tests.conftest import REPO, checkout_env

# an import of, or a dotted module path into, the harness / baselines under their installed names
# (fr_eval, fr_baselines) or their folder names (eval, baselines): "fr_eval.protocols.run_eval", "baselines"
PACKAGE = r"(?:fr_)?(?:eval|baselines)"
FORBIDDEN = re.compile(rf"""(\bimport\s+{PACKAGE}\b|\bfrom\s+{PACKAGE}\b|["']{PACKAGE}(\.\w+)*[\"':])""")


def test_core_names_no_harness_or_baselines():
    offenders = []
    for path in sorted((REPO / "fr_torch").rglob("*.py")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if FORBIDDEN.search(line):
                offenders.append(f"{path.relative_to(REPO)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_harness_commands_are_declared_as_entry_points():
    text = (REPO / "pyproject.toml").read_text()
    from fr_eval.commands import COMMANDS

    for name, constant in (("eval", "EVAL"), ("train-reliability", "TRAIN_RELIABILITY")):
        assert f'{name} = "fr_eval.commands:{constant}"' in text
        assert name in COMMANDS
    assert 'lee2009 = "fr_baselines.lee2009:Lee2009"' in text  # baselines plug in like any package's methods


def test_unknown_command_prints_one_line():
    out = subprocess.run([sys.executable, "-m", "fr_torch.cli", "no-such-command"], capture_output=True, text=True,
                         cwd=REPO, timeout=120)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr


def test_forbidden_pattern_catches_both_names():
    for line in ("import fr_eval", "from fr_baselines.ctrlc import CTRLC", 'load("fr_eval.commands:EVAL")',
                 "from eval.metrics import x", '"baselines"', "'fr_baselines.lee2009:Lee2009'"):
        assert FORBIDDEN.search(line), line
    for line in ("evaluate = 1", "from .evaluation import x", '"fr eval --dataset yud"', "model.eval()"):
        assert not FORBIDDEN.search(line), line


def test_no_generic_top_level_packages():
    """The wheel installs the harness and baselines as fr_eval / fr_baselines (folders eval/, baselines/)."""
    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    top_level = {name.split(".")[0] for name in setuptools["packages"]}
    assert top_level == {"fr_torch", "fr_eval", "fr_baselines"}, top_level
    assert setuptools["package-dir"]["fr_eval"] == "eval" and setuptools["package-dir"]["fr_baselines"] == "baselines"


def test_every_package_folder_is_installed():
    """Every folder with an ``__init__.py`` under fr_torch/, eval/ and baselines/ is in the wheel's
    package list (a sub-package missing there imports in a checkout but not once installed)."""
    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {"fr_torch": REPO / "fr_torch", "fr_eval": REPO / "eval", "fr_baselines": REPO / "baselines"}
    found = {".".join((name, *init.parent.relative_to(folder).parts))
             for name, folder in folders.items() for init in folder.rglob("__init__.py")}
    assert found <= set(setuptools["packages"]), sorted(found - set(setuptools["packages"]))


def test_harness_commands_found_from_any_folder(tmp_path):
    """``fr`` (here ``python -m fr_torch.cli``) finds the harness commands from any working
    directory: the (editable) installation declares them as entry points of ``fr_eval``."""
    out = subprocess.run([sys.executable, "-m", "fr_torch.cli", "train-reliability", "--help"], capture_output=True,
                         text=True, cwd=tmp_path, env=checkout_env(), timeout=120)
    assert out.returncode == 0 and "--extra-synthetic" in out.stdout, out.stderr


# --------------------------------------------------------------------------- the module graph

#: Layers of fr_torch, lowest first: a module may import its own layer and those below it.
LAYERS = (
    {"errors", "resources", "registry", "output", "redaction"},  # infrastructure
    {"core"},  # the tensor engine
    {"images", "synthetic"},  # image files and arrays
    {"detectors"},  # line segments from images
    {"runtime"},  # FREstimator on images, pipelines, device policy
    {"batch", "video", "plugins"},  # applications of the runtime
    {"cli"},  # the fr command
)

#: Rooms of the engine fr_torch.core, lowest first, as the package declares them
#: (fr_torch/core/__init__.py, ROOMS): a module imports its own room and those below it.
CORE_ROOMS = tuple(set(room) for room in ROOMS)

#: Layers of the harness fr_eval (folder eval/), lowest first, by sub-package or top-level module.
HARNESS_LAYERS = (
    {"paths", "machine"},  # where the data lives, what machine a measurement ran on
    {"datasets", "scoring"},  # labelled samples (and their builders); errors, tables, figures
    {"protocols", "bench"},  # fr eval, leave one dataset out, training, studies; fr bench and speed
    {"commands", "__main__"},  # the harness's fr commands
)


@functools.cache
def _module_graph() -> dict[str, set[str]]:
    """``{module: modules it imports}`` for every module of fr_torch, eval (as fr_eval) and baselines
    (as fr_baselines), from every import statement (function-level and relative ones included).
    ``from package import name`` counts as an import of ``package.name`` when that is a module."""
    import ast

    roots = {"fr_torch": REPO / "fr_torch", "fr_eval": REPO / "eval", "fr_baselines": REPO / "baselines"}
    sources = {}
    for package, folder in roots.items():
        for path in folder.rglob("*.py"):
            parts = (package, *path.relative_to(folder).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            sources[".".join(parts[:-1] if is_package else parts)] = (path, is_package)

    def known(name: str) -> str | None:  # the module itself, else the longest module prefix
        while name and name not in sources:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for module, (path, is_package) in sources.items():
        here = module.split(".") if is_package else module.split(".")[:-1]  # the package of the module
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(here[: len(here) - node.level + 1] + ([base] if base else []))
                deps |= {f"{base}.{alias.name}" for alias in node.names} | {base}
            elif isinstance(node, ast.Import):
                deps |= {alias.name for alias in node.names}
        graph[module] = {known(d) for d in deps if d.split(".")[0] in roots and known(d)} - {module}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles_in_the_whole_tree():
    graph = _module_graph()
    assert len(graph) > 60
    assert _cycles(graph) == []


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _upward_imports(package: str, layers) -> list[str]:
    """Imports from a module of ``package`` into a higher layer of ``package``; every module must
    belong to a layer (by its first name below ``package``)."""
    rank = {name: level for level, names in enumerate(layers) for name in names}
    graph = _module_graph()

    def first_name(module: str) -> str:  # the module's first name below ``package``
        return module[len(package) + 1:].split(".")[0]

    unplaced = sorted(m for m in graph if m.startswith(package + ".") and first_name(m) not in rank)
    assert not unplaced, f"place these modules in a layer of tests/test_layers.py: {unplaced}"
    offenders = []
    for module, deps in graph.items():
        if not module.startswith(package + "."):
            continue
        here = rank[first_name(module)]
        for dep in deps:
            if dep.startswith(package + ".") and rank[first_name(dep)] > here:
                offenders.append(f"{module} imports {dep}")
    return sorted(offenders)


def test_fr_torch_layers_import_downwards_only():
    offenders = _upward_imports("fr_torch", LAYERS)
    assert not offenders, "\n".join(offenders)


def test_engine_rooms_import_downwards_only():
    offenders = _upward_imports("fr_torch.core", CORE_ROOMS)
    assert not offenders, "\n".join(offenders)


def test_engine_rooms_stay_small_and_say_what_they_hold():
    """Every engine file under 600 lines, no room of more than 8 files, and every room's docstring
    says what it holds and what it may import (fr_torch/core/__init__.py draws the rooms)."""
    core = REPO / "fr_torch" / "core"
    long_files = [f"{p.relative_to(REPO)}: {n}" for p in core.rglob("*.py")
                  if (n := len(p.read_text().splitlines())) > 600]
    assert not long_files, long_files
    rooms = [path for path in core.iterdir() if (path / "__init__.py").is_file()]
    assert {room.name for room in rooms} == set().union(*CORE_ROOMS[1:6])
    for room in rooms:
        files = [p for p in room.iterdir() if p.is_file() and p.suffix in (".py", ".c")]
        assert len(files) <= 8, (room.name, sorted(p.name for p in files))
        doc = (room / "__init__.py").read_text()
        assert doc.startswith('"""') and "May import" in doc, room.name


def test_harness_layers_import_downwards_only():
    offenders = _upward_imports("fr_eval", HARNESS_LAYERS)
    assert not offenders, "\n".join(offenders)


def test_harness_protocols_and_bench_do_not_import_each_other():
    """Layer 2 of the harness holds two independent applications: the evaluation protocols and the
    speed benchmarks; what both need sits below them."""
    offenders = [f"{module} imports {dep}" for module, deps in _module_graph().items() for dep in deps
                 for a, b in (("protocols", "bench"), ("bench", "protocols"))
                 if module.startswith(f"fr_eval.{a}.") and dep.startswith(f"fr_eval.{b}")]
    assert not offenders, "\n".join(sorted(offenders))


def test_relative_imports_are_in_the_graph():
    graph = _module_graph()
    assert "fr_baselines.vp_geometry" in graph["fr_baselines.lee2009"]  # from . import vp_geometry as vg
    assert "fr_eval.bench.detectors" in graph["fr_eval.bench.report"]  # from fr_eval.bench import detectors


def test_architecture_table_is_the_codes_own():
    """docs/architecture.md's room-to-room import table is what ``tools/engine_map.py`` reads from
    the code now (the same command redraws docs/engine.png)."""
    done = subprocess.run([sys.executable, str(REPO / "tools" / "engine_map.py"), "--check"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
