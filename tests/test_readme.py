"""The README's first command and the container commands, as a user reads them.

* The first command is run as written and prints the J the README quotes next to it.
* The compose commands of docs/getting-started.md ("In containers") are, character for character,
  the ones .ci/compose-test runs (its ``readme_*`` lines): CI runs exactly what a user reads, and
  every compose command there is run by CI or says "(not in CI)".

Every other command of the README and the docs is run by tests/test_docs.py (its ```bash blocks),
or is marked not run with its reason.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess

import pytest

from tests.harness import ROOT

README = (ROOT / "README.md").read_text()
GETTING_STARTED = (ROOT / "docs" / "getting-started.md").read_text()
COMPOSE_TEST = (ROOT / ".ci" / "compose-test").read_text()
NOT_IN_CI = "(not in CI)"
# a comment: `#` after whitespace, followed by whitespace (not `"*"`, not `--start=-1,2`)
COMMENT = re.compile(r"\s+#(?:\s.*)?$")
J_IN_OUTPUT = re.compile(r"\bJ\b[^0-9\n-]*(-?[0-9]+\.[0-9]+)")


def bash_commands(text: str) -> list[tuple[str, str]]:
    """(command, its comment) of every logical line of every ```bash block, continuations joined."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        logical = ""
        for line in block.splitlines():
            body = COMMENT.sub("", line)
            comment = line[len(body) :].strip()
            if body.rstrip().endswith("\\"):
                logical += body.rstrip()[:-1].strip() + " "
                continue
            logical += body.strip()
            if logical:
                commands.append((logical, comment))
            logical = ""
    return commands


def section(text: str, title: str) -> str:
    start = text.index(f"\n## {title}")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else None]


def compose_test_commands() -> list[str]:
    return re.findall(r"^readme_\w+='(.*)'$", COMPOSE_TEST, flags=re.M)


def run(argv: list[str], timeout: float) -> subprocess.CompletedProcess[str]:
    """Run in a session of its own; on timeout (or any error) its whole process group is killed."""
    process = subprocess.Popen(
        argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        stdout, stderr = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
    return subprocess.CompletedProcess(argv, process.returncode, stdout, stderr)


@pytest.mark.integration
def test_first_command_prints_the_j_the_readme_quotes() -> None:
    command, comment = bash_commands(README)[0]
    assert command.startswith("./srl run "), command
    quoted = re.search(r"J\s+(-?[0-9]+\.[0-9]+)", comment)
    assert quoted, f"the README quotes no J next to its first command: {comment!r}"
    done = run(["bash", "-c", command], timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    printed = J_IN_OUTPUT.search(done.stdout)
    assert printed, done.stdout
    decimals = len(quoted.group(1).split(".")[1])
    print(f"README: J {quoted.group(1)}; `{command}` printed J {printed.group(1)}")
    # the README quotes it to `decimals` places: equal when rounded to them
    assert round(float(printed.group(1)), decimals) == float(quoted.group(1)), (printed.group(1), quoted.group(1))


def test_the_compose_commands_ci_runs_are_the_docs() -> None:
    readme = {command for command, _ in bash_commands(section(GETTING_STARTED, "In containers"))}
    ci = compose_test_commands()
    assert len(ci) >= 5, ci
    assert {"docker compose up", "COMPOSE_PROFILES=demo-robot docker compose up"} <= set(ci)
    missing = [command for command in ci if command not in readme]
    assert not missing, f".ci/compose-test runs commands docs/getting-started.md does not show: {missing}"
    not_run = [
        command
        for command, comment in bash_commands(section(GETTING_STARTED, "In containers"))
        if command not in ci and NOT_IN_CI not in comment
    ]
    assert not not_run, f"compose commands of docs/getting-started.md that .ci/compose-test does not run: {not_run}"
