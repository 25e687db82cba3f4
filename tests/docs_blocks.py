"""The runnable commands of the documentation: every fenced ``bash`` block of README.md and docs/.

A block is run from the repository root by bash with ``set -e`` (``./srl`` is this checkout's
script, ``srl`` its venv's command, the router on a free port), at most :data:`BLOCK_SECONDS`,
unless the line right before its fence is ``<!-- not run: REASON -->`` with a reason. A command line ending in
``# prints: TEXT`` has TEXT checked in the block's output (stdout and stderr together).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
from dataclasses import dataclass, field, replace
from pathlib import Path

from common.system.ports import free_port

BLOCK_SECONDS = 120


FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([\w+-]*)")
NOT_RUN = re.compile(r"^\s*<!--\s*not run:(.*?)-->\s*$")
PRINTS = re.compile(r"\s#\s*prints:\s*(.+?)\s*$")
COMMENT = re.compile(r"(^|\s+)#(?:\s.*)?$")  # a shell comment: `#` at the start or after blanks, then a blank
RUNS_THE_TESTS = re.compile(r"(^|[\s;&|(])(\./)?srl\s+test\b|\bpytest\b|\.ci/run\b", re.MULTILINE)


@dataclass
class Block:
    path: Path  # relative to the repository root
    line: int  # of the opening fence, 1-based
    text: str
    skipped_because: str | None = None  # the not-run reason ("" if the marker gives none)
    expected: list[str] = field(default_factory=list)  # the # prints: texts
    same_as: list[str] = field(default_factory=list)  # ids of blocks with the same commands, run with this one

    @property
    def id(self) -> str:
        return f"{self.path}:{self.line}"

    @property
    def commands(self) -> str:
        """The block without its comments: what bash runs."""
        return "\n".join(line for line in (COMMENT.sub("", raw).rstrip() for raw in self.text.splitlines()) if line)


def blocks_of(path: Path, root: Path) -> list[Block]:
    """Every fenced block whose info string is ``bash`` in the Markdown file ``path``."""
    lines = path.read_text().splitlines()
    found: list[Block] = []
    index = 0
    while index < len(lines):
        opening = FENCE.match(lines[index])
        if not opening:
            index += 1
            continue
        fence, language = opening.group(2), opening.group(3)
        end = index + 1
        while end < len(lines) and not lines[end].strip().startswith(fence):
            end += 1
        if language == "bash":
            text = "\n".join(lines[index + 1 : end])
            marker = NOT_RUN.match(lines[index - 1]) if index > 0 else None
            found.append(
                Block(
                    path=path.relative_to(root),
                    line=index + 1,
                    text=text,
                    skipped_because=marker.group(1).strip() if marker else None,
                    expected=[m.group(1) for m in map(PRINTS.search, text.splitlines()) if m],
                )
            )
        index = end + 1
    return found


def documentation_files(root: Path) -> list[Path]:
    return sorted([root / "README.md", *(root / "docs").rglob("*.md")])


def all_blocks(root: Path) -> list[Block]:
    return [block for path in documentation_files(root) if path.is_file() for block in blocks_of(path, root)]


def runnable_blocks(blocks: list[Block]) -> list[Block]:
    """The blocks to run: one per distinct command text (the README and a page often show the same
    command), carrying every copy's ``# prints:`` texts, so each copy is checked by one run."""
    runs: dict[str, Block] = {}
    for block in blocks:
        if block.skipped_because is not None:
            continue
        first = runs.get(block.commands)
        if first is None:
            runs[block.commands] = replace(block, expected=list(block.expected), same_as=[])
            continue
        first.same_as.append(block.id)
        first.expected += [text for text in block.expected if text not in first.expected]
    return list(runs.values())


def run_block(block: Block, root: Path, seconds: float = BLOCK_SECONDS, tmp: Path | None = None) -> str | None:
    """Run one block; None if it succeeded and printed what it says, else what went wrong.

    ``tmp``: where the block's ``/tmp/...`` paths go (in its commands and in its ``# prints:``
    texts), and its temporary directory (``TMPDIR``: what a library makes there, as
    stable-baselines3's default logger and torch's compiler cache do), so a run leaves nothing in
    /tmp and never meets another user's file of that name."""
    text, expected = block.text, block.expected
    if tmp is not None:
        text = text.replace("/tmp/", f"{tmp}/")
        expected = [line.replace("/tmp/", f"{tmp}/") for line in expected]
    env = dict(os.environ)
    env["PATH"] = f"{root / '.venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    if tmp is not None:
        env["TMPDIR"] = str(tmp)
    # a router port of its own (the packaged 7447 may be taken by another test or a running system):
    # the environment is below any flag the block gives, so a block that names its router keeps it
    env["SRL_TRANSPORT__ROUTER"] = f"tcp/127.0.0.1:{free_port()}"
    process = subprocess.Popen(
        ["bash", "-c", "set -e\n" + text],
        cwd=root,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own process group: a timeout ends everything the block started
    )
    try:
        output, _ = process.communicate(timeout=seconds)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate()
        return f"{block.id}: did not finish in {seconds:.0f} s; output:\n{output[-4000:]}"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)  # whatever the block left running in the background
    if process.returncode != 0:
        return f"{block.id}: exit {process.returncode}; output:\n{output[-4000:]}"
    missing = [line for line in expected if line not in output]
    if missing:
        return f"{block.id}: the output lacks {missing}; output:\n{output[-4000:]}"
    return None
