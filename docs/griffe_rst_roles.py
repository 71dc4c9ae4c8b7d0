"""Griffe extension for the docs build: renders the reST markup of the docstrings as Markdown.

The docstrings cross-reference with Sphinx roles (``:class:`~fr_torch.core.geometry.camera.Camera```) and open
literal blocks with ``::``.  MkDocs renders Markdown, so each role becomes inline code (``~`` keeps
the last dotted component, as Sphinx does) and a paragraph-ending ``::`` becomes ``:`` (the
indented block after it is already a Markdown code block).  Only the rendered text changes; the
source docstrings are read as they are.
"""
from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const|ref|term):`(~?)([^`]+)`")
_LITERAL_BLOCK = re.compile(r"(\S)::[ \t]*$", re.MULTILINE)


def _role_to_code(match: re.Match) -> str:
    tilde, target = match.groups()
    target = target.split("<")[-1].rstrip(">").strip()  # ":class:`text <target>`" -> target
    return f"`{target.split('.')[-1] if tilde else target}`"


def rst_to_markdown(text: str) -> str:
    """Sphinx roles -> inline code; a line-ending ``::`` -> ``:``."""
    return _LITERAL_BLOCK.sub(r"\1:", _ROLE.sub(_role_to_code, text))


class ReSTRoles(griffe.Extension):
    """Rewrites every docstring griffe loads with :func:`rst_to_markdown`."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value)
