"""The documentation cannot rot silently: the site builds with warnings as errors, every relative
link of the README and the Markdown pages points to an existing file, the README stays a short
front door, and every ``--option`` the pages show exists in the code.

Fast and light: nothing here imports torch; the site's API reference is read from the docstrings
by griffe (static analysis) in a ``mkdocs`` subprocess.
"""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
README_MAX_BYTES = 12_000

# Markdown files whose relative links must resolve: the README, the site's pages, the decision log.
LINKED_FILES = [README, *sorted((REPO / "docs").rglob("*.md")), *sorted((REPO / "results").glob("DECISIONS.md")),
                *sorted((REPO / "results" / "decisions").glob("*.md"))]

FENCED_BLOCK = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")
# Options of other tools that the pages show (mkdocs, pip, ray, argparse's --help).
OTHER_TOOLS_OPTIONS = {"--help", "--strict", "--head", "--no-deps", "--no-build-isolation"}


def relative_links(markdown: str) -> list[str]:
    """Targets of the Markdown links and images of ``markdown`` that are relative paths (code blocks
    and inline code excluded; URLs, ``mailto:`` and in-page ``#anchors`` skipped)."""
    text = INLINE_CODE.sub("", FENCED_BLOCK.sub("", markdown))
    targets = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("#"):
            continue
        targets.append(target)
    return targets


def test_relative_links_helper():
    text = ("[a](docs/x.md) [b](https://e.org) [c](#top) ![d](img.png \"t\") `[e](no.md)`\n"
            "```\n[f](no.md)\n```\n[g](../y.md#part)")
    assert relative_links(text) == ["docs/x.md", "img.png", "../y.md#part"]


def test_readme_is_a_short_front_door():
    size = README.stat().st_size
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes (limit {README_MAX_BYTES}): move detail to docs/"


@pytest.mark.parametrize("path", LINKED_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_point_to_existing_files(path: Path):
    broken = []
    for target in relative_links(path.read_text(encoding="utf-8")):
        file_part = target.split("#", 1)[0].split("?", 1)[0]
        if file_part and not (path.parent / file_part).exists():
            broken.append(target)
    assert not broken, f"{path.relative_to(REPO)}: links to missing files: {broken}"


def test_documented_options_exist():
    """Every ``--option`` in the README and the pages is declared somewhere in the code (as the
    string literal argparse, or a script such as eval/reproduce.sh, is given), so a renamed or removed
    option cannot stay documented."""
    declared = set()
    for folder in ("fr_torch", "eval", "baselines", "tools"):
        for source in [*(REPO / folder).rglob("*.py"), *(REPO / folder).rglob("*.sh")]:
            declared |= set(re.findall(r"""["'](--[a-z][a-z0-9-]*)["'=]""", source.read_text(encoding="utf-8")))
    missing = {}
    for path in [README, *sorted((REPO / "docs").rglob("*.md"))]:
        unknown = set(OPTION.findall(path.read_text(encoding="utf-8"))) - declared - OTHER_TOOLS_OPTIONS
        if unknown:
            missing[str(path.relative_to(REPO))] = sorted(unknown)
    assert not missing, f"options documented but not declared in the code: {missing}"


def test_docs_site_builds_strict(tmp_path):
    needed = ("mkdocs", "mkdocstrings", "mkdocstrings_handlers.python")
    absent = [name for name in needed if importlib.util.find_spec(name.split(".")[0]) is None
              or importlib.util.find_spec(name) is None]
    if absent:
        pytest.skip(f"documentation tools not installed ({', '.join(absent)}): pip install -r requirements.txt")
    # cwd = the repository: mkdocs.yml's griffe paths and extension are relative to it.
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                           str(REPO / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    for page in ("index.html", "cli/index.html", "reference/core/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    reference = (tmp_path / "site" / "reference" / "runtime" / "index.html").read_text(encoding="utf-8")
    assert "FREstimator" in reference and "calibrate_images" in reference  # docstrings were rendered
    assert ":class:`" not in reference  # reST roles rendered as code (docs/griffe_rst_roles.py)
