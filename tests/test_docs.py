"""The documentation stays true to the code.

* The generated pages (docs/reference/, docs/benchmarks/, docs/changelog.md, the README's headline)
  are what ``srl docs`` would write now, and the reference pages name every setting, option,
  message and key: enumerated here from the code itself, not through tools/docs/.
* ``mkdocs build --strict`` passes: no broken link, no page missing from the nav.
* Every fenced ``bash`` block of README.md and docs/ runs as written (tests/docs_blocks.py).
* No cited path or anchor dangles, and the code says nothing of issue numbers or DESIGN.md
  (tests/docs_refs.py).

Each check has a negative control: a doctored page or tree that it must catch.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import tomllib
from pathlib import Path

import pytest

from common.config.settings import DEFAULT_CONFIG, Settings
from common.contracts import keys, messages
from tests import docs_blocks, docs_refs
from tests.harness import ROOT
from tools.docs.command import stale_files

REFERENCE = ROOT / "docs" / "reference"


# -- the generated pages are current and complete ----------------------------------------------
@pytest.mark.integration
def test_the_generated_pages_are_what_srl_docs_writes_now() -> None:
    from tools.cli import build_parser

    stale = stale_files(build_parser(), ROOT)
    assert not stale, f"stale generated files (run ./srl docs): {stale}"


def test_srl_docs_check_names_a_stale_file_and_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools.cli import main

    (tmp_path / "docs" / "benchmarks" / "data").mkdir(parents=True)
    assert main(["docs", "--root", str(tmp_path)]) == 0
    assert main(["docs", "--check", "--root", str(tmp_path)]) == 0
    page = tmp_path / "docs" / "reference" / "settings.md"
    page.write_text(page.read_text().replace("SRL_PLANT__V_MAX", "SRL_PLANT__V_MIN"))
    capsys.readouterr()
    assert main(["docs", "--check", "--root", str(tmp_path)]) == 1
    assert "docs/reference/settings.md" in capsys.readouterr().err


def sections(page: str, level: int) -> dict[str, str]:
    """Heading text -> the text under it, for the headings of ``level`` (and deeper ones inside)."""
    parts = re.split(rf"^({'#' * level} .*)$", page, flags=re.MULTILINE)
    return {parts[i][level + 1 :].strip(): parts[i + 1] for i in range(1, len(parts) - 1, 2)}


def missing_settings(page: str) -> list[str]:
    """Every setting of the models and of srl.toml, with its section, default and environment variable."""
    missing = []
    packaged = tomllib.loads(DEFAULT_CONFIG.read_text())
    by_section = sections(page, 2)
    for section, field in Settings.model_fields.items():
        model = field.annotation
        assert model is not None
        names = set(model.model_fields) | set(packaged.get(section, {}))
        text = by_section.get(f"[{section}]", "")
        for name in sorted(names):
            row = next((line for line in text.splitlines() if line.startswith(f"| `{section}.{name}` |")), None)
            if row is None or f"`SRL_{section.upper()}__{name.upper()}`" not in row:
                missing.append(f"{section}.{name}")
            elif name in packaged.get(section, {}) and f"| `{json.dumps(packaged[section][name])}` |" not in row:
                missing.append(f"{section}.{name} = {json.dumps(packaged[section][name])} (the packaged default)")
    return missing


def parser_options(parser: argparse.ArgumentParser, name: str = "srl") -> dict[str, list[str]]:
    """Command -> its option strings (or positional names), for every command under ``parser``."""
    found: dict[str, list[str]] = {name: []}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub_parser in action.choices.items():
                found.update(parser_options(sub_parser, f"{name} {sub_name}"))
        elif not isinstance(action, argparse._HelpAction):
            found[name] += list(action.option_strings) or [str(action.metavar or action.dest)]
    return found


def missing_cli(page: str) -> list[str]:
    from tools.cli import build_parser

    headings = {**sections(page, 2), **sections(page, 3)}
    missing = []
    for command, names in parser_options(build_parser()).items():
        text = headings.get(command)
        if text is None:
            missing.append(command)
            continue
        own = re.split(r"^#", text, flags=re.MULTILINE)[0]  # not the subcommands' sections below it
        missing += [
            f"{command} {n}" for n in names if not re.search(rf"^\| `([^`]*, )?{re.escape(n)}(, [^`]*)?` \|", own, re.M)
        ]
    return missing


def message_classes() -> list[type[messages.Message]]:
    return [
        value
        for value in vars(messages).values()
        if isinstance(value, type) and issubclass(value, messages.Message) and value is not messages.Message
    ]


def missing_messages(page: str) -> list[str]:
    by_name = sections(page, 2)
    missing = []
    for model in message_classes():
        text = by_name.get(model.__name__)
        if text is None:
            missing.append(model.__name__)
            continue
        missing += [f"{model.__name__}.{f}" for f in model.model_fields if f"| `{f}` |" not in text]
    return missing


def missing_keys(page: str) -> list[str]:
    missing = []
    for name, value in vars(keys).items():
        pattern = getattr(value, "pattern", value)
        is_key = isinstance(value, keys.Topic | keys.Service) or (isinstance(value, str) and value.startswith("srl/"))
        if is_key and (f"## {name}\n" not in page or f"`{pattern}`" not in page):
            missing.append(name)
        if isinstance(value, keys.Topic) and f"[{value.schema.__name__}](messages.md#" not in page:
            missing.append(f"{name} schema")
    missing += [
        f"{n}()"
        for n, v in vars(keys).items()
        if callable(v)
        and getattr(v, "__module__", "") == keys.__name__
        and not isinstance(v, type)
        and not n.startswith("_")
        and f"`{n}(" not in page
    ]
    return missing


CHECKS = {
    "settings.md": missing_settings,
    "cli.md": missing_cli,
    "messages.md": missing_messages,
    "keys.md": missing_keys,
}
# a doctored page of each kind: one item's text replaced, which its check must notice
DOCTORED = [
    ("settings.md", "`SRL_TRANSPORT__ROUTER`"),
    ("settings.md", "`0.22`"),  # plant.v_max's packaged default
    ("cli.md", "`--horizons`"),
    ("messages.md", "| `q_weights` |"),
    ("keys.md", "`srl/{robot}/critic/weights`"),
]


@pytest.mark.parametrize("page", sorted(CHECKS))
def test_the_reference_page_names_everything_the_code_defines(page: str) -> None:
    missing = CHECKS[page]((REFERENCE / page).read_text())
    assert not missing, f"docs/reference/{page} lacks {missing} (run ./srl docs)"


@pytest.mark.parametrize(("page", "item"), DOCTORED)
def test_a_reference_page_without_an_item_is_caught(page: str, item: str) -> None:
    text = (REFERENCE / page).read_text()
    assert item in text
    assert CHECKS[page](text.replace(item, "`elsewhere`")), f"{page} without {item!r} went unnoticed"


# -- the site builds --------------------------------------------------------------------------
@pytest.mark.integration
def test_mkdocs_build_strict_passes(tmp_path: Path) -> None:
    done = subprocess.run(
        [str(ROOT / ".venv" / "bin" / "mkdocs"), "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr


# -- the commands of the pages run as written ---------------------------------------------------
BLOCKS = docs_blocks.all_blocks(ROOT)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("block", docs_blocks.runnable_blocks(BLOCKS), ids=lambda b: b.id)
def test_the_documented_commands_run_and_print_what_they_say(block: docs_blocks.Block, tmp_path: Path) -> None:
    # the test suite inside the test suite would run this test again, and it again: such a block is not run
    assert not docs_blocks.RUNS_THE_TESTS.search(block.text), (
        f"{block.id} runs the test suite: give it a block of its own, marked <!-- not run: it is the test suite -->"
    )
    failure = docs_blocks.run_block(block, ROOT, tmp=tmp_path)
    assert failure is None, failure


def test_blocks_with_the_same_commands_run_once_and_check_every_copys_output(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("```bash\necho one two   # prints: one\n```\n")
    (tmp_path / "docs" / "a.md").write_text("```bash\necho one two   # prints: two\n```\n\n```bash\necho three\n```\n")
    runs = docs_blocks.runnable_blocks(docs_blocks.all_blocks(tmp_path))
    assert [(b.id, b.expected, b.same_as) for b in runs] == [
        ("README.md:1", ["one", "two"], ["docs/a.md:1"]),
        ("docs/a.md:5", [], []),
    ]


@pytest.mark.integration
def test_a_blocks_tmp_paths_go_to_the_tests_own_directory(tmp_path: Path) -> None:
    name = f"srl-block-probe-{os.getpid()}.txt"
    block = docs_blocks.Block(
        path=Path("README.md"), line=1, text=f"echo hi > /tmp/{name}; ls /tmp/{name}", expected=[f"/tmp/{name}"]
    )
    assert docs_blocks.run_block(block, ROOT, seconds=20, tmp=tmp_path) is None
    assert (tmp_path / name).read_text() == "hi\n"
    assert not (Path("/tmp") / name).exists()


def test_every_block_not_run_says_why() -> None:
    unexplained = [b.id for b in BLOCKS if b.skipped_because is not None and not b.skipped_because]
    assert not unexplained, f"<!-- not run: REASON --> without a reason before {unexplained}"


FAKE_PAGE = """# A page

```bash
echo hello  # prints: hello
```

<!-- not run: it needs a robot -->
```bash
exit 3
```

<!-- not run: -->
```bash
true
```

```bash
echo hello  # prints: goodbye
```

```bash
false
echo never
```
"""


@pytest.mark.integration
@pytest.mark.slow
def test_a_failing_block_and_a_wrong_prints_are_caught(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("# Readme\n")
    (tmp_path / "docs" / "page.md").write_text(FAKE_PAGE)
    found = docs_blocks.all_blocks(tmp_path)
    assert [b.line for b in found] == [3, 8, 13, 17, 21]
    assert [b.skipped_because for b in found] == [None, "it needs a robot", "", None, None]
    assert found[0].expected == ["hello"]
    run = [b for b in found if b.skipped_because is None]
    results = [docs_blocks.run_block(b, tmp_path, seconds=20) for b in run]
    assert results[0] is None
    assert results[1] is not None and "goodbye" in results[1] and "docs/page.md:17" in results[1]
    assert results[2] is not None and "exit 1" in results[2]
    slow = docs_blocks.Block(Path("docs/page.md"), 1, "sleep 30")
    assert "did not finish" in (docs_blocks.run_block(slow, tmp_path, seconds=1) or "")


def test_a_block_that_runs_the_test_suite_is_recognised() -> None:
    for text in ("./srl test", "./srl run\n./srl test -x", "SRL_TEST_REQUIRE_ALL=1 ./srl test", ".venv/bin/pytest -q"):
        assert docs_blocks.RUNS_THE_TESTS.search(text), text
    for text in ("./srl run --duration 5", "./srl up --robots 8  # the test of a fleet", "srl bench actor"):
        assert not docs_blocks.RUNS_THE_TESTS.search(text), text


# -- no dangling references, no history in the code ---------------------------------------------
def test_no_cited_path_or_anchor_dangles() -> None:
    findings = docs_refs.dangling_references(ROOT)
    assert not findings, f"{len(findings)} dangling references:\n" + "\n".join(map(str, findings))


def test_the_code_names_no_issue_numbers_and_no_design_md() -> None:
    findings = docs_refs.history_mentions(ROOT)
    assert not findings, f"{len(findings)} mentions:\n" + "\n".join(map(str, findings))


def test_dangling_references_and_history_are_caught(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "common").mkdir()
    (tmp_path / "tests").mkdir()
    (tmp_path / "README.md").write_text("# Readme\n\n## Getting started\n\nSee [the page](docs/page.md#usage).\n")
    (tmp_path / "docs" / "page.md").write_text(
        "# Page\n\n## Usage\n\n[up](#usage), [down](#nowhere), [readme](../README.md#getting-started), "
        "[gone](gone.md), [bad](../README.md#no-such-section)\n"
    )
    (tmp_path / "common" / "good.py").write_text(
        '"""Follows docs/page.md#usage and README.md#getting-started; see tests/test_good.py."""\n'
        "# the rule: docs/page.md\n"
    )
    (tmp_path / "tests" / "test_good.py").write_text("")
    (tmp_path / "common" / "bad.py").write_text(
        '"""See common/math/missing.py and docs/page.md#missing-anchor."""\n'
        "# as issue 12 found (DESIGN.md section 2)\n"
        "x = 1  # README.md#gone\n"
    )
    found = {str(f) for f in docs_refs.dangling_references(tmp_path)}
    assert found == {
        "docs/page.md:5: #nowhere: no such heading on this page",
        "docs/page.md:5: gone.md does not exist",
        "docs/page.md:5: README.md#no-such-section: no such heading",
        "common/bad.py:1: common/math/missing.py does not exist",
        "common/bad.py:1: docs/page.md#missing-anchor: no such heading",
        "common/bad.py:3: README.md#gone: no such heading",
    }, found
    history = {str(f) for f in docs_refs.history_mentions(tmp_path)}
    assert history == {"common/bad.py:2: 'issue 12'", "common/bad.py:2: 'DESIGN.md'"}, history
