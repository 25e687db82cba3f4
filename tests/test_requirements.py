"""Tests that need more than python3 are skipped on a machine without it, with one line saying what
and how (tests/conftest.py), and ``SRL_TEST_REQUIRE_ALL=1`` (CI) makes every such skip a failure.

Each case runs a small test file through pytest (pytester, in process) with the real conftest and
the machine's requirement check replaced by a fake one, so that it holds as root and not.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests import netns

CONFTEST = (Path(__file__).parent / "conftest.py").read_text()
TEST_FILE = """
import pytest

@pytest.mark.needs_root
def test_needs_root():
    pass

def test_plain():
    pass
"""
MARKERS = """
[pytest]
markers =
    needs_root: test
    slow: test
"""


def _run(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch, missing: list[str], require_all: str | None
) -> pytest.RunResult:
    monkeypatch.setattr(netns, "missing_requirements", lambda: missing)
    if require_all is None:
        monkeypatch.delenv("SRL_TEST_REQUIRE_ALL", raising=False)
    else:
        monkeypatch.setenv("SRL_TEST_REQUIRE_ALL", require_all)
    pytester.makeini(MARKERS)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(test_probe=TEST_FILE)
    return pytester.runpytest("-ra", "-p", "no:cacheprovider")


def test_missing_root_skips_with_one_line_saying_what_and_how(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    result = _run(pytester, monkeypatch, ["network namespaces and iptables need root (running as uid 1000)"], None)
    result.assert_outcomes(passed=1, skipped=1)
    assert result.ret == 0
    lines = [line for line in result.outlines if line.startswith("SKIPPED")]
    assert len(lines) == 1, result.outlines
    assert "needs_root: network namespaces and iptables need root" in lines[0]
    assert "sudo ./srl test test_probe.py" in lines[0]


def test_require_all_turns_the_skip_into_a_failure(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    result = _run(pytester, monkeypatch, ["`iptables` not found on PATH (apt-get install -y iptables)"], "1")
    result.assert_outcomes(passed=1, errors=1)  # a failure in setup
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    assert any(
        "SRL_TEST_REQUIRE_ALL is set and this test cannot run" in line and "iptables" in line
        for line in result.outlines
    ), result.outlines


def test_require_all_fails_a_session_with_any_skip(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SRL_TEST_REQUIRE_ALL", "1")
    pytester.makeini(MARKERS)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(test_probe="import pytest\n\ndef test_skips():\n    pytest.skip('no reason to run')\n")
    result = pytester.runpytest("-p", "no:cacheprovider")
    result.assert_outcomes(skipped=1)
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    result.stdout.fnmatch_lines(["*SRL_TEST_REQUIRE_ALL is set: 1 test(s) skipped, failing the run*"])


def test_machine_with_everything_runs_the_test(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    result = _run(pytester, monkeypatch, [], "1")
    result.assert_outcomes(passed=2)
    assert result.ret == 0


def test_missing_compiler_skips_the_jit_build_test_with_one_line(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    import shutil

    monkeypatch.setattr(shutil, "which", lambda name: None)  # no gcc, no cc on this "machine"
    monkeypatch.delenv("SRL_TEST_REQUIRE_ALL", raising=False)
    pytester.makeini(MARKERS + "    needs_compiler: test\n")
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(
        test_probe=(
            "import pytest\n\n@pytest.mark.needs_compiler\ndef test_jit():\n    pass\n\ndef test_plain():\n    pass\n"
        )
    )
    result = pytester.runpytest("-ra", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, skipped=1)
    lines = [line for line in result.outlines if line.startswith("SKIPPED")]
    assert len(lines) == 1 and "needs_compiler: no C compiler (gcc or cc) on PATH" in lines[0], result.outlines
    assert "apt-get install gcc" in lines[0]
