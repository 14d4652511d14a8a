"""Griffe extension for the API reference (mkdocs.yml, mkdocstrings' ``extensions``).

The docstrings document parameters that go together on one line, ``a, b: what they are``,
which Google style as griffe reads it does not know (it would warn that a parameter named
``a, b`` is not in the signature). Before a docstring is parsed, such a line becomes one
item per name with the same description, so that each name is still checked against the
signature.

Sphinx roles (``:class:`~a.b.C```, ``:meth:`.f```) become code spans (``C``, ``f``), as
Sphinx would show them, not the role's text.

It also keeps what a module imports out of its page, ``__all__`` or not: a package's
``__init__`` re-exports its classes, documented in the module that defines them.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_SECTIONS = re.compile(
    r"^\s*(args|arguments|params|parameters|other parameters|keyword args|keyword arguments)"
    r"\s*:\s*$",
    re.IGNORECASE,
)
_ROLE = re.compile(r":(?:py:)?(?:mod|class|meth|func|data|attr|exc|obj|const):`([~.]*)([^`]+)`")
_GROUPED = re.compile(r"^(\s+)([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)+)\s*:(.*)$")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def split_grouped(text: str) -> str:
    """``text`` with each grouped parameter item of its Args sections split by name."""
    lines = text.splitlines()
    out: list[str] = []
    i = 0
    header: int | None = None  # the indentation of the current Args header
    while i < len(lines):
        line = lines[i]
        if _SECTIONS.match(line):
            header = _indent(line)
            out.append(line)
            i += 1
            continue
        if header is not None and line.strip() and _indent(line) <= header:
            header = None
        match = _GROUPED.match(line) if header is not None else None
        if match is None:
            out.append(line)
            i += 1
            continue
        indent, names, first = match.groups()
        body = []
        i += 1
        while i < len(lines) and (not lines[i].strip() or _indent(lines[i]) > len(indent)):
            body.append(lines[i])
            i += 1
        trailing = []
        while body and not body[-1].strip():
            trailing.insert(0, body.pop())
        for name in (n.strip() for n in names.split(",")):
            out.extend([f"{indent}{name}:{first}", *body])
        out.extend(trailing)
    return "\n".join(out)


def _role(match: re.Match[str]) -> str:
    prefix, target = match.groups()
    return f"``{target.rpartition('.')[2] if '~' in prefix else target}``"


def plain_roles(text: str) -> str:
    """``text`` with each Sphinx cross-reference role a code span of its target."""
    return _ROLE.sub(_role, text)


class PlainDocstrings(griffe.Extension):
    """Splits ``a, b: ...`` parameter items and turns Sphinx roles into code spans before
    griffe parses the docstrings."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        docstring = obj.docstring
        if docstring is not None:
            docstring.value = plain_roles(split_grouped(docstring.value))


class NoReExports(griffe.Extension):
    """Marks every imported name (an alias) of a loaded package as not public."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        modules = [pkg]
        while modules:
            module = modules.pop()
            for member in module.members.values():
                if member.is_alias:
                    if not member.inherited:
                        member.public = False
                elif member.is_module:
                    modules.append(member)  # type: ignore[arg-type]
