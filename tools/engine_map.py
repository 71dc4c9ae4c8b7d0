"""The engine's rooms drawn from the code's own imports: ``docs/engine.png`` and the table of
room-to-room imports in ``docs/architecture.md``.

``python tools/engine_map.py``: reads every module of ``fr_torch/core`` (static analysis: nothing
is imported), groups them by room (the rooms of ``fr_torch/core/__init__.py``, lowest first), and
writes the figure (one column per room in the order of the engine's stages, its modules inside
with their line counts, an arrow for every room that imports another, labelled with how many
imports) and the table between the ``engine-imports`` markers of ``docs/architecture.md``.
``--check``: exit 1 when the table in ``docs/architecture.md`` is not the one the code gives now
(``tests/test_layers.py`` runs it).
"""
from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter
from pathlib import Path

from fr_torch.core import ROOMS as CORE_ROOMS

REPO = Path(__file__).resolve().parents[1]
CORE = REPO / "fr_torch" / "core"
ARCHITECTURE = REPO / "docs" / "architecture.md"
FIGURE = REPO / "docs" / "engine.png"
BEGIN, END = "<!-- engine-imports: begin (python tools/engine_map.py) -->", "<!-- engine-imports: end -->"

#: The rooms in the order of the engine's stages, lowest first, by their label
#: (:data:`fr_torch.core.ROOMS`), and the room of each first name below ``fr_torch.core``.
ROOMS = tuple(room[0] for room in CORE_ROOMS)
ROOM_OF_NAME = {name: room[0] for room in CORE_ROOMS for name in room}


def room_of(module: str) -> str | None:
    """The room of a dotted module below ``fr_torch.core`` (``search.refine`` -> ``search``)."""
    return ROOM_OF_NAME.get(module.split(".")[0])


def modules() -> dict[str, Path]:
    """``{module below fr_torch.core: path}`` of every module but the packages' ``__init__``."""
    return {".".join(p.relative_to(CORE).with_suffix("").parts): p for p in sorted(CORE.rglob("*.py"))
            if p.name != "__init__.py"}


def imports(path: Path) -> list[str]:
    """The ``fr_torch.core`` modules ``path`` imports (absolute imports; the engine uses no others)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("fr_torch.core."):
            found.append(node.module.removeprefix("fr_torch.core."))
        elif isinstance(node, ast.ImportFrom) and node.module == "fr_torch.core":
            found += [alias.name for alias in node.names]
    return found


def room_edges() -> Counter:
    """``{(importing room, imported room): number of import statements}`` between different rooms."""
    edges = Counter()
    for module, path in modules().items():
        here = room_of(module)
        for target in imports(path):
            there = room_of(target)
            if there is not None and there != here:
                edges[(here, there)] += 1
    return edges


def table() -> str:
    """The markdown table of room-to-room imports (rows: the importing room)."""
    edges = room_edges()
    lines = ["| room | imports (statements) |", "| --- | --- |"]
    for room in ROOMS:
        targets = [f"{there} ({n})" for (here, there), n in sorted(edges.items(), key=lambda e: ROOMS.index(e[0][1]))
                   if here == room]
        lines.append(f"| {room} | {', '.join(targets) or '—'} |")
    return "\n".join(lines)


def with_table(text: str) -> str:
    head, _, rest = text.partition(BEGIN)
    _, _, tail = rest.partition(END)
    return f"{head}{BEGIN}\n{table()}\n{END}{tail}"


def draw(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

    members: dict[str, list[str]] = {room: [] for room in ROOMS}
    for module, file in modules().items():
        members[room_of(module)].append(f"{module.split('.')[-1]} ({len(file.read_text().splitlines())})")
    width, gap = 2.3, 0.5
    height = max(len(m) for m in members.values()) * 0.32 + 0.9
    fig, ax = plt.subplots(figsize=(len(ROOMS) * (width + gap) * 0.95, height + 1.6))
    centre = {}
    for i, room in enumerate(ROOMS):
        x = i * (width + gap)
        ax.add_patch(FancyBboxPatch((x, 0), width, height, boxstyle="round,pad=0.05", fc="#eef3fb", ec="#3b5b92"))
        ax.text(x + width / 2, height - 0.3, f"{i}. {room}", ha="center", va="center", weight="bold", fontsize=11)
        for j, name in enumerate(members[room]):
            ax.text(x + 0.15, height - 0.75 - 0.32 * j, name, ha="left", va="center", fontsize=8.5, family="monospace")
        centre[room] = x + width / 2
    for k, ((here, there), n) in enumerate(sorted(room_edges().items())):
        bend = -(0.25 + 0.05 * (k % 4))  # below the rooms (arrows run right to left)
        ax.add_patch(FancyArrowPatch((centre[here], -0.1), (centre[there], -0.1),
                                     connectionstyle=f"arc3,rad={bend}", arrowstyle="-|>", mutation_scale=9,
                                     lw=0.6 + 0.15 * min(n, 10), color="#777777", alpha=0.8))
    ax.text(0, height + 0.45, "fr_torch.core: rooms in the order of the engine's stages (lines per module); "
            "arrows: imports, from the importing room (all point left: downwards)", fontsize=9.5)
    ax.set_xlim(-0.3, len(ROOMS) * (width + gap))
    ax.set_ylim(-(len(ROOMS) * 0.62), height + 0.8)
    ax.axis("off")
    fig.savefig(path, dpi=110, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check docs/architecture.md's table")
    args = parser.parse_args()
    text = ARCHITECTURE.read_text()
    if args.check:
        if with_table(text) != text:
            print("docs/architecture.md's engine-imports table is stale: run python tools/engine_map.py",
                  file=sys.stderr)
            return 1
        return 0
    ARCHITECTURE.write_text(with_table(text))
    draw(FIGURE)
    print(f"wrote {FIGURE.relative_to(REPO)} and the table of {ARCHITECTURE.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
