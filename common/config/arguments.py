"""Settings from the command line: which settings flags each command takes, their help with the
packaged defaults, and the resolved :class:`~common.config.settings.Settings` (flags > environment >
``--config`` > common/config/srl.toml). Shared by every service's ``__main__`` and the ``srl`` tools.
"""

from __future__ import annotations

import argparse
import functools
import logging
import math
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn, get_args

from pydantic import ValidationError
from pydantic_settings import SettingsError

from common.config.settings import MAX_HORIZON, TABLE_SETTINGS, WORKSPACE_HALF_WIDTH, Settings, parse_start

log = logging.getLogger(__name__)


class UsageError(Exception):
    """A problem with what the user asked for: printed as one clear line, exit code 2."""


_NUMBER = r"(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
_NEGATIVE_NUMBERS = re.compile(rf"^-{_NUMBER}(,[-+]?{_NUMBER})*$")


class Parser(argparse.ArgumentParser):
    """argparse, but ``--start -1.2,0.7`` works: a token of negative numbers is a value.

    argparse takes any token starting with ``-`` for an option unless it looks like ONE negative
    number (its ``_negative_number_matcher``); lists such as ``-1.2,0.7`` and exponents such as
    ``-1e9`` are widened into that class. No srl option looks like a number, so nothing is lost.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBERS

    def error(self, message: str) -> NoReturn:
        """One line (argparse adds its usage block first): what is wrong and where help is."""
        self.exit(2, f"{self.prog}: error: {message} (see: {self.prog} --help)\n")


def floats_arg(count: int) -> Callable[[str], tuple[float, ...]]:
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(part) for part in text.split(","))
        except ValueError as error:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}") from error
        if len(values) != count or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"expected {count} finite comma-separated numbers, got {text!r}")
        return values

    return parse


MODES = ("realtime", "lockstep")


def add_mode_argument(parser: argparse.ArgumentParser) -> None:
    """--mode, as the actor, the simulator and ``srl up`` take it (one definition of its meaning)."""
    parser.add_argument(
        "--mode",
        choices=MODES,
        default="realtime",
        help="realtime: every delta by the clock; lockstep: the actor steps the plant (default: realtime)",
    )


def add_lifetime_arguments(
    parser: argparse.ArgumentParser, run_help: str = "stop after this long (default: until signalled)"
) -> None:
    """--run-seconds and --connect-timeout, as every long-running service process takes them."""
    parser.add_argument("--run-seconds", type=float, help=run_help)
    add_connect_timeout_argument(parser)


CONNECT_TIMEOUT_SECONDS = 30.0


def add_connect_timeout_argument(parser: argparse.ArgumentParser) -> None:
    """--connect-timeout, as every process that joins a running system takes it (services, srl record,
    srl view, srl status): how long to wait for the router before one clear error."""
    parser.add_argument(
        "--connect-timeout",
        type=float,
        default=CONNECT_TIMEOUT_SECONDS,
        help=f"[s] wait this long for the router (default: {CONNECT_TIMEOUT_SECONDS:g})",
    )


def add_seconds_argument(
    parser: argparse.ArgumentParser,
    default: float | None = None,
    helptext: str = "stop after this long (default: until Ctrl-C)",
) -> None:
    """--seconds: how long a tool runs [s]; without a default, until Ctrl-C (srl record, view,
    status), with one, a benchmark's real-time run (its help says per what)."""
    parser.add_argument("--seconds", type=float, default=default, help=helptext)


CIRCLE_RADIUS_M = 1.5


def _circle_radius(text: str) -> float:
    try:
        radius = float(text)
    except ValueError:
        radius = math.nan
    if not (math.isfinite(radius) and radius > 0):
        raise argparse.ArgumentTypeError(f"{text}: the start circle's radius must be a positive number of metres")
    return radius


def add_circle_argument(parser: argparse.ArgumentParser) -> None:
    """--circle, as a fleet's plant host (srl plant-sim --robots) and srl up --robots take it: where
    the robots start (common.math.fleet.circle_starts)."""
    parser.add_argument(
        "--circle",
        type=_circle_radius,
        default=CIRCLE_RADIUS_M,
        metavar="R",
        help="with --robots: the robots start evenly on a circle of R metres around the target, "
        f"each heading away from it (default: {CIRCLE_RADIUS_M:g})",
    )


def add_robots_argument(parser: argparse.ArgumentParser, what: str) -> None:
    """--robots, as the actor host, the plant host, the critic and ``srl up`` take it (docs/fleets.md)."""
    parser.add_argument(
        "--robots",
        metavar="IDS|K",
        help=what + "comma-separated robot ids, or a count K for robot1..robotK (default: one robot, --robot)",
    )


def add_robot_endpoints_argument(parser: argparse.ArgumentParser) -> None:
    """--robot-endpoints, for several ROS 2 robots (robot-bridge --robots, srl up --robots --plant robot)."""
    parser.add_argument(
        "--robot-endpoints",
        metavar="NS=ENDPOINT,...",
        help="with --robots: each robot's own Zenoh router, by its ROS namespace (= its robot id), e.g. "
        "tb3_1=tcp/10.0.0.11:7447,tb3_2=tcp/10.0.0.12:7447; robots not named use --robot-endpoint "
        "(default: none; srl up with neither starts an emulated TurtleBot3 per robot)",
    )


def ros_fleet_endpoints(args: argparse.Namespace, robots: list[str], shared_endpoint: str) -> dict[str, str]:
    """Robot id (= ROS namespace) -> its robot's endpoint (common.math.fleet.ros_fleet); one line if wrong.
    ``--namespace`` is refused beside ``--robots``: there each robot's namespace is its id."""
    from common.math.fleet import FleetError, ros_fleet

    if getattr(args, "namespace", None):
        raise UsageError("--namespace with --robots: each robot's ROS namespace is its robot id (--robots tb3_1,tb3_2)")
    try:
        return ros_fleet(robots, getattr(args, "robot_endpoints", None), shared_endpoint)
    except FleetError as error:
        raise UsageError(str(error)) from None


def fleet_robots(args: argparse.Namespace, prefix: str = "robot") -> list[str] | None:
    """The robots of ``--robots`` (None: not given; a count K: ``<prefix>1`` .. ``<prefix>K``); a
    bad list is a :class:`UsageError` (one line). A fleet runs in real time: ``--mode lockstep``
    with ``--robots`` is refused."""
    from common.math.fleet import FleetError, parse_robots

    text = getattr(args, "robots", None)
    if text is None:
        return None
    try:
        robots = parse_robots(text, prefix)
    except FleetError as error:
        raise UsageError(str(error)) from None
    if getattr(args, "mode", "realtime") != "realtime":
        raise UsageError("--robots runs in real time only (a fleet is not stepped in lockstep); use --mode realtime")
    return robots


def add_log_level(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--log-level",
        default="WARNING",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        type=str.upper,
        help="console log level (default: WARNING: warnings and errors only)",
    )


def _start_arg(text: str) -> tuple[float, ...]:
    try:
        return parse_start(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


# The packaged defaults, shown in every option's help (the settings file is the one source).
def _choices(section: str, name: str) -> tuple[str, ...]:
    """The values a setting allows: the rows of its table (TABLE_SETTINGS, read when the parser is
    built: a plugin's rows too), else its ``Literal``: the settings model is their one definition."""
    if (section, name) in TABLE_SETTINGS:
        return TABLE_SETTINGS[(section, name)][1]()
    section_model = Settings.model_fields[section].annotation
    assert section_model is not None
    return tuple(str(v) for v in get_args(section_model.model_fields[name].annotation))


@functools.cache
def _packaged_defaults() -> dict[str, dict[str, Any]]:
    """The packaged srl.toml, read once per process: every option's help quotes it, and a
    process builds the help of ~100 options (callers only read the result)."""
    import tomllib

    from common.config.settings import DEFAULT_CONFIG

    with DEFAULT_CONFIG.open("rb") as file:
        return tomllib.load(file)


def _default(section: str, name: str) -> str:
    value = _packaged_defaults().get(section, {}).get(name)
    if isinstance(value, list):
        value = ",".join(str(v) for v in value)
    return (
        f"(default: {value!r} from common/config/srl.toml)"
        if isinstance(value, str) and not value
        else f"(default: {value}, common/config/srl.toml)"
    )


# Which settings flags each subcommand takes: a flag a command would ignore is refused
# (argparse: "unrecognized arguments"), so a typo'd intent never passes silently.
TRANSPORT_FLAGS = ("config", "router", "robot")
ACTOR_FLAGS = ("agent", "horizon", "solver", "predictor", "no_jit")
EPISODE_FLAGS = ("start", "duration")
ALL_FLAGS = (*TRANSPORT_FLAGS, *ACTOR_FLAGS, *EPISODE_FLAGS)
COMMAND_SETTINGS: dict[str, tuple[str, ...]] = {
    "run": (*ALL_FLAGS, "system"),
    "up": (*ALL_FLAGS, "resume", "system"),
    # the in-process benchmarks set their agents and N themselves (--agents, --horizons)
    "bench actor": ("config", "solver", "predictor", "no_jit"),
    "bench parking": ("config", "solver", "predictor", "no_jit"),
    "bench loop": ALL_FLAGS,
    "bench bridge": ALL_FLAGS,
    "bench fleet": ("config", *ACTOR_FLAGS),  # robots, routers and starts are the fleet's own
    "bench capacity": ("config", *ACTOR_FLAGS),  # the same fleets as bench fleet
    # another system than the robot: the services of one robot (actor, plant-sim, critic)
    "actor": (*ALL_FLAGS, "system"),
    "router": TRANSPORT_FLAGS,
    "plant-sim": (*TRANSPORT_FLAGS, "start", "system"),  # where the simulated robot starts
    "critic": (*TRANSPORT_FLAGS, "agent", "horizon", "resume", "system"),  # the stack names its checkpoint
    "robot-bridge": TRANSPORT_FLAGS,
    "tb3-emulator": (*TRANSPORT_FLAGS, "start"),  # default initial pose
    "status": TRANSPORT_FLAGS,
    # every robot is recorded / shown: no --robot
    "record": ("config", "router"),
    "view": ("config", "router"),
}


def add_settings_arguments(parser: argparse.ArgumentParser, flags: Sequence[str] = ALL_FLAGS) -> None:
    """Flags that override the config file (only those given take effect)."""
    if "config" in flags:
        parser.add_argument(
            "--config",
            type=Path,
            metavar="FILE",
            help="a TOML file overriding common/config/srl.toml (any subset; also SRL_CONFIG) (default: none)",
        )
    if "system" in flags:
        parser.add_argument(
            "--system",
            choices=_choices("plant", "system"),
            help=f"the sampled system to control (docs/reference/variants.md) {_default('plant', 'system')}",
        )
    if "agent" in flags:
        parser.add_argument(
            "--agent",
            choices=_choices("actor", "agent"),
            help=f"the stacked actor's objective {_default('actor', 'agent')}",
        )
    if "horizon" in flags:
        parser.add_argument(
            "--horizon",
            type=int,
            metavar="N",
            help=f"N (N - 1 held actions), 2..{MAX_HORIZON}, or 0 for the system's own (default: the "
            "system's own, the robot's 12; actor.horizon)",
        )
    if "start" in flags:
        parser.add_argument(
            "--start",
            type=_start_arg,
            metavar="X,Y[,ALPHA]",
            help="start in the goal frame [m, m, rad]; X,Y heads away from the target, e.g. --start "
            "-1.2,0.7; another system than the robot: its whole state, comma-separated "
            "(default: the system's own, the robot's 2,2)",
        )
    if "duration" in flags:
        parser.add_argument(
            "--duration", type=float, metavar="SECONDS", help=f"episode length [s] {_default('episode', 'duration')}"
        )
    if "solver" in flags:
        parser.add_argument(
            "--solver",
            choices=_choices("actor", "solver"),
            help=f"NLP solver of the actor {_default('actor', 'solver')}",
        )
    if "predictor" in flags:
        parser.add_argument(
            "--predictor",
            choices=_choices("actor", "predictor"),
            help=f"the actor's state predictor {_default('actor', 'predictor')}",
        )
    if "no_jit" in flags:
        parser.add_argument(
            "--no-jit",
            action="store_true",
            help="do not JIT-compile the actor problem with the C compiler (default: compile)",
        )
    if "router" in flags:
        parser.add_argument(
            "--router", metavar="ENDPOINT", help=f"Zenoh router endpoint {_default('transport', 'router')}"
        )
    if "robot" in flags:
        parser.add_argument(
            "--robot", metavar="ID", help=f"robot id, the <robot> chunk of every key {_default('transport', 'robot')}"
        )
    if "resume" in flags:
        parser.add_argument(
            "--resume",
            action="store_true",
            help="start the critic from its checkpoint of an earlier run of this robot and stack "
            "(default: a fresh critic per run; setting critic.resume)",
        )


SETTINGS_FLAGS = ("config", "system", "agent", "horizon", "start", "duration", "solver", "predictor", "router", "robot")


def settings_argv(args: argparse.Namespace) -> list[str]:
    """The settings flags that were given, as argv, to hand the same settings to children.

    A child gets only the flags its subcommand takes: :func:`child_argv` filters."""
    argv: list[str] = []
    for name in SETTINGS_FLAGS:
        value = getattr(args, name, None)
        if value is None:
            continue
        if name == "start":
            value = ",".join(repr(float(c)) for c in value)
        argv.append(f"--{name}={value}")
    for name in ("no_jit", "resume"):
        if getattr(args, name, False):
            argv.append(f"--{name.replace('_', '-')}")
    return argv


def child_argv(argv: list[str]) -> list[str]:
    """``[command, ...]`` without the settings flags ``command`` does not take (it would refuse them)."""
    takes = COMMAND_SETTINGS.get(argv[0]) if argv else None
    if takes is None:
        return argv
    known = {f"--{n.replace('_', '-')}" for n in (*ALL_FLAGS, "resume", "system")}
    return [a for a in argv if a.split("=", 1)[0] not in known or a.split("=", 1)[0][2:].replace("-", "_") in takes]


BRIDGE_FLAGS = ("profile", "ros_distro", "domain_id", "namespace", "cmd_type", "robot_endpoint")


def add_bridge_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of the robot bridge's [bridge] settings (srl up, robot-bridge, tb3-emulator)."""
    parser.add_argument(
        "--profile",
        choices=_choices("bridge", "profile"),
        help="robot wire profile: rmw_zenoh (rmw_zenoh_cpp) or ros2dds (zenoh-bridge-ros2dds) "
        f"{_default('bridge', 'profile')}",
    )
    parser.add_argument(
        "--ros-distro",
        choices=_choices("bridge", "ros_distro"),
        help=f"the robot's ROS 2 distribution {_default('bridge', 'ros_distro')}",
    )
    parser.add_argument("--domain-id", type=int, help=f"the robot's ROS_DOMAIN_ID {_default('bridge', 'domain_id')}")
    parser.add_argument("--namespace", help=f"the robot's ROS namespace (e.g. tb3_1) {_default('bridge', 'namespace')}")
    parser.add_argument(
        "--cmd-type",
        choices=_choices("bridge", "cmd_type"),
        help=f"cmd_vel message type (auto: read from the robot's liveliness tokens) {_default('bridge', 'cmd_type')}",
    )
    parser.add_argument(
        "--robot-endpoint",
        help="the robot's Zenoh router, e.g. tcp/192.168.1.20:7447 "
        f"(srl up: no emulator is started) {_default('bridge', 'robot_endpoint')}",
    )


def bridge_argv(args: argparse.Namespace) -> list[str]:
    """The bridge flags that were given, as argv, for the bridge and emulator children."""
    return [
        f"--{name.replace('_', '-')}={getattr(args, name)}"
        for name in BRIDGE_FLAGS
        if getattr(args, name, None) is not None
    ]


def settings_from_args(args: argparse.Namespace, any_system: bool = False) -> Settings:
    """The settings of a command line (flags > ``SRL_*`` > ``--config`` > srl.toml); UsageError (one
    line) for invalid ones, and, unless ``any_system`` (``srl run``, ``srl up`` and the services in
    lockstep, the critic), for a system other than the robot: the other commands carry the robot's
    pose (:meth:`Settings.robot_only`)."""
    overrides: dict[str, dict[str, Any]] = {"actor": {}, "episode": {}, "transport": {}, "bridge": {}}
    for name in BRIDGE_FLAGS:
        if getattr(args, name, None) is not None:
            overrides["bridge"][name] = getattr(args, name)
    for name in ("router", "robot", "connect"):  # connect: srl router's links to other routers
        if getattr(args, name, None) is not None:
            overrides["transport"][name] = getattr(args, name)
    for name in ("agent", "horizon", "solver", "predictor"):
        if getattr(args, name, None) is not None:
            overrides["actor"][name] = getattr(args, name)
    if getattr(args, "system", None) is not None:
        overrides["plant"] = {"system": args.system}
    if getattr(args, "no_jit", False):
        overrides["actor"]["jit"] = False
    if getattr(args, "resume", False):
        overrides["critic"] = {"resume": True}
    if getattr(args, "start", None) is not None:
        overrides["episode"]["start"] = args.start
    if getattr(args, "duration", None) is not None:
        overrides["episode"]["duration"] = args.duration
    try:
        settings = Settings.load(getattr(args, "config", None), **{k: v for k, v in overrides.items() if v})
    except ValidationError as error:
        problems = "; ".join(_setting_problem(e, overrides) for e in error.errors())
        raise UsageError(f"invalid settings: {problems}") from error
    except SettingsError as error:  # an SRL_... variable that is not even JSON where a list is due
        raise UsageError(f"invalid settings: {error} (check the SRL_* environment variables)") from error
    except (FileNotFoundError, ValueError) as error:
        raise UsageError(str(error)) from error
    if not any_system:
        try:
            settings.robot_only(f"srl {getattr(args, 'command', None) or 'this command'}")
        except ValueError as error:
            raise UsageError(str(error)) from error
    x, y = settings.start_state()[:2]
    if settings.system.wheeled and max(abs(x), abs(y)) > WORKSPACE_HALF_WIDTH:
        log.warning(
            "start (%g, %g) m is more than %g m from the target: outside any workspace the robot "
            "could park in (the paper's starts are within 2 m)",
            x,
            y,
            WORKSPACE_HALF_WIDTH,
        )
    return settings


def _setting_problem(error: Any, overrides: dict[str, dict[str, Any]]) -> str:
    """One validation error, naming where the bad value came from (flag, variable or file)."""
    loc = [str(p) for p in error["loc"]]
    where = ".".join(loc)
    message = f"{where}: {error['msg']}"
    if len(loc) >= 2 and loc[1] not in overrides.get(loc[0], {}):
        variable = f"SRL_{loc[0]}__{loc[1]}".upper()
        for name, value in os.environ.items():
            if name.upper() == variable:
                return f"{message} (from the environment variable {name}={value!r})"
    return message


# -- srl run ---------------------------------------------------------------------------
