"""Test-wide isolation: no test reads or writes the user's real critic checkpoint."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture(autouse=True)
def critic_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    # Settings read SRL_<SECTION>__<NAME>; service processes started by a test inherit it.
    """The checkpoint template of this test (``{robot}`` = robot id)."""
    path = tmp_path / "critic-{robot}.json"
    monkeypatch.setenv("SRL_CRITIC__CHECKPOINT", str(path))
    monkeypatch.setenv("SRL_RUNS_DIR", str(tmp_path / "runs"))  # srl up's JSON summaries
    yield path


@pytest.fixture
def no_srl_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """No ``SRL_*`` variable set (tests of how settings are resolved, from files and flags only)."""
    import os

    for name in list(os.environ):
        if name.upper().startswith("SRL_"):
            monkeypatch.delenv(name)
