"""Griffe extension for the API reference: the docstrings' Sphinx roles read as code (ADR 0048).

The code's docstrings are Google style with Sphinx cross-reference roles
(``:class:`~cellcal.devices.Frame```); mkdocstrings renders Markdown, where a role would show
as typed. Each becomes a code span: the last name with ``~``, else the target as written.
Doctest lines go into a ``pycon`` code block.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|attr|data|exc|obj|const|ref|term):"
                   r"`(?P<tilde>~?)(?P<target>[^`]+)`")


def plain_roles(text: str) -> str:
    """``:class:`~a.b.C``` -> ```C```; ``:func:`a.b``` -> ```a.b```; ``:meth:`.x``` -> ```x```."""

    def code(found: re.Match[str]) -> str:
        target = found["target"].strip()
        shown = re.match(r"^(.*?)\s*<(.+)>$", target)
        if shown:
            return f"`{shown[1]}`"
        target = target.lstrip(".")
        return f"`{target.rsplit('.', 1)[-1] if found['tilde'] else target}`"

    return _ROLE.sub(code, text)


def fenced_doctests(text: str) -> str:
    """Doctest lines (``>>> ...`` and what follows up to a blank line) in a ``pycon`` fence, as Markdown needs them.

    Google style's ``Example:`` section is prose, where ``>>>`` would read as quote marks.
    """
    out: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        prompt = re.match(r"^(\s*)>>> ", lines[i])
        if prompt is None:
            out.append(lines[i])
            i += 1
            continue
        indent = prompt[1]
        out.append(f"{indent}```pycon")
        while i < len(lines) and lines[i].strip():
            out.append(lines[i])
            i += 1
        out.append(f"{indent}```")
    return "\n".join(out)


class RstRoles(griffe.Extension):
    """Rewrites the roles and doctests of every docstring griffe loads."""

    def on_instance(self, *, node: Any, obj: griffe.Object, agent: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = fenced_doctests(plain_roles(obj.docstring.value))
