"""``common`` is pure: importing any of it never pulls in zenoh or ROS (rclpy).

Checked in a fresh interpreter, since this test process may already have imported them.
Each module is blamed for the forbidden modules that appear right after importing it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import common

pytestmark = pytest.mark.integration

ROOT = Path(common.__file__).resolve().parent.parent
FORBIDDEN = ("zenoh", "rclpy")

_PROBE = """
import importlib, json, pkgutil, sys
FORBIDDEN = {forbidden!r}
def forbidden():
    return {{m for m in sys.modules if m.split(".")[0] in FORBIDDEN}}
blame = {{}}
before = forbidden()
if before:
    blame["<interpreter start>"] = sorted(before)
import common
names = ["common"] + sorted(m.name for m in pkgutil.walk_packages(common.__path__, "common."))
for name in names:
    if name in {skip!r}:
        continue
    importlib.import_module(name)
    new = forbidden() - before
    if new:
        blame[name] = sorted(new)
    before |= new
{extra}
print(json.dumps({{"modules": names, "blame": blame, "loaded": sorted(forbidden())}}))
"""


def _probe(extra: str = "", skip: tuple[str, ...] = ()) -> dict:
    code = _PROBE.format(extra=extra, forbidden=FORBIDDEN, skip=skip)
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


# common/net/transport.py is the ONLY module of common that imports zenoh (docs/architecture.md).
# Everything else -- the math, the messages, the keys, the settings, the loop -- stays free of it.
ALLOWED_TO_IMPORT_ZENOH = ("common.net.transport",)


def test_common_modules_are_free_of_zenoh_and_ros() -> None:
    report = _probe(skip=ALLOWED_TO_IMPORT_ZENOH)
    # every module of the package was imported (the probe did its job)
    expected = {
        ".".join(p.relative_to(ROOT).with_suffix("").parts)
        for p in (ROOT / "common").rglob("*.py")
        if p.stem != "__init__"
    }
    assert expected - set(ALLOWED_TO_IMPORT_ZENOH) <= set(report["modules"])
    assert {
        "common.math.dynamics",
        "common.math.features",
        "common.math.critic",
        "common.math.actor",
        "common.config.settings",
        "common.math.loop",
    } <= set(report["modules"])
    assert report["blame"] == {}, f"modules of common that import zenoh/rclpy: {report['blame']}"
    assert report["loaded"] == []


def test_only_the_transport_module_imports_zenoh_and_nothing_imports_ros() -> None:
    report = _probe()
    assert set(report["blame"]) <= set(ALLOWED_TO_IMPORT_ZENOH), report["blame"]
    assert not [m for m in report["loaded"] if m.split(".")[0] == "rclpy"]


def test_probe_detects_a_forbidden_import() -> None:
    # the same probe flags zenoh when something does import it (the check can fail)
    pytest.importorskip("zenoh")
    report = _probe(extra="import zenoh", skip=("common.net.transport",))
    assert "zenoh" in report["loaded"]
