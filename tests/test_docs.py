"""The documentation stays true to the code.

* The generated pages (docs/reference/, docs/benchmarks/, docs/changelog.md, the README's headline)
  are what ``srl docs`` would write now, and the reference pages name every setting, option,
  message and key: enumerated here from the code itself, not through tools/docs/.
* Every benchmark page (docs/benchmarks/) is a summary of at most 1,500 words (``wc -w``), its rows
  linked as a file (data/KIND.json, and a CSV where the page summarises them).
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


# -- a benchmark page is a summary, its data a file ---------------------------------------------
BENCHMARKS = ROOT / "docs" / "benchmarks"
MAX_WORDS = 1500


def words(text: str) -> int:
    """Words as ``wc -w`` counts them: whatever whitespace separates (a table's ``|`` is one)."""
    return len(text.split())


def oversized_pages(directory: Path, limit: int = MAX_WORDS) -> list[str]:
    """``name: N words`` of every page in ``directory`` with more than ``limit`` words."""
    counts = {path.name: words(path.read_text()) for path in sorted(directory.glob("*.md"))}
    return [f"{name}: {count} words" for name, count in counts.items() if count > limit]


def test_every_benchmark_page_has_at_most_1500_words(tmp_path: Path) -> None:
    from tools.docs import benchmarks

    assert benchmarks.MAX_WORDS == MAX_WORDS
    assert sorted(BENCHMARKS.glob("*.md")), "no benchmark pages"
    oversized = oversized_pages(BENCHMARKS)
    assert not oversized, (
        f"benchmark pages over {MAX_WORDS} words (summarise them in tools/docs/benchmarks.py): {oversized}"
    )
    # negative control: a page one word over is caught, one at the limit is not
    assert words("a | b\n\tc  d") == 5
    (tmp_path / "over.md").write_text("| word |\n" * 500 + "word\n")
    (tmp_path / "at.md").write_text("word " * MAX_WORDS)
    assert oversized_pages(tmp_path) == [f"over.md: {MAX_WORDS + 1} words"]


def test_a_benchmark_page_summarises_many_rows_and_links_their_data() -> None:
    from tools.docs import benchmarks

    rows = [
        {
            "method": "robot",
            "plant": plant,
            "localization": "amcl",
            "agent": "rlqv",
            "horizon": 12,
            "start": [i / 100, 1.0, 0.5],
            "true_final_distance": i / 1000,
            "sign_changes": 0,
            "saturated_commands": 0,
            "deadband_commands": 0,
            "arrival_seconds": None if i % 7 == 0 else 10.0 + i / 100,
            "final_ok": i < 50,
            "span_ok": True,
            "sign_changes_ok": True,
            "arrival_ok": i % 7 != 0,
            "passed": i < 50 and i % 7 != 0,
        }
        for plant in ("physics", "slipping")
        for i in range(1000)
    ]
    data = {"seconds": 35.0, "window_seconds": 10.0, "targets": {}, "rows": rows, "passed": 84, "total": 2000}
    page = benchmarks.benchmark_page("parking", data)
    assert words(page) <= MAX_WORDS
    assert "| robot | slipping | amcl | rlqv | 12 | 42/1000 | 50/1000 | 1000/1000 | 857/1000 |" in page
    assert "[parking.json](data/parking.json)" in page and "[parking.csv](data/parking.csv)" in page
    table = benchmarks.csv_text(rows).splitlines()
    assert len(table) == 1 + len(rows) and table[0].startswith("method,plant,localization,agent,horizon,start.0,")
    assert benchmarks.nearest_rank([3.0, 1.0, float("inf"), 2.0], 0.5) == 2.0


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


# what trains the baselines: srl experiment baselines, or Python that imports their packages
NEEDS_BASELINES = re.compile(r"experiment baselines|^\s*(?:import|from)\s+(?:torch|stable_baselines3)\b", re.MULTILINE)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize(
    "block",
    [
        # a block that trains SAC or PPO needs the baselines extra (tests/conftest.py: needs_baselines)
        pytest.param(b, id=b.id, marks=[pytest.mark.needs_baselines] if NEEDS_BASELINES.search(b.commands) else [])
        for b in docs_blocks.runnable_blocks(BLOCKS)
    ],
)
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


# -- the hand-written site reads in an afternoon ------------------------------------------------
PAGE_WORDS = 3000
SITE_WORDS = 25_000
NOT_HAND_WRITTEN = ("reference/", "benchmarks/", "changelog.md")  # under docs/: generated, not counted
MAY_BE_DATED = ("notes/", "benchmarks/", "changelog.md")  # under docs/: dated write-ups and measurements
# a date (2026-11-27, or a month: 2026-11), a link's path included (the notes are named without
# one), or a machine's load ("load 1.2", "load average"); a version number (3.8.2) is neither
DATED = re.compile(r"(?<![\w.])(?:19|20)\d{2}-\d{2}(?:-\d{2})?(?!\d)|\bload(?: average|\s+\d)", re.IGNORECASE)


def reading_findings(docs: Path) -> tuple[list[str], int]:
    """What keeps the hand-written pages under ``docs`` from reading in an afternoon, and their words.

    The rule, on every ``*.md`` under ``docs``: a page outside reference/, benchmarks/ and
    changelog.md has at most PAGE_WORDS words (``len(text.split())``, as ``wc -w``); no line of a
    page outside notes/, benchmarks/ and changelog.md matches DATED, code blocks included (an
    output example with a date is dated too)."""
    findings, total = [], 0
    for path in sorted(docs.rglob("*.md")):
        name, text = path.relative_to(docs).as_posix(), path.read_text()
        if not name.startswith(NOT_HAND_WRITTEN):
            total += words(text)
            if words(text) > PAGE_WORDS:
                findings.append(f"docs/{name}: {words(text)} words (at most {PAGE_WORDS})")
        if not name.startswith(MAY_BE_DATED):
            findings += [
                f"docs/{name}:{number}: dated: {line.strip()[:80]}"
                for number, line in enumerate(text.splitlines(), 1)
                if DATED.search(line)
            ]
    return findings, total


def test_the_hand_written_pages_read_in_an_afternoon(tmp_path: Path) -> None:
    """Every hand-written page has at most 3,000 words, and no page outside docs/notes/,
    docs/benchmarks/ and docs/changelog.md has a dated line (an ISO date, a machine's load): a
    measurement with its date goes in a note or a benchmark page, and the guide links it.

    Together the hand-written pages have at most SITE_WORDS (25,000) words: the site reads in an
    afternoon."""
    # negative control: a long dated guide and a link to a dated name are caught; a version number,
    # an undated note's link, a loaded machine, a payload, and dates in a note or a benchmark page are not
    docs = tmp_path / "docs"
    (docs / "notes").mkdir(parents=True)
    (docs / "benchmarks").mkdir()
    (docs / "guide.md").write_text("# Guide\n\nMeasured 2026-11-27.\n\n" + "word " * PAGE_WORDS + "\n\nat load 1.2\n")
    (docs / "fine.md").write_text(
        "# Fine\n\nCasADi 3.8.2, [the note](notes/baselines.md), a loaded machine, a payload 64 KiB.\n"
    )
    (docs / "linked.md").write_text("[the run](notes/2026-11-27-a.md)\n")
    (docs / "notes" / "2026-11-27-a.md").write_text("# 2026-11-27\n\nload average 3.1, load 1.2\n")
    (docs / "benchmarks" / "big.md").write_text("Date 2026-11-27, load 1.0\n" + "word " * (PAGE_WORDS + 1))
    assert reading_findings(docs) == (
        [
            "docs/guide.md: 3007 words (at most 3000)",
            "docs/guide.md:3: dated: Measured 2026-11-27.",
            "docs/guide.md:7: dated: at load 1.2",
            "docs/linked.md:1: dated: [the run](notes/2026-11-27-a.md)",
        ],
        3007 + 13 + 2 + 7,  # the guide, fine.md, linked.md and the note: all but the benchmark page
    )
    findings, total = reading_findings(ROOT / "docs")
    print(f"\nhand-written pages: {total} words in all (at most {SITE_WORDS})")
    assert not findings, "pages too long or dated:\n" + "\n".join(findings)
    assert total <= SITE_WORDS, f"the hand-written pages have {total} words, at most {SITE_WORDS}: cut, do not move"


# -- the architecture page's map of the code is the code's --------------------------------------
def code_map_findings(page: str, root: Path) -> list[str]:
    """What the map of the code in ``page`` (its ``text`` block under "The floors of the code")
    leaves out or names wrongly: every module of common/ and services/ (but ``__init__``,
    ``__main__`` and the services' ``command.py``) is named on its folder's lines, by its file name
    or its stem; every ``NAME.py`` named there exists in that folder; every folder of tools/ is
    named (tools/ is mapped by folder)."""
    block = page.split("## The floors of the code", 1)[1].split("```text", 1)[1].split("```", 1)[0]
    lines: dict[str, str] = {}  # "common/math" -> the text of its lines
    top, folder = "", ""
    for line in block.splitlines():
        label = re.match(r"^(\s*)([a-z0-9_]+/)", line)
        if label and not label.group(1):
            top, folder = label.group(2).rstrip("/"), ""
            lines[top] = lines.get(top, "") + line
        elif label and len(label.group(1)) == 2:
            folder = f"{top}/{label.group(2).rstrip('/')}"
            lines[folder] = line
        elif folder:
            lines[folder] += " " + line
        else:
            lines[top] = lines.get(top, "") + " " + line
    findings = []
    for floor in ("common", "services"):
        for package in sorted(p for p in (root / floor).iterdir() if (p / "__init__.py").is_file()):
            name = f"{floor}/{package.name}"
            text = lines.get(name)
            if text is None:
                findings.append(f"{name}/ is not on the map")
                continue
            for module in sorted(package.glob("*.py")):
                skip = ("__init__", "__main__") + (("command",) if floor == "services" else ())
                if module.stem not in skip and not re.search(rf"\b{re.escape(module.stem)}\b", text):
                    findings.append(f"{name}/{module.name} is not on the map")
            for named in re.findall(r"\b([a-z0-9_]+)\.py\b", text):
                if named != "command" and not (package / f"{named}.py").is_file():
                    findings.append(f"{name}/{named}.py is on the map but not in the code")
    tools_text = lines.get("tools", "") + " ".join(v for k, v in lines.items() if k.startswith("tools/"))
    for sub in sorted(p for p in (root / "tools").iterdir() if (p / "__init__.py").is_file()):
        if f"{sub.name}/" not in tools_text:
            findings.append(f"tools/{sub.name}/ is not on the map")
    return findings


def test_the_architecture_pages_map_of_the_code_is_the_code(tmp_path: Path) -> None:
    page = (ROOT / "docs" / "architecture.md").read_text()
    findings = code_map_findings(page, ROOT)
    assert not findings, "docs/architecture.md, 'The floors of the code':\n" + "\n".join(findings)
    # negative control: a module added to the code and a module named but gone are both caught
    (tmp_path / "common" / "math").mkdir(parents=True)
    (tmp_path / "services" / "actor").mkdir(parents=True)
    (tmp_path / "tools" / "gym").mkdir(parents=True)
    for package in ("common/math", "services/actor", "tools/gym"):
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "common" / "math" / "critic.py").write_text("")
    (tmp_path / "common" / "math" / "brand_new.py").write_text("")
    (tmp_path / "services" / "actor" / "command.py").write_text("")
    fake = "## The floors of the code\n\n```text\ntools/  gym/\nservices/\n  actor/  host.py\n"
    fake += "common/\n  math/  critic\n```\n"
    assert code_map_findings(fake, tmp_path) == [
        "common/math/brand_new.py is not on the map",
        "services/actor/host.py is on the map but not in the code",
    ]


def test_the_headlines_fleet_row_says_each_sizes_cpu_at_rest_and_one_robot_in_the_singular() -> None:
    """The README's fleet figure (tools/docs/benchmarks.py headline_table) from a benchmark's rows:
    per size its missed deadlines, jitter, robots at target and CPU per robot tick, with the CPU at
    rest when every robot arrived (left out when not: NaN); the baseline rows stay on the page."""
    from tools.docs.benchmarks import headline_table

    def row(robots: int, rest: float, layout: str = "host") -> dict[str, object]:
        return {
            "robots": robots,
            "layout": layout,
            "fleet": {"missed_deadlines": 0, "jitter_p99_ms": 1.5, "parked": robots, "at_target": robots},
            "cpu_ms_per_robot_tick": 0.3,
            "cpu_phases": {"at_rest": {"cpu_ms_per_robot_tick": rest}},
        }

    fleet = {"seconds": 30.0, "recorded": True, "rows": [row(1, 6.4), row(8, 9.0, "process"), row(100, float("nan"))]}
    table = headline_table({"fleet": fleet}, None)
    line = next(text for text in table.splitlines() if text.startswith("| Fleet on one machine"))
    assert "`srl record` attached" in line
    assert "1 robot: 0 missed, jitter p99 1.50 ms, 1 at target, 0.30 ms CPU per robot tick (at rest 6.40);" in line
    assert "100 robots: 0 missed, jitter p99 1.50 ms, 100 at target, 0.30 ms CPU per robot tick |" in line
    assert "9.00" not in line  # the baseline of one process per robot: on the benchmark's page
