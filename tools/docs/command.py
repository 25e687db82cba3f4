"""``srl docs``: write the generated pages, or (``--check``) say which one is stale.

What is generated, all of it from files in this repository:

* docs/reference/settings.md, cli.md, messages.md, keys.md (tools/docs/reference.py);
* docs/benchmarks/KIND.md and index.md from docs/benchmarks/data/KIND.json, and beside a JSON whose
  rows a page summarises its CSV, KIND.csv (tools/docs/benchmarks.py);
* docs/changelog.md, CHANGELOG.md as the site shows it;
* the README's headline table, between its ``<!-- headline:begin -->`` and ``<!-- headline:end -->``.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from tools.docs import benchmarks, reference, systems

ROOT = Path(__file__).resolve().parents[2]
BENCHMARK_DATA = Path("docs/benchmarks/data")
PAPER_SUMMARY = Path("docs/paper/paper-grid/summary.json")


def changelog_page(text: str) -> str:
    """CHANGELOG.md as a page of docs/: its links into docs/ made relative to docs/."""
    return re.sub(r"\]\((?:\./)?docs/", "](", text)


def generated_files(srl: argparse.ArgumentParser, root: Path = ROOT) -> dict[Path, str]:
    """Every generated file (relative to ``root``) and the text the code would give it now."""
    files: dict[Path, str] = {
        Path("docs/reference/settings.md"): reference.settings_page(),
        Path("docs/reference/cli.md"): reference.cli_page(srl),
        Path("docs/reference/messages.md"): reference.messages_page(),
        Path("docs/reference/keys.md"): reference.keys_page(),
        Path("docs/reference/variants.md"): reference.variants_page(),
    }
    files.update(systems.pages(root))
    for name, text in benchmarks.pages(root / BENCHMARK_DATA).items():
        files[Path("docs/benchmarks") / name] = text
    changelog = root / "CHANGELOG.md"
    if changelog.is_file():
        files[Path("docs/changelog.md")] = changelog_page(changelog.read_text())
    readme = root / "README.md"
    if readme.is_file():
        table = benchmarks.headline_table(
            benchmarks.load_data(root / BENCHMARK_DATA), benchmarks.read_json(root / PAPER_SUMMARY)
        )
        files[Path("README.md")] = benchmarks.replace_headline(readme.read_text(), table)
    return {path: text if text.endswith("\n") else text + "\n" for path, text in sorted(files.items())}


def orphans(root: Path, files: dict[Path, str]) -> list[Path]:
    """Generated files under docs/benchmarks/ that nothing generates any more (their JSON is gone): a
    page that says it is generated, a CSV beside no JSON."""
    found = []
    for path in sorted((root / "docs/benchmarks").glob("*.md")):
        relative = path.relative_to(root)
        if relative not in files and path.read_text().startswith(reference.GENERATED):
            found.append(relative)
    for path in sorted((root / BENCHMARK_DATA).glob("*.csv")):
        relative = path.relative_to(root)
        if relative not in files and not path.with_suffix(".json").is_file():
            found.append(relative)
    return found


def stale_files(srl: argparse.ArgumentParser, root: Path = ROOT) -> list[str]:
    """The generated files that differ from what the code would write now (empty: all current)."""
    files = generated_files(srl, root)
    stale = [str(p) for p, text in files.items() if not (root / p).is_file() or (root / p).read_text() != text]
    return stale + [f"{p} (nothing generates it: delete it)" for p in orphans(root, files)]


def write(srl: argparse.ArgumentParser, root: Path = ROOT) -> list[str]:
    """Write every generated file that changed; the paths written."""
    written = []
    files = generated_files(srl, root)
    for path, text in files.items():
        target = root / path
        if target.is_file() and target.read_text() == text:
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
        written.append(str(path))
    for path in orphans(root, files):
        (root / path).unlink()
        written.append(f"{path} (deleted)")
    return written


NAME = "docs"
HELP = "write the generated documentation pages (reference, benchmarks, README headline)"
DESCRIPTION = (
    "Write the documentation pages generated from the code: docs/reference/*.md (settings, CLI, wire\n"
    "messages, keys, a page per built-in system), docs/benchmarks/*.md (from docs/benchmarks/data/*.json),\n"
    "docs/changelog.md and the README's headline table. --check writes nothing and exits 1 naming every\n"
    "stale file; --systems first runs `srl experiment paper --system S` for each built-in system but the\n"
    "robot (about 20 s each on 2 cores) and keeps its summary and figures in docs/paper/systems/S/."
)


def main(args: argparse.Namespace) -> int:
    """``srl docs [--check]``: the exit code."""
    root = Path(args.root) if args.root else ROOT
    if args.check and args.systems:
        print("srl docs: error: --systems writes the systems' results; it does not go with --check", file=sys.stderr)
        return 2
    if args.check:
        stale = stale_files(args.srl_parser, root)
        for path in stale:
            print(f"srl docs: stale: {path} (run srl docs)", file=sys.stderr)
        if not stale:
            print(f"srl docs: {len(generated_files(args.srl_parser, root))} generated files are current")
        return 1 if stale else 0
    kept = []
    if args.systems:  # the experiments through the command line this srl parsed (args.srl_parser)
        from common.process.runtime import main as run_command

        try:
            kept = systems.run_experiments(root, lambda argv: run_command(args.srl_parser, argv))
        except RuntimeError as error:
            print(f"srl docs: error: {error}; nothing kept", file=sys.stderr)
            return 1
    written = kept + write(args.srl_parser, root)
    print(f"srl docs: wrote {len(written)} files" + "".join(f"\n  {p}" for p in written))
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 if a generated file differs from what srl docs writes",
    )
    parser.add_argument(
        "--systems",
        action="store_true",
        help="first run the paper's experiment on each built-in system but the robot and keep its results "
        "(docs/paper/systems/)",
    )
    parser.add_argument(
        "--root", metavar="DIR", help="the repository to generate in (default: the checkout srl runs from)"
    )
    parser.set_defaults(func=main)
