"""The Python API reference (docs/reference/python-api.md) shows docstrings as a reader reads
them: the Sphinx roles srl's docstrings name code with become inline code
(tools/docs/griffe_roles.py, loaded by mkdocs.yml), and every object the page names exists."""

from __future__ import annotations

import re
from pathlib import Path

import griffe
import pytest

from tools.docs.griffe_roles import ROLE, SphinxRoles, plain

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "reference" / "python-api.md"
# griffe asks git for the repository's root (its source links): a process, so not the fast tier
pytestmark = pytest.mark.integration
IDENTIFIERS = re.findall(r"^::: (\S+)$", PAGE.read_text(), flags=re.MULTILINE)


def test_a_role_becomes_inline_code_and_its_short_form_the_last_name() -> None:
    assert plain("see :func:`common.math.critic.at_rest` and :class:`~common.math.actor.StackedActor`.") == (
        "see `common.math.critic.at_rest` and `StackedActor`."
    )
    assert plain(":meth:`step`, :mod:`a.b`, :data:`X`, :attr:`y`, :exc:`E`, :obj:`o`") == (
        "`step`, `a.b`, `X`, `y`, `E`, `o`"
    )
    untouched = "``code`` and `code`, a :term: and :func: alone"
    assert plain(untouched) == untouched


def test_mkdocs_loads_the_extension() -> None:
    assert "tools/docs/griffe_roles.py:SphinxRoles" in (ROOT / "mkdocs.yml").read_text()


def docstrings(obj: griffe.Object | griffe.Alias) -> list[str]:
    """The docstrings of ``obj`` and its public members, as the reference renders them."""
    found = [obj.docstring.value] if obj.docstring is not None else []
    for name, member in obj.members.items():
        if not name.startswith("_") and not member.is_alias and member.docstring is not None:
            found.append(member.docstring.value)
    return found


@pytest.mark.parametrize("identifier", IDENTIFIERS)
def test_each_object_of_the_page_renders_without_a_raw_role(identifier: str) -> None:
    module, _, name = identifier.rpartition(".")
    with_roles = griffe.load(module, search_paths=[str(ROOT)], allow_inspection=False)[name]
    rendered = griffe.load(
        module, search_paths=[str(ROOT)], allow_inspection=False, extensions=griffe.load_extensions(SphinxRoles)
    )[name]
    assert docstrings(rendered), f"{identifier} has no docstring"
    assert not [d for d in docstrings(rendered) if ROLE.search(d)], identifier
    # the negative control: what the extension mends is there without it (or the page's object has none)
    assert len(docstrings(with_roles)) == len(docstrings(rendered))


def test_the_page_names_objects_whose_docstrings_had_roles() -> None:
    """The extension is needed: some of the page's objects' docstrings name code with a role."""
    raw = []
    for identifier in IDENTIFIERS:
        module, _, name = identifier.rpartition(".")
        raw += docstrings(griffe.load(module, search_paths=[str(ROOT)], allow_inspection=False)[name])
    assert IDENTIFIERS and any(ROLE.search(d) for d in raw)
