"""What a release carries, and that its pieces agree: one version, the license, the citation.

* The version: pyproject.toml's ``version`` is the newest milestone heading of CHANGELOG.md (its
  ``## [Unreleased]`` section is what comes after it), CITATION.cff carries the same version and
  that milestone's date, and ``srl --version`` prints it (from the installed package's metadata).
* The license: LICENSE is the Apache License 2.0, the standard text unchanged, and pyproject.toml
  declares it (``license = "Apache-2.0"``), as does the installed package's metadata.
* The citation: CITATION.cff is YAML with the keys CFF 1.2.0 requires, and names the paper srl
  implements under ``references``, with the same title and authors as the README's BibTeX entry.

Each check has a negative control beside it: the same check on a deliberately wrong input fails.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest
import yaml

import tools.cli
from tests.harness import ROOT

PAPER_TITLE = "A generalized stacked reinforcement learning method for sampled systems"
PAPER_AUTHORS = [
    ("Pavel", "Osinenko"),
    ("Dmitrii", "Dobriborsci"),
    ("Grigory", "Yaremenko"),
    ("Georgiy", "Malaniya"),
]
# https://www.apache.org/licenses/LICENSE-2.0.txt, byte for byte (Debian's
# /usr/share/common-licenses/Apache-2.0 is the same file)
APACHE_2_SHA256 = "cfc7749b96f63bd31c3c42b5c471bf756814053e847c10f3eb003417bc523d30"
APACHE_2_SECTIONS = (
    "1. Definitions.",
    "2. Grant of Copyright License.",
    "3. Grant of Patent License.",
    "4. Redistribution.",
    "5. Submission of Contributions.",
    "6. Trademarks.",
    "7. Disclaimer of Warranty.",
    "8. Limitation of Liability.",
    "9. Accepting Warranty or Additional Liability.",
    "END OF TERMS AND CONDITIONS",
)
MILESTONE = re.compile(r"^## \[(\d+)\.(\d+)\.(\d+)\] - (\d{4}-\d{2}-\d{2})$", flags=re.M)
WRONG_VERSION = "0.0.0-wrong"


def pyproject() -> dict[str, Any]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def milestones(changelog: str) -> list[tuple[str, str]]:
    """``(version, date)`` of every milestone heading of a changelog, in the file's order."""
    return [(".".join(match[:3]), match[3]) for match in MILESTONE.findall(changelog)]


def newest_milestone(changelog: str) -> tuple[str, str]:
    """The first milestone heading (the changelog lists the newest first): ``(version, date)``."""
    found = milestones(changelog)
    assert found, "the changelog has no milestone heading '## [X.Y.Z] - YYYY-MM-DD'"
    return found[0]


def license_problems(text: str) -> list[str]:
    """What keeps ``text`` from being the standard Apache License 2.0 (empty: it is)."""
    problems = []
    if not re.match(r"\s*Apache License\s+Version 2\.0, January 2004\s", text):
        problems.append("does not open with 'Apache License / Version 2.0, January 2004'")
    problems += [f"no section {title!r}" for title in APACHE_2_SECTIONS if title not in text]
    if hashlib.sha256(text.encode()).hexdigest() != APACHE_2_SHA256:
        problems.append("is not the standard text byte for byte (apache.org's LICENSE-2.0.txt)")
    return problems


def cff_problems(cff: Any) -> list[str]:
    """What keeps a parsed CITATION.cff from carrying what CFF 1.2.0 requires and what srl's
    citation needs (empty: nothing)."""
    if not isinstance(cff, dict):
        return [f"is not a YAML mapping: {type(cff).__name__}"]
    problems = [f"no {key!r}" for key in ("cff-version", "message", "title", "authors") if not cff.get(key)]
    if cff.get("cff-version") != "1.2.0":
        problems.append(f"cff-version is {cff.get('cff-version')!r}, not '1.2.0'")
    references = cff.get("references") or []
    papers = [r for r in references if isinstance(r, dict) and r.get("title") == PAPER_TITLE]
    if not papers:
        problems.append(f"no reference titled {PAPER_TITLE!r}")
    for paper in papers:
        problems += [f"the paper's reference has no {key!r}" for key in ("type", "authors") if not paper.get(key)]
        names = [(a.get("given-names"), a.get("family-names")) for a in paper.get("authors") or []]
        if names != PAPER_AUTHORS:
            problems.append(f"the paper's authors are {names}, not {PAPER_AUTHORS}")
    return problems


def readme_bibtex() -> str:
    citing = (ROOT / "README.md").read_text().split("\n## Citing\n", 1)
    assert len(citing) == 2, "README.md has no '## Citing' section"
    block = re.search(r"```bibtex\n(.*?)```", citing[1], flags=re.S)
    assert block, "README.md's Citing section has no ```bibtex block"
    return block.group(1)


# -- one version ---------------------------------------------------------------------------------
def test_pyproject_version_is_the_changelogs_newest_milestone() -> None:
    changelog = (ROOT / "CHANGELOG.md").read_text()
    version, _ = newest_milestone(changelog)
    assert pyproject()["project"]["version"] == version, (
        f"pyproject.toml says {pyproject()['project']['version']}, CHANGELOG.md's newest milestone is {version}"
    )
    # the changelog: Unreleased first, then the milestones, newest first
    assert changelog.index("\n## [Unreleased]") < changelog.index(f"\n## [{version}]")
    found = [tuple(int(part) for part in v.split(".")) for v, _ in milestones(changelog)]
    assert found == sorted(found, reverse=True), f"CHANGELOG.md's milestones are not newest first: {found}"
    # negative control: a newer milestone in the changelog, and pyproject.toml no longer agrees
    newer = changelog.replace("\n## [Unreleased]", "\n## [Unreleased]\n\n## [99.0.0] - 2099-01-01", 1)
    assert newest_milestone(newer) == ("99.0.0", "2099-01-01")
    assert newest_milestone(newer)[0] != pyproject()["project"]["version"]


def test_version_is_the_installed_metadatas_else_pyprojects(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    expected = pyproject()["project"]["version"]
    assert metadata.version("srl") == expected, (
        f"the installed srl is {metadata.version('srl')}, pyproject.toml says {expected}: "
        "reinstall (./srl does when pyproject.toml changed; or pip install -e .)"
    )
    assert tools.cli.version() == expected

    def not_installed(name: str) -> str:
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(tools.cli.metadata, "version", not_installed)
    assert tools.cli.version() == expected  # the fallback: pyproject.toml itself
    # negative control: the fallback reads the file it names, so a wrong version there shows
    wrong = tmp_path / "pyproject.toml"
    wrong.write_text(f'[project]\nname = "srl"\nversion = "{WRONG_VERSION}"\n')
    monkeypatch.setattr(tools.cli, "PYPROJECT", wrong)
    assert tools.cli.version() == WRONG_VERSION != expected


def test_version_option_prints_the_metadatas_version(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """In process: ``srl --version`` prints what the metadata says (a deliberately wrong one here)."""
    monkeypatch.setattr(tools.cli.metadata, "version", lambda name: WRONG_VERSION)
    with pytest.raises(SystemExit) as done:
        tools.cli.main(["--version"])
    assert done.value.code in (0, None)
    assert capsys.readouterr().out == f"srl {WRONG_VERSION}\n"


@pytest.mark.integration
def test_srl_version_prints_the_version_and_exits_0() -> None:
    expected = pyproject()["project"]["version"]
    done = subprocess.run(
        [sys.executable, "-m", "tools.cli", "--version"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout == f"srl {expected}\n", (done.stdout, expected)


# -- the license -----------------------------------------------------------------------------------
def test_license_is_apache_2_and_pyproject_says_so() -> None:
    text = (ROOT / "LICENSE").read_text()
    assert license_problems(text) == [], license_problems(text)
    project = pyproject()["project"]
    assert project["license"] == "Apache-2.0", project.get("license")
    assert "LICENSE" in project["license-files"], project.get("license-files")
    assert metadata.metadata("srl")["License-Expression"] == "Apache-2.0", "reinstall srl (pip install -e .)"
    # negative controls: another license, and the standard text with one word changed
    assert license_problems("MIT License\n\nCopyright (c) 2026\n") != []
    changed = text.replace("irrevocable", "revocable", 1)
    assert changed != text and license_problems(changed) != []


# -- the citation ----------------------------------------------------------------------------------
def test_citation_cff_names_srl_and_the_paper() -> None:
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff_problems(cff) == [], cff_problems(cff)
    assert cff["type"] == "software"
    assert cff["license"] == pyproject()["project"]["license"]
    version, date = newest_milestone((ROOT / "CHANGELOG.md").read_text())
    assert (str(cff["version"]), str(cff["date-released"])) == (version, date)
    # negative controls: a required key missing, the paper missing, the paper's authors changed
    assert cff_problems({k: v for k, v in cff.items() if k != "title"}) != []
    assert cff_problems({**cff, "references": []}) != []
    wrong = {**cff["references"][0], "authors": cff["references"][0]["authors"][:-1]}
    assert cff_problems({**cff, "references": [wrong]}) != []
    assert cff_problems(["not", "a", "mapping"]) != []


def test_readme_bibtex_is_the_paper_of_citation_cff() -> None:
    bibtex = readme_bibtex()
    entries = [line for line in bibtex.splitlines() if not line.lstrip().startswith("%")]
    entry = "\n".join(entries)
    assert re.match(r"@\w+\{[\w:-]+,", entry), entry
    title = re.search(r"^\s*title\s*=\s*\{(.*)\},?$", entry, flags=re.M)
    author = re.search(r"^\s*author\s*=\s*\{(.*)\},?$", entry, flags=re.M)
    assert title and author, entry
    assert title.group(1) == PAPER_TITLE
    names = [tuple(reversed(name.split(", "))) for name in author.group(1).split(" and ")]
    assert names == PAPER_AUTHORS, names
    assert entry.count("{") == entry.count("}"), "unbalanced braces"
    assert "CITATION.cff" in (ROOT / "README.md").read_text().split("\n## Citing\n", 1)[1]
