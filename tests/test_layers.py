"""One-way layers: the core (``fr_torch/``) names neither the evaluation harness nor the baselines,
not even in a string; they plug in through entry points (``fr_torch/registry.py``)."""
import re
import subprocess
import sys
import tomllib

from tests.conftest import REPO, checkout_env

# an import of, or a dotted module path into, the harness / baselines under their installed names
# (fr_eval, fr_baselines) or their folder names (eval, baselines): "fr_eval.run_eval", "baselines"
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


def test_harness_commands_found_from_any_folder(tmp_path):
    """``fr`` (here ``python -m fr_torch.cli``) finds the harness commands from any working
    directory: the (editable) installation declares them as entry points of ``fr_eval``."""
    out = subprocess.run([sys.executable, "-m", "fr_torch.cli", "train-reliability", "--help"], capture_output=True,
                         text=True, cwd=tmp_path, env=checkout_env(), timeout=120)
    assert out.returncode == 0 and "--extra-synthetic" in out.stdout, out.stderr


# --------------------------------------------------------------------------- the module graph

#: Layers of fr_torch, lowest first: a module may import its own layer and those below it.
LAYERS = (
    {"errors", "resources", "registry", "output"},  # infrastructure
    {"core"},  # the tensor engine
    {"images", "synthetic"},  # image files and arrays
    {"detectors"},  # line segments from images
    {"runtime"},  # FREstimator on images, pipelines, device policy
    {"batch", "video", "plugins"},  # applications of the runtime
    {"cli"},  # the fr command
)


def _module_graph() -> dict[str, set[str]]:
    """``{module: modules it imports}`` for every module of fr_torch, eval (as fr_eval) and baselines
    (as fr_baselines), from every import statement (function-level ones included)."""
    import ast

    roots = {"fr_torch": REPO / "fr_torch", "fr_eval": REPO / "eval", "fr_baselines": REPO / "baselines"}
    graph = {}
    for package, folder in roots.items():
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            module = ".".join((package, *parts))[: -len(".__init__")] if parts[-1] == "__init__" else \
                ".".join((package, *parts))
            deps = set()
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    deps.add(node.module)
                elif isinstance(node, ast.Import):
                    deps |= {alias.name for alias in node.names}
            graph[module] = {d for d in deps if d.split(".")[0] in roots and d != module}
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


def test_fr_torch_layers_import_downwards_only():
    rank = {name: level for level, names in enumerate(LAYERS) for name in names}
    offenders = []
    for module, deps in _module_graph().items():
        if not module.startswith("fr_torch.") or module == "fr_torch":
            continue
        here = rank[module.split(".")[1]]
        for dep in deps:
            if dep.startswith("fr_torch.") and rank[dep.split(".")[1]] > here:
                offenders.append(f"{module} imports {dep}")
    assert not offenders, "\n".join(sorted(offenders))
