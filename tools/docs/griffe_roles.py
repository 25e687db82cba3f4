"""A Griffe extension for the Python API reference (mkdocs.yml loads it into mkdocstrings).

srl's docstrings follow one convention: Google-style sections (``Args:``, ``Returns:``) where a
function needs them, and code named with Sphinx's roles (``:func:`name```, ``:class:`name```,
``:meth:`` ``:mod:`` ``:data:`` ``:attr:`` ``:exc:`` ``:obj:``), as Python's own docs do.
mkdocstrings renders a docstring as Markdown, where a role would show raw: this extension turns
each into inline code before it is rendered (``~a.b.c``, Sphinx's short form, shows ``c``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:func|class|meth|mod|data|attr|exc|obj):`(~?)([^`]+)`")


def plain(text: str) -> str:
    """``text`` with every Sphinx role made inline code: ``:func:`~a.b``` -> ```b```."""
    return ROLE.sub(lambda m: f"`{m.group(2).rsplit('.', 1)[-1] if m.group(1) else m.group(2)}`", text)


class SphinxRoles(griffe.Extension):
    """Every loaded object's docstring with its roles made inline code (:func:`plain`)."""

    def on_object(self, *, obj: griffe.Object, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain(obj.docstring.value)
