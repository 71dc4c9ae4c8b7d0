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
