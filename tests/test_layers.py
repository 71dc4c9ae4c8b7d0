"""One-way layers: the core (``fr_torch/``) names neither the evaluation harness nor the baselines,
not even in a string; they plug in through entry points (``fr_torch/registry.py``)."""
import re
import subprocess
import sys

from tests.conftest import REPO

# an import of, or a dotted module path into, eval / baselines ("eval.run_eval", "baselines")
FORBIDDEN = re.compile(r"""(\bimport\s+(eval|baselines)\b|\bfrom\s+(eval|baselines)\b"""
                       r"""|["'](eval|baselines)(\.\w+)*["'])""")


def test_core_names_no_harness_or_baselines():
    offenders = []
    for path in sorted((REPO / "fr_torch").rglob("*.py")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if FORBIDDEN.search(line):
                offenders.append(f"{path.relative_to(REPO)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_harness_commands_are_declared_as_entry_points():
    text = (REPO / "pyproject.toml").read_text()
    from eval.commands import COMMANDS

    for name, constant in (("eval", "EVAL"), ("train-reliability", "TRAIN_RELIABILITY")):
        assert f'{name} = "eval.commands:{constant}"' in text
        assert name in COMMANDS
    assert 'lee2009 = "baselines.lee2009:Lee2009"' in text  # baselines plug in like any package's methods


def test_unknown_command_prints_one_line():
    out = subprocess.run([sys.executable, "-m", "fr_torch.cli", "no-such-command"], capture_output=True, text=True,
                         cwd=REPO, timeout=120)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr


def test_python_m_eval_runs_harness_commands_from_a_checkout():
    out = subprocess.run([sys.executable, "-m", "eval", "train-reliability", "--help"], capture_output=True, text=True,
                         cwd=REPO, timeout=120)
    assert out.returncode == 0 and "--extra-synthetic" in out.stdout, out.stderr
