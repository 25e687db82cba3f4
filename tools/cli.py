"""The ``srl`` command: one subcommand per service or tool.

Each subcommand is one module with ``NAME``, ``HELP``, optionally ``DESCRIPTION`` (its ``--help``
opening; else ``HELP`` as a sentence), ``add_arguments(parser)`` (which sets ``func``) and
``main(args)``: tools/commands/<name>.py, services/<name>/command.py, tools/experiment/command.py,
tools/launch/health.py, tools/docs/command.py. This module only lists them, in the order
``srl --help`` shows them. ``python -m tools.cli ...`` runs the same code; logging is configured
once, in common.process.runtime.main.
"""

from __future__ import annotations

import argparse
import tomllib
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import Any

from common.config.arguments import Parser, add_log_level
from common.process.runtime import entry as runtime_entry
from common.process.runtime import main as runtime_main

DESCRIPTION = """srl: stacked RL-QV (actor, critic, plant) as Zenoh services, and the tools around them.

Settings come from common/config/srl.toml, overridden by --config FILE (or SRL_CONFIG), by
SRL_<SECTION>__<NAME> environment variables and by the flags of each subcommand. SRL_PLUGINS
(files or modules, comma-separated) adds your own agents and plant models (docs/extending.md).
Start with:  srl run            (one episode in this process)
             srl up             (router + every service as processes, a live status line)
"""


PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def version() -> str:
    """srl's version: the installed package's metadata, written from pyproject.toml's ``version``
    (the newest milestone of CHANGELOG.md) at install; that file itself where srl is not installed
    (the source tree on ``PYTHONPATH``)."""
    try:
        return metadata.version("srl")
    except metadata.PackageNotFoundError:
        return str(tomllib.loads(PYPROJECT.read_text())["project"]["version"])


class VersionAction(argparse.Action):
    """``srl --version``: ``srl X.Y.Z`` on stdout, exit 0 (argparse's own version action, but the
    version is looked up only when asked for)."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(
        self, parser: argparse.ArgumentParser, namespace: Any, values: Any, option_string: str | None = None
    ) -> None:
        print(f"srl {version()}")
        parser.exit()


def command_modules() -> list[ModuleType]:
    """Every subcommand's module, in ``srl --help`` order (imported here: building the parser
    imports no service's or tool's heavy libraries, each command imports those when it runs)."""
    from services.actor import command as actor
    from services.critic import command as critic
    from services.plant_sim import command as plant_sim
    from services.robot_bridge import command as robot_bridge
    from services.tb3_emulator import command as tb3_emulator
    from tools.commands import bench, build, certs, plot, record, router, run, status, up, view
    from tools.docs import command as docs
    from tools.experiment import command as experiment
    from tools.launch import health

    return [
        run,
        certs,
        router,
        plant_sim,
        critic,
        actor,
        robot_bridge,
        tb3_emulator,
        up,
        bench,
        status,
        record,
        plot,
        view,
        experiment,
        build,
        health,
        docs,
    ]


def sentence(text: str) -> str:
    """A help line as the opening sentence of a ``--help``: capitalized, with a full stop."""
    return text[:1].upper() + text[1:] + "."


def add_command(sub: Any, module: ModuleType) -> None:
    """Register one subcommand module (``NAME``, ``HELP``, ``add_arguments``) on ``sub``, the
    ``srl`` parser's subparsers."""
    description = getattr(module, "DESCRIPTION", None) or sentence(module.HELP)
    module.add_arguments(sub.add_parser(module.NAME, help=module.HELP, description=description))


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="srl", description=DESCRIPTION)
    add_log_level(parser)
    parser.add_argument("--version", action=VersionAction, help="print srl's version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in command_modules():
        add_command(sub, module)
    # the parser itself, for the commands that describe every command (srl docs: the CLI reference)
    parser.set_defaults(srl_parser=parser)
    for action in sub._choices_actions:  # every subcommand's --help opens with what it does
        subparser = sub.choices[action.dest]
        if not subparser.description:
            subparser.description = sentence(action.help or "")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``srl ARGS`` in this process (tests, benchmarks): the exit code."""
    return runtime_main(build_parser(), argv)


def entry(argv: Sequence[str] | None = None) -> None:
    """The ``srl`` console command (common.process.runtime.entry: exit codes, the exit after Zenoh)."""
    runtime_entry(build_parser, argv)


if __name__ == "__main__":
    entry()
