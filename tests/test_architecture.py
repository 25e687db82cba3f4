"""The architecture as rules over the imports, each with a negative control (as test_purity.py).

Floors, from the ground up: ``common/`` -> ``services/<name>/`` (one folder per process of the
system) -> ``tools/`` (the ``srl`` command, the launcher, benchmarks, the experiment, recordings).
``common/`` has floors of its own, one folder each, from the ground up (docs/architecture.md):

    system/     the operating system, no srl concept: die with the parent, absolute-time ticks,
                atomic files, the JIT build of compiled code
    math/       numbers and arrays: dynamics, features, critics, the actor, Algorithm 1, models
    contracts/  what crosses a process boundary: keys, wire messages, run summaries, ROS 2 wire
    config/     settings (the one srl.toml), their command-line flags, Settings -> math objects
    net/        the Zenoh transport (the only module of common that imports zenoh), security
    process/    a service process's life: signals, the session, its summary, its exit

Read from the source text (every import, also those inside functions), never by importing:

* services never import tools; common never imports services or tools;
* a module of a floor of ``common`` imports ``common`` only from its own floor or one below;
* ``common/net/transport.py`` is the only module of common that imports zenoh, also inside a
  function (test_purity.py checks what importing a module loads; a function's import runs later);
* no module reads or writes another module's underscore names.

The floors are the folders: a new module is ruled by where it is put, and a folder of
``common`` that is not a floor fails :func:`test_every_folder_of_common_is_a_floor`.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "services", "tools")
COMMON_FLOORS = ("system", "math", "contracts", "config", "net", "process")  # from the ground up
ZENOH_GATE = "common.net.transport"  # the only module of common that imports zenoh (test_purity.py)
# Private names of other libraries that our code uses on purpose, each with its reason.
FOREIGN_PRIVATE = {
    "_choices_actions": "argparse: the subcommands' help lines (tools/cli.py fills in descriptions)",
    "_actions": "argparse: every argument of a parser, for the generated CLI reference (tools/docs/reference.py)",
    "_negative_number_matcher": "argparse: lists of negative numbers as values (common/process/runtime.py Parser)",
    "_run_exitfuncs": "atexit: run the handlers before os._exit (common/process/runtime.py entry)",
    "_exit": "os: leave without the interpreter's finalization once Zenoh ran (common/process/runtime.py, lifeline.py)",
}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def sources() -> Iterator[tuple[str, str]]:
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            yield module_name(path), path.read_text()


def imports(source: str, module: str) -> set[str]:
    """Every module ``source`` imports (absolute names; ``from . import x`` resolved)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = module.split(".")[: -node.level] if node.level else []
                base = ".".join([*parent, base] if base else parent)
            found.add(base)
    return found


def under(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def common_floor(module: str) -> int | None:
    """The height of ``module``'s floor in ``common`` (0 = math), None outside the floors."""
    parts = module.split(".")
    if parts[0] != "common" or len(parts) < 2 or parts[1] not in COMMON_FLOORS:
        return None
    return COMMON_FLOORS.index(parts[1])


def floor_violations(module: str, source: str) -> list[str]:
    found = imports(source, module)
    problems = []
    if under(module, ("services",)):
        problems += [
            f"{module} imports {name} (services never import tools)" for name in found if under(name, ("tools",))
        ]
    if under(module, ("common",)):
        problems += [
            f"{module} imports {name} (common never imports services or tools)"
            for name in found
            if under(name, ("services", "tools"))
        ]
        height = common_floor(module)
        for name in found:
            theirs = common_floor(name)
            if height is not None and theirs is not None and theirs > height:
                problems.append(
                    f"{module} imports {name} (common/{COMMON_FLOORS[height]}/ never imports the floor "
                    f"above it, common/{COMMON_FLOORS[theirs]}/)"
                )
        if module != ZENOH_GATE:
            problems += [
                f"{module} imports {name} (only {ZENOH_GATE} imports zenoh)"
                for name in found
                if under(name, ("zenoh",))
            ]
    return problems


def private_violations(module: str, source: str) -> list[str]:
    """``from ours import _x``, ``ours_module._x`` and ``obj._x`` on anything but self/cls."""
    tree = ast.parse(source)
    ours = {
        alias.asname or alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import)
        for alias in node.names
        if under(alias.name, PACKAGES)
    }
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and under(node.module or "", PACKAGES):
            problems += [
                f"{module} imports {node.module}.{a.name}"
                for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")
            ]
        elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            owner = node.value
            if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
                continue
            if node.attr in FOREIGN_PRIVATE and not (isinstance(owner, ast.Name) and owner.id in ours):
                continue
            problems.append(f"{module}:{node.lineno} uses .{node.attr} of {ast.unparse(owner)}")
    return problems


def test_every_package_is_read() -> None:
    names = {name for name, _ in sources()}
    assert {"common.math.loop", "common.process.runtime", "services.actor.service", "tools.cli"} <= names


def test_every_folder_of_common_is_a_floor() -> None:
    folders = {p.name for p in (ROOT / "common").iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(COMMON_FLOORS)
    loose = sorted(p.name for p in (ROOT / "common").glob("*.py") if p.name != "__init__.py")
    assert loose == [], f"modules of common outside a floor: {loose}"


def test_the_folder_rule_catches_a_module_outside_the_floors() -> None:
    assert common_floor("common.loose") is None
    assert common_floor("common.system.jit") == 0
    assert common_floor("common.process.runtime") == len(COMMON_FLOORS) - 1


def test_no_import_runs_up_a_floor() -> None:
    problems = [p for name, source in sources() for p in floor_violations(name, source)]
    assert problems == []


def test_no_module_uses_another_modules_underscore_names() -> None:
    problems = [p for name, source in sources() for p in private_violations(name, source)]
    assert problems == []


@pytest.mark.parametrize(
    ("module", "source", "expected"),
    [
        ("services.actor.service", "from tools.cli import main\n", "services never import tools"),
        ("services.critic.command", "def f():\n    import tools.launch.up\n", "services never import tools"),
        ("common.process.runtime", "from services.actor import command\n", "common never imports services or tools"),
        ("common.contracts.keys", "import tools.launch.health\n", "common never imports services or tools"),
        ("common.math.loop", "from common.config.settings import Settings\n", "never imports the floor above it"),
        ("common.math.actor", "def f():\n    from common.net.transport import Bus\n", "never imports the floor above"),
        ("common.contracts.keys", "from common.config import settings\n", "common/contracts/ never imports"),
        ("common.config.arguments", "from common.process.runtime import serve\n", "common/config/ never imports"),
        ("common.math.critic", "import zenoh\n", "only common.net.transport imports zenoh"),
        ("common.system.jit", "from common.math.actor import StackedActor\n", "common/system/ never imports"),
        ("common.process.runtime", "def f():\n    import zenoh\n", "only common.net.transport imports zenoh"),
        ("common.contracts.keys", "from zenoh.ext import z_serialize\n", "only common.net.transport imports zenoh"),
    ],
)
def test_the_floor_rules_catch_an_upward_import(module: str, source: str, expected: str) -> None:
    problems = floor_violations(module, source)
    assert len(problems) == 1 and expected in problems[0]


@pytest.mark.parametrize(
    "source",
    [
        "from services.actor.service import _run_lockstep\n",
        "import common.net.transport\ncommon.net.transport._threads\n",
        "def f(port):\n    port._settings = 1\n",
        "def f(bus):\n    return bus._keep\n",
    ],
)
def test_the_private_rule_catches_another_modules_underscore_name(source: str) -> None:
    assert len(private_violations("tools.experiment.runner", source)) == 1


def test_the_private_rule_allows_own_names() -> None:
    source = (
        "class A:\n    def f(self):\n        return self._x, type(self).__name__\n    @classmethod\n"
        "    def g(cls):\n        return cls._y\n"
    )
    assert private_violations("common.x", source) == []
