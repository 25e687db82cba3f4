"""References that must not dangle: the files and anchors the code and the documentation cite.

Cited where: comments and docstrings of the Python code under common/, services/, tools/ and
tests/, and the text of README.md and docs/**/*.md. What is checked:

* a repository path (``common/math/actor.py``, ``docs/concepts.md``, ``tests/test_docs.py``) exists;
* a Markdown link's target (relative to its page) exists, and its ``#anchor`` is a heading (or an
  explicit id) of that page; an in-page ``(#anchor)`` is one of the page's own;
* an anchor cited after a page's path (the README's or a page of docs/) is a heading of that page;
* the code under common/, services/ and tools/ says nothing of issue numbers or DESIGN.md
  (history belongs in commits and CHANGELOG.md; DESIGN.md is not shipped).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
import unicodedata
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

CODE_DIRS = ("common", "services", "tools", "tests")
NO_HISTORY_DIRS = ("common", "services", "tools")
TOP_DIRS = ("common", "services", "tools", "tests", "docs", "docker", ".ci")
ROOT_FILES = ("README.md", "CHANGELOG.md", "mkdocs.yml", "pyproject.toml", "Dockerfile", "docker-compose.yml")
EXTENSIONS = r"(?:py|md|toml|yml|yaml|json|png|sh|txt|csv|npz|mcap|xml|cfg|ini|j2)"
# a path from the repository root: a top directory, then path characters, ending in a file name or a slash
_DIRS = "|".join(re.escape(d) for d in TOP_DIRS)
_FILES = "|".join(re.escape(f) for f in ROOT_FILES)
PATH = re.compile(
    rf"(?<![\w./@-])((?:{_DIRS})/(?:[\w.+-]+/)*(?:[\w+-]+\.{EXTENSIONS}\b|[\w+-]+/?)|(?:{_FILES}))(#[\w-]+)?"
)
LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HISTORY = re.compile(r"[Ii]ssue #?\d+")
PLACEHOLDER = re.compile(r"(^|/)([A-Z][A-Z_]*|x|X|N|name|NAME|<[^>]*>|\{[^}]*\}|\*+)(\.\w+)?(/|$)")


@dataclass(frozen=True)
class Finding:
    where: str  # file:line
    what: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"


# -- anchors ------------------------------------------------------------------------------------
def slugs(heading: str) -> set[str]:
    """The anchors a heading gets: MkDocs' (Python-Markdown toc) and GitHub's."""
    text = re.sub(r"`([^`]*)`", r"\1", heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading: its text
    text = re.sub(r"\{#([\w-]+)\}\s*$", "", text).strip()
    normal = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    mkdocs = re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", normal).strip().lower())
    github = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
    return {mkdocs, github}


def anchors_of(path: Path) -> set[str]:
    """Every anchor of a Markdown page: its headings (numbered as MkDocs and GitHub number repeats), explicit ids."""
    found: set[str] = set()
    counts: dict[str, int] = {}
    in_fence = False
    for line in path.read_text().splitlines():
        if re.match(r"^\s*(```|~~~)", line):
            in_fence = not in_fence
            continue
        if in_fence:
            continue
        heading = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            explicit = re.search(r"\{#([\w-]+)\}\s*$", heading.group(1))
            if explicit:
                found.add(explicit.group(1))
            for slug in slugs(heading.group(1)):
                number = counts.get(slug, 0)
                counts[slug] = number + 1
                found.add(slug if number == 0 else f"{slug}_{number}")  # MkDocs' repeats
                found.add(slug if number == 0 else f"{slug}-{number}")  # GitHub's repeats
        found.update(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", line))
        found.update(re.findall(r"\bid=\"([^\"]+)\"", line))
    return found


# -- where references are cited -----------------------------------------------------------------
def python_texts(path: Path) -> Iterator[tuple[int, str]]:
    """``(line, text)`` of every comment and docstring of a Python file."""
    source = path.read_text()
    try:
        for token in tokenize.generate_tokens(io.StringIO(source).readline):
            if token.type == tokenize.COMMENT:
                yield token.start[0], token.string
    except (tokenize.TokenError, SyntaxError):
        return
    try:
        tree = ast.parse(source)
    except SyntaxError:
        return
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                for offset, line in enumerate(first.value.value.splitlines()):
                    yield first.lineno + offset, line


def markdown_texts(path: Path) -> Iterator[tuple[int, str]]:
    yield from enumerate(path.read_text().splitlines(), start=1)


def code_files(root: Path, dirs: tuple[str, ...] = CODE_DIRS) -> list[Path]:
    return sorted(p for d in dirs if (root / d).is_dir() for p in (root / d).rglob("*.py") if ".venv" not in p.parts)


def markdown_files(root: Path) -> list[Path]:
    pages = [root / "README.md", root / "CHANGELOG.md", *sorted((root / "docs").rglob("*.md"))]
    return [p for p in pages if p.is_file()]


# -- the checks ---------------------------------------------------------------------------------
def _is_placeholder(path: str) -> bool:
    return bool(PLACEHOLDER.search(path))


def _check_target(root: Path, base: Path, target: str, anchor: str | None, where: str) -> Iterator[Finding]:
    """``target`` (a file or directory under ``base``) exists; ``anchor``, if any, is one of its anchors."""
    path = (base / target).resolve() if target else None
    if path is not None and not path.exists():
        if not _is_placeholder(target):
            yield Finding(where, f"{target} does not exist")
        return
    if anchor:
        page = path if path is not None else None
        if page is not None and page.is_file() and page.suffix == ".md" and anchor not in anchors_of(page):
            shown = page.relative_to(root) if page.is_relative_to(root) else page
            yield Finding(where, f"{shown}#{anchor}: no such heading")


def references_in(root: Path, path: Path, texts: Iterator[tuple[int, str]], links: bool) -> Iterator[Finding]:
    relative = path.relative_to(root)
    own_anchors: set[str] | None = None
    for number, text in texts:
        where = f"{relative}:{number}"
        if links:
            for link in LINK.findall(text):
                if re.match(r"^[a-z][a-z0-9+.-]*:", link) or link.startswith("//"):
                    continue  # http:, https:, mailto:
                target, _, anchor = link.partition("#")
                if not target:
                    own_anchors = anchors_of(path) if own_anchors is None else own_anchors
                    if anchor and anchor not in own_anchors:
                        yield Finding(where, f"#{anchor}: no such heading on this page")
                    continue
                yield from _check_target(root, path.parent, target, anchor or None, where)
        for match in PATH.finditer(LINK.sub("]", text) if links else text):
            target, anchor = match.group(1), (match.group(2) or "")[1:]
            yield from _check_target(root, root, target, anchor or None, where)


def dangling_references(root: Path) -> list[Finding]:
    """Every cited path or anchor that does not exist, in the code's comments and docstrings and in the pages."""
    findings: list[Finding] = []
    for path in code_files(root):
        findings += references_in(root, path, python_texts(path), links=False)
    for path in markdown_files(root):
        findings += references_in(root, path, markdown_texts(path), links=True)
    return list(dict.fromkeys(findings))  # once per line, in file order


def history_mentions(root: Path) -> list[Finding]:
    """Issue numbers and DESIGN.md anywhere in the files of common/, services/, tools/."""
    findings = []
    for directory in NO_HISTORY_DIRS:
        for path in sorted((root / directory).rglob("*")):
            if (
                not path.is_file()
                or path.suffix in (".pyc", ".png", ".so", ".npz", ".mcap")
                or "__pycache__" in path.parts
            ):
                continue
            try:
                lines = path.read_text().splitlines()
            except UnicodeDecodeError:
                continue
            for number, line in enumerate(lines, start=1):
                for match in HISTORY.finditer(line):
                    findings.append(Finding(f"{path.relative_to(root)}:{number}", f"{match.group(0)!r}"))
                if "DESIGN.md" in line:
                    findings.append(Finding(f"{path.relative_to(root)}:{number}", "'DESIGN.md'"))
    return findings
