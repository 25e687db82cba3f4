"""The ``srl`` command: one subcommand per service or tool.

``python -m services.cli ...`` runs the same code. Logging is configured here, once.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from pydantic import ValidationError
from pydantic_settings import SettingsError

from common.lifeline import die_with_parent
from common.provenance import PlantConflictError
from common.security import SecurityError
from common.settings import MAX_HORIZON, WORKSPACE_HALF_WIDTH, Settings, parse_start

log = logging.getLogger(__name__)


class UsageError(Exception):
    """A problem with what the user asked for: printed as one clear line, exit code 2."""


class SignalledError(Exception):
    """Ended by a signal: one line, exit 128 + the signal's number (130 Ctrl-C, 143 SIGTERM)."""

    def __init__(self, signum: int) -> None:
        import signal

        self.signum = signum
        super().__init__(f"{signal.Signals(signum).name}")


class SignalStop(threading.Event):
    """A stop event that remembers the signal that set it."""

    signum: int | None = None


@contextlib.contextmanager
def stop_on_signals() -> Iterator[SignalStop]:
    """SIGINT and SIGTERM set an event (checked between steps) instead of raising inside native
    code: a KeyboardInterrupt raised in a CasADi callback surfaces as ``SystemError ... returned a
    result with an exception set``. The previous handlers are restored after."""
    import signal

    stop = SignalStop()

    def handler(signum: int, _frame: object) -> None:
        if stop.signum is None:
            stop.signum = signum
        stop.set()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for signum, action in previous.items():
            signal.signal(signum, action)


def _start_arg(text: str) -> tuple[float, ...]:
    try:
        return parse_start(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


# The packaged defaults, shown in every option's help (the settings file is the one source).
def _packaged_defaults() -> dict[str, dict[str, Any]]:
    import tomllib

    from common.settings import DEFAULT_CONFIG

    with DEFAULT_CONFIG.open("rb") as file:
        return tomllib.load(file)


def _default(section: str, name: str) -> str:
    value = _packaged_defaults().get(section, {}).get(name)
    if isinstance(value, list):
        value = ",".join(str(v) for v in value)
    return f"(default: {value!r} from common/srl.toml)" if isinstance(value, str) and not value else \
        f"(default: {value}, common/srl.toml)"


# Which settings flags each subcommand takes: a flag a command would ignore is refused
# (argparse: "unrecognized arguments"), so a typo'd intent never passes silently.
TRANSPORT_FLAGS = ("config", "router", "robot")
ACTOR_FLAGS = ("agent", "horizon", "solver", "predictor", "no_jit")
EPISODE_FLAGS = ("start", "duration")
ALL_FLAGS = (*TRANSPORT_FLAGS, *ACTOR_FLAGS, *EPISODE_FLAGS)
COMMAND_SETTINGS: dict[str, tuple[str, ...]] = {
    "run": ALL_FLAGS,
    "up": (*ALL_FLAGS, "resume"),
    "bench": ALL_FLAGS,
    "actor": ALL_FLAGS,
    "router": TRANSPORT_FLAGS,
    "plant-sim": (*TRANSPORT_FLAGS, "start"),  # where the simulated robot starts
    "critic": (*TRANSPORT_FLAGS, "agent", "horizon", "resume"),  # the stack names its checkpoint
    "robot-bridge": TRANSPORT_FLAGS,
    "tb3-emulator": (*TRANSPORT_FLAGS, "start"),  # default initial pose
    "status": TRANSPORT_FLAGS,
}


def add_settings_arguments(parser: argparse.ArgumentParser, flags: Sequence[str] = ALL_FLAGS) -> None:
    """Flags that override the config file (only those given take effect)."""
    if "config" in flags:
        parser.add_argument("--config", type=Path, metavar="FILE",
                            help="a TOML file overriding common/srl.toml (any subset; also SRL_CONFIG) (default: none)")
    if "agent" in flags:
        parser.add_argument("--agent", choices=["mpc", "rlq", "rlqv", "rlqv+"],
                            help=f"the stacked actor's objective {_default('actor', 'agent')}")
    if "horizon" in flags:
        parser.add_argument("--horizon", type=int, metavar="N",
                            help=f"N (N - 1 held actions), 2..{MAX_HORIZON} {_default('actor', 'horizon')}")
    if "start" in flags:
        parser.add_argument("--start", type=_start_arg, metavar="X,Y[,ALPHA]",
                            help="start in the goal frame [m, m, rad]; X,Y heads away from the target, "
                                 f"e.g. --start -1.2,0.7 {_default('episode', 'start')}")
    if "duration" in flags:
        parser.add_argument("--duration", type=float, metavar="SECONDS",
                            help=f"episode length [s] {_default('episode', 'duration')}")
    if "solver" in flags:
        parser.add_argument("--solver", choices=["fatrop", "ipopt"],
                            help=f"NLP solver of the actor {_default('actor', 'solver')}")
    if "predictor" in flags:
        parser.add_argument("--predictor", choices=["euler", "rk4"],
                            help=f"the actor's state predictor {_default('actor', 'predictor')}")
    if "no_jit" in flags:
        parser.add_argument("--no-jit", action="store_true",
                            help="do not JIT-compile the actor problem with the C compiler (default: compile)")
    if "router" in flags:
        parser.add_argument("--router", metavar="ENDPOINT",
                            help=f"Zenoh router endpoint {_default('transport', 'router')}")
    if "robot" in flags:
        parser.add_argument("--robot", metavar="ID",
                            help=f"robot id, the <robot> chunk of every key {_default('transport', 'robot')}")
    if "resume" in flags:
        parser.add_argument("--resume", action="store_true",
                            help="start the critic from its checkpoint of an earlier run of this robot and stack "
                                 "(default: a fresh critic per run; setting critic.resume)")


SETTINGS_FLAGS = ("config", "agent", "horizon", "start", "duration", "solver", "predictor", "router", "robot")


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
    known = {f"--{n.replace('_', '-')}" for n in (*ALL_FLAGS, "resume")}
    return [a for a in argv if a.split("=", 1)[0] not in known
            or a.split("=", 1)[0][2:].replace("-", "_") in takes]


BRIDGE_FLAGS = ("profile", "ros_distro", "domain_id", "namespace", "cmd_type", "robot_endpoint")


def add_bridge_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of the robot bridge's [bridge] settings (srl up, robot-bridge, tb3-emulator)."""
    parser.add_argument("--profile", choices=["rmw_zenoh", "ros2dds"],
                        help="robot wire profile: rmw_zenoh (rmw_zenoh_cpp) or ros2dds (zenoh-bridge-ros2dds) "
                        f"{_default('bridge', 'profile')}")
    parser.add_argument("--ros-distro", choices=["humble", "jazzy"],
                        help=f"the robot's ROS 2 distribution {_default('bridge', 'ros_distro')}")
    parser.add_argument("--domain-id", type=int, help=f"the robot's ROS_DOMAIN_ID {_default('bridge', 'domain_id')}")
    parser.add_argument("--namespace", help=f"the robot's ROS namespace (e.g. tb3_1) {_default('bridge', 'namespace')}")
    parser.add_argument("--cmd-type", choices=["auto", "twist", "twist_stamped"],
                        help="cmd_vel message type (auto: read from the robot's liveliness tokens) "
                        f"{_default('bridge', 'cmd_type')}")
    parser.add_argument("--robot-endpoint", help="the robot's Zenoh router, e.g. tcp/192.168.1.20:7447 "
                        f"(srl up: no emulator is started) {_default('bridge', 'robot_endpoint')}")


def bridge_argv(args: argparse.Namespace) -> list[str]:
    """The bridge flags that were given, as argv, for the bridge and emulator children."""
    return [f"--{name.replace('_', '-')}={getattr(args, name)}" for name in BRIDGE_FLAGS
            if getattr(args, name, None) is not None]


def settings_from_args(args: argparse.Namespace) -> Settings:
    overrides: dict[str, dict[str, Any]] = {"actor": {}, "episode": {}, "transport": {}, "bridge": {}}
    for name in BRIDGE_FLAGS:
        if getattr(args, name, None) is not None:
            overrides["bridge"][name] = getattr(args, name)
    for name in ("router", "robot"):
        if getattr(args, name, None) is not None:
            overrides["transport"][name] = getattr(args, name)
    for name in ("agent", "horizon", "solver", "predictor"):
        if getattr(args, name, None) is not None:
            overrides["actor"][name] = getattr(args, name)
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
    x, y = settings.episode.start[:2]
    if max(abs(x), abs(y)) > WORKSPACE_HALF_WIDTH:
        log.warning("start (%g, %g) m is more than %g m from the target: outside any workspace the robot "
                    "could park in (the paper's starts are within 2 m)", x, y, WORKSPACE_HALF_WIDTH)
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
def cmd_run(args: argparse.Namespace) -> int:
    from common.loop import episode_summary, run_episode

    settings = settings_from_args(args)
    started = time.perf_counter()
    if args.transport == "zenoh":
        # The same Algorithm 1 through the real services: lockstep, synchronous critic.
        from common.loop import Episode
        from services.up import ServiceDiedError, run_up

        try:
            summary = run_up(settings, settings_argv(args), mode="lockstep", plant="sim",
                             sync_critic=True, duration=settings.episode.duration, quiet=not args.verbose)
        except (ServiceDiedError, TimeoutError) as error:
            raise UsageError(str(error)) from error
        episode = Episode(summary["agent"], summary["horizon"],
                          states=[__import__("numpy").array(s) for s in summary["trajectory"]])
    else:
        with stop_on_signals() as stop:
            episode = run_episode(settings, stop=stop)
        if stop.signum is not None:
            raise SignalledError(stop.signum)
        summary = episode_summary(episode, settings)
    summary["wall_seconds"] = time.perf_counter() - started
    summary["transport"] = args.transport
    if args.plot:
        from services.plots import plot_episode

        plot_episode(episode, settings.plant.sampling_time, args.plot)
        summary["plot"] = str(args.plot)
    if not args.trajectory:
        summary.pop("trajectory", None)
    elif "trajectory" not in summary:
        summary["trajectory"] = [[float(c) for c in s] for s in episode.states]
    print(format_run_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0


def format_run_summary(summary: dict[str, Any]) -> str:
    s = summary["settings"]
    solve = summary["solve_ms"]
    lines = [
        f"srl run: agent {summary['agent']}, N = {summary['horizon']}, transport {summary['transport']}",
        f"  start          {_fmt_state(summary['start_state'])}",
        f"  final state    {_fmt_state(summary['final_state'])}   "
        f"distance to target {summary['final_distance']:.3f} m",
        f"  steps          {summary['steps']} x delta = {s['plant']['sampling_time']} s "
        f"({summary['episode_seconds']:.1f} s episode)",
        f"  accumulated J  {summary['accumulated_cost']:.4f}",
        f"  solve [ms]     median {solve['median']:.3f}  p99 {solve['p99']:.3f}  max {solve['max']:.3f}"
        f"   failures {summary['solver_failures']}",
        f"  wall time      {summary['wall_seconds']:.2f} s",
        f"  settings       R = diag{tuple(s['cost']['r_diag'])}, gamma = {s['critic']['discount_rate']} "
        f"(beta = {s['derived']['discount_beta']:.4f}), M = {s['critic']['replay_size']}, "
        f"lambda = {s['critic']['ridge']}, bounds = {s['critic']['weight_bounds'] or 'none'}, "
        f"solver {s['actor']['solver']}, predictor {s['actor']['predictor']}",
    ]
    if "plot" in summary:
        lines.append(f"  plot           {summary['plot']}")
    return "\n".join(lines)


def _fmt_state(state: Sequence[float]) -> str:
    return f"x = {state[0]:+.3f} m, y = {state[1]:+.3f} m, alpha = {state[2]:+.3f} rad"


# -- services -------------------------------------------------------------------------
def _serve(args: argparse.Namespace, service: str, body: Callable[..., dict[str, Any]]) -> int:
    """Common life of a service process: settings, signals, session, run, final JSON line."""
    import signal
    import threading

    from common.transport import Bus

    settings = settings_from_args(args)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    die_with_parent(stop)  # started by srl up: stop when it dies, even by SIGKILL
    bus = connect_with_retry(lambda: Bus.open(settings.transport, service), settings, service,
                             args.connect_timeout, stop)
    try:
        result = body(settings, bus, stop)
    finally:
        bus.close()
    result["resources"] = own_resources()
    print(json.dumps(result), flush=True)
    return 0


# A router that accepts TCP but refuses the session this long is refusing the login (a wrong
# password does not become right); shorter, it may still be starting.
LOGIN_REFUSED_AFTER = 2.0


def connect_with_retry(opener: Callable[[], Any], settings: Settings, service: str, timeout: float,
                       stop: threading.Event) -> Any:
    """Open the Zenoh session, retrying every 0.2 s for ``timeout`` s, and say why it failed.

    "waiting for the router" is said at once; at the end a router that listens but refuses the
    session (secure: the login) is told apart from one that is not there at all, without Zenoh's
    Rust internals (those go to DEBUG)."""
    import zenoh

    transport = settings.transport
    deadline = time.monotonic() + timeout
    refused_since: float | None = None
    said = False
    while True:
        try:
            return opener()
        except zenoh.ZError as error:
            log.debug("%s: zenoh.open: %s", service, error)
            now = time.monotonic()
            listening = _endpoint_listening(transport.router)
            refused_since = (refused_since or now) if listening else None
            if transport.secure and refused_since is not None and now - refused_since >= LOGIN_REFUSED_AFTER:
                raise UsageError(f"{service}: the router at {transport.router} refused the login of user "
                                 f"{transport.user!r}: wrong password or unknown user (check transport.password_file "
                                 "or SRL_TRANSPORT__PASSWORD against the router's users file)") from None
            if now > deadline or stop.is_set():
                if listening:
                    raise UsageError(f"{service}: something listens at {transport.router} but refused a Zenoh "
                                     "session (not a Zenoh router, or it requires a login: transport.secure)") from None
                raise UsageError(f"{service}: cannot reach the Zenoh router at {transport.router} after "
                                 f"{timeout:.0f} s (is `srl router` running? see --router, --connect-timeout)"
                                 ) from None
            if not said:
                log.warning("%s: waiting for the Zenoh router at %s (up to %.0f s)", service, transport.router, timeout)
                said = True
            time.sleep(0.2)


def zenoh_reason(error: Exception) -> str:
    """Zenoh's error text without its Rust source location (`` at /root/.cargo/...rs:447.``)."""
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(error)).strip()


def _endpoint_listening(endpoint: str) -> bool:
    """Whether a TCP-based endpoint (tcp/, tls/, ws/) accepts a plain connection."""
    import socket

    protocol, _, address = endpoint.partition("/")
    if protocol not in ("tcp", "tls", "ws"):
        return False
    host, _, port = address.split("?")[0].split("#")[0].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
            return True
    except (OSError, ValueError):
        return False


def own_resources() -> dict[str, float]:
    """CPU seconds and peak resident memory of this process (for benchmarks)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {"cpu_seconds": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024.0}


def cmd_router(args: argparse.Namespace) -> int:
    import signal
    import threading

    import zenoh

    from common.transport import zenoh_config

    settings = settings_from_args(args)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    die_with_parent(stop)  # started by srl up: stop when it dies, even by SIGKILL
    try:
        session = zenoh.open(zenoh_config(settings.transport, router=True))
    except zenoh.ZError as error:
        raise UsageError(f"router: cannot listen on {settings.transport.router}: {zenoh_reason(error)} "
                         "(another router on that port? choose one with --router)") from error
    # its one line of normal output, on stdout (not a warning): what it serves and how
    transport = settings.transport
    rules = f"; users and access rules of robot {transport.robot} enforced" if transport.secure else ""
    print(f"srl router: router listening on {settings.transport.router} (multicast scouting "
          f"{'on' if settings.transport.multicast_scouting else 'off'}{rules})", flush=True)
    stop.wait()
    session.close()
    print(json.dumps({"service": "router", "endpoint": settings.transport.router,
                      "resources": own_resources()}), flush=True)
    return 0


def cmd_plant_sim(args: argparse.Namespace) -> int:
    from services.plant_sim.service import run

    return _serve(args, "plant", lambda s, bus, stop: run(s, bus, args.mode, stop, args.run_seconds))


def cmd_critic(args: argparse.Namespace) -> int:
    from services.critic.service import run

    return _serve(args, "critic", lambda s, bus, stop: run(s, bus, stop, args.run_seconds))


def cmd_actor(args: argparse.Namespace) -> int:
    from services.actor.service import run

    return _serve(args, "actor", lambda s, bus, stop: run(s, bus, args.mode, stop, args.run_seconds,
                                                          args.sync_critic))


def cmd_robot_bridge(args: argparse.Namespace) -> int:
    from services.robot_bridge.service import run

    return _serve(args, "plant", lambda s, bus, stop: run(s, bus, stop, args.run_seconds))


# The emulator's cmd_vel timeout. 0.5 s is the OpenCR firmware's own HEARTBEAT_TIMEOUT_MS (it
# stops the wheels when turtlebot3_node falls silent for 500 ms) and twist_mux's customary topic
# timeout: five missed 10 Hz commands. At 0.22 m/s a broken command path then costs <= 11 cm.
CMD_TIMEOUT_DEFAULT = 0.5


def cmd_tb3_emulator(args: argparse.Namespace) -> int:
    import signal
    import threading

    import zenoh

    from common.frames import Pose2D, from_goal_frame
    from common.transport import zenoh_config
    from services.robot_bridge import ros_wire
    from services.robot_bridge.ros_wire import CMD_TYPES, DEFAULT_CMD_TYPE, RosGraph
    from services.tb3_emulator.service import Tb3Model, run

    settings = settings_from_args(args)
    bridge = settings.bridge
    if args.initial_pose is not None:
        pose = Pose2D(*args.initial_pose)
    else:  # the episode's start (goal frame) where the bridge's goal puts it in the odom frame
        pose = from_goal_frame(Pose2D(*(float(c) for c in settings.start_state())), Pose2D(*bridge.goal))
    cmd_type = DEFAULT_CMD_TYPE[bridge.ros_distro] if bridge.cmd_type == "auto" else CMD_TYPES[bridge.cmd_type]
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    die_with_parent(stop)  # started by srl up: stop when it dies, even by SIGKILL
    if args.listen:  # the robot's own Zenoh router (like rmw_zenohd on the robot)
        config = zenoh_config(settings.transport, router=True, listen=[args.listen])
        config.insert_json5("connect/endpoints", "[]")
        session = zenoh.open(config)
    else:
        session = connect_with_retry(lambda: zenoh.open(zenoh_config(settings.transport)), settings,
                                     "tb3-emulator", args.connect_timeout, stop)
    v_max = ros_wire.TB3_BURGER_V_MAX if args.v_max is None else args.v_max
    omega_max = ros_wire.TB3_BURGER_OMEGA_MAX if args.omega_max is None else args.omega_max
    model = Tb3Model(pose, v_max, omega_max, args.latency, args.cmd_timeout,
                     (args.noise[0], args.noise[1]), args.seed, time.monotonic())
    try:
        result = run(session, RosGraph.from_settings(bridge), cmd_type, model, stop, args.run_seconds,
                     bridge.odom_topic, bridge.cmd_vel_topic, args.odom_rate, attachment=args.attachment)
    finally:
        session.close()
    result["initial_pose"] = list(pose)
    result["resources"] = own_resources()
    print(json.dumps(result), flush=True)
    return 0


def cmd_certs(args: argparse.Namespace) -> int:
    """``srl certs --out DIR``: TLS material (common/certs.py) and, with --passwords, credentials."""
    from common.certs import write_tls_material
    from common.security import ROLES, write_credentials

    out = Path(args.out).expanduser()
    if (out / "ca.pem").exists():
        if args.if_missing:
            print(f"srl certs: {out} already holds a CA: kept", flush=True)
            return 0
        raise UsageError(f"{out} already holds a CA (ca.pem): choose a new directory (or --if-missing)")
    files = write_tls_material(out, ROLES, args.hosts)
    if args.passwords:
        write_credentials(out)
    print(f"srl certs: CA, router ({', '.join(['localhost', '127.0.0.1', '::1', *args.hosts])}) and "
          f"{', '.join(ROLES)} certificates{' and passwords' if args.passwords else ''} in {files.directory} "
          "(0700, files 0600)", flush=True)
    return 0


def _floats_arg(count: int) -> Callable[[str], tuple[float, ...]]:
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(part) for part in text.split(","))
        except ValueError as error:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}") from error
        if len(values) != count or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"expected {count} finite comma-separated numbers, got {text!r}")
        return values

    return parse


def cmd_up(args: argparse.Namespace) -> int:
    from services.up import ServiceDiedError, Stopped, run_up

    settings = settings_from_args(args)
    run_name = time.strftime("up-%Y%m%d-%H%M%S", time.gmtime()) + f"-{os.getpid()}"
    summary_dir = args.summary_dir or default_runs_dir() / run_name
    started = time.monotonic()

    first_version: list[float] = []

    def show_status(counters: dict[str, float]) -> None:
        line = format_status_line(counters, time.monotonic() - started, first_version)
        print(f"srl up {line}", file=sys.stderr, flush=True)

    try:
        summary = run_up(settings, settings_argv(args), mode=args.mode, plant=args.plant,
                         sync_critic=args.mode == "lockstep", duration=settings.episode.duration,
                         bridge_args=bridge_argv(args), secure=args.secure, on_status=show_status,
                         summary_dir=summary_dir)
    except Stopped as stopped:  # SIGINT, SIGTERM, SIGHUP: everything was stopped, credentials removed
        print(f"srl up: stopped by {stopped}: every service stopped", file=sys.stderr)
        return stopped.exit_code
    except ServiceDiedError as error:
        print(f"srl up: error: {error}", file=sys.stderr)
        for line in error.tail:
            print(f"  [{error.name}] {line}", file=sys.stderr)
        return 1
    except (TimeoutError, ValueError) as error:
        raise UsageError(str(error)) from error
    summary.pop("trajectory", None)
    print(format_up_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0


def default_runs_dir() -> Path:
    """Where ``srl up`` writes its runs' JSON summaries: ``SRL_RUNS_DIR`` or ~/.local/state/srl/runs."""
    return Path(os.environ.get("SRL_RUNS_DIR") or Path.home() / ".local/state/srl/runs")


def format_status_line(c: dict[str, float], elapsed: float, first_version: list[float]) -> str:
    """One line of the actor's 1 Hz status (``srl/<robot>/status/actor``).

    Weight versions are microsecond clock values (they never go back across critic restarts);
    shown is how many versions the actor moved on since this line first saw one, and how many
    steps old the weights it used were (staleness)."""
    pose = ""
    if all(k in c for k in ("x", "y", "alpha")):
        pose = (f"  x {c['x']:+.2f} y {c['y']:+.2f} alpha {c['alpha']:+.2f}"
                f"  distance {math.hypot(c['x'], c['y']):.2f} m")
    version = c.get("weights_version", -1.0)
    if not first_version and version > 0:
        first_version.append(version)
    weights = f"weights +{int(version - first_version[0])}" if first_version else "weights initial"
    return (f"{elapsed:5.1f} s: step {int(c.get('steps', 0))}{pose}  J {c.get('accumulated_cost', 0.0):.3f}"
            f"  {weights} (staleness {int(c.get('staleness_steps', 0))})"
            f"  missed deadlines {int(c.get('missed_deadlines', 0))}"
            f"  solver failures {int(c.get('solver_failures', 0))}")


def cmd_status(args: argparse.Namespace) -> int:
    """The actor's status line once a second, from a monitor session, until Ctrl-C or --seconds."""
    from services.up import StatusMonitor

    settings = settings_from_args(args)
    with stop_on_signals() as stop:
        monitor = connect_with_retry(lambda: StatusMonitor(settings), settings, "status", args.connect_timeout,
                                     stop)
        try:
            started, shown, first_version = time.monotonic(), 0, []  # type: ignore[var-annotated]
            end = None if args.seconds is None else started + args.seconds
            while not stop.is_set() and (end is None or time.monotonic() < end):
                if monitor.seen > shown and monitor.latest is not None:
                    shown = monitor.seen
                    line = format_status_line(monitor.latest, time.monotonic() - started, first_version)
                    print(f"{settings.transport.robot} {line}", flush=True)
                stop.wait(0.05)
        finally:
            monitor.close()
    return 0


def format_up_summary(summary: dict[str, Any]) -> str:
    lines = [f"srl up: {summary['mode']} run, plant {summary['plant']}, agent {summary.get('agent')}, "
             f"N = {summary.get('horizon')}"]
    lines.append("  services       " + ", ".join(f"{k} (pid {v})" for k, v in summary["services"].items()))
    if summary.get("secure"):
        lines.append("  security       user/password login per role + access rules at the router (common/security.py)"
                     + (", mutual TLS" if str(summary.get("router", "")).startswith("tls/") else ""))
    lines.append(f"  steps          {summary.get('steps')}   accumulated J {summary.get('accumulated_cost', 0):.4f}")
    if summary.get("final_state"):
        lines.append(f"  final state    {_fmt_state(summary['final_state'])}")
    lines.append(f"  critic         {summary.get('transitions_received')} transitions received, "
                 f"actor used weights version {summary.get('weights_version')}")
    if summary.get("critic_checkpoint"):
        lines.append(f"  checkpoint     {summary['critic_checkpoint']} "
                     f"({'restored' if summary.get('critic_restored') else 'fresh critic; --resume to restore'})")
    if summary.get("summary_dir"):
        lines.append(f"  summaries      {summary['summary_dir']}/<service>.json")
    if "loop" in summary:
        period = summary["loop"]["period_ms"]
        lines.append(f"  loop [ms]      period median {period['median']:.3f} p99 {period['p99']:.3f} "
                     f"max {period['max']:.3f}, missed deadlines {summary['loop']['missed_deadlines']}")
    staleness = summary.get("staleness_steps")
    if staleness:
        lines.append(f"  staleness      median {staleness['median']} max {staleness['max']} steps")
    return "\n".join(lines)


# -- srl bench -------------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "loop":
        from services.bench_loop import run_loop_benchmark

        return run_loop_benchmark(args, settings_from_args(args), settings_argv(args))
    if args.what == "bridge":
        from services.bench_bridge import run_bridge_benchmark

        return run_bridge_benchmark(args, settings_from_args(args), settings_argv(args), bridge_argv(args))
    if args.what == "actor":
        from services.bench_actor import run_actor_benchmark

        return run_actor_benchmark(args, settings_from_args(args))
    raise UsageError(f"unknown benchmark {args.what!r}")


# A value that is a number or a comma-separated list of numbers, negative first: "-1.2,0.7", "-1e9,0".
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


DESCRIPTION = """srl: stacked RL-QV (actor, critic, plant) as Zenoh services, and the tools around them.

Settings come from common/srl.toml, overridden by --config FILE (or SRL_CONFIG), by
SRL_<SECTION>__<NAME> environment variables and by the flags of each subcommand.
Start with:  srl run            (one episode in this process)
             srl up             (router + every service as processes, a live status line)
"""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="srl", description=DESCRIPTION)
    parser.add_argument("--log-level", default="WARNING", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        type=str.upper, help="console log level (default: WARNING: warnings and errors only)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, helptext: str, description: str | None = None) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=helptext, description=description or helptext[0].upper() + helptext[1:] + ".")

    run = command("run", "one closed-loop episode of Algorithm 1 (actor, plant, critic)",
                  "One closed-loop episode of Algorithm 1 (actor step, plant, critic update) and a summary.\n"
                  "Ctrl-C: exit 130; SIGTERM: 143; a closed stdout pipe (srl run | head): 141.")
    add_settings_arguments(run, COMMAND_SETTINGS["run"])
    run.add_argument("--transport", choices=["inproc", "zenoh"], default="inproc",
                     help="inproc: one process; zenoh: router, plant_sim, critic, actor as processes (default: inproc)")
    run.add_argument("--verbose", action="store_true", help="with --transport zenoh: show the services' logs")
    run.add_argument("--trajectory", action="store_true", help="include the state trajectory in the JSON")
    run.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    run.add_argument("--plot", type=Path, metavar="PNG",
                     help="write a figure: path, controls, costs and the critic's learning (weights, TD residuals) "
                          "(default: no figure)")
    run.set_defaults(func=cmd_run)

    certs = command("certs", "a private CA, the router's and each role's TLS certificate (mTLS)")
    certs.add_argument("--out", required=True,
                       help="directory to create (0700; files 0600); never in the repository (default: none, required)")
    certs.add_argument("--hosts", nargs="*", default=[], metavar="HOST",
                       help="names/addresses clients use to reach the router, besides localhost, 127.0.0.1, ::1 "
                       "(default: none)")
    certs.add_argument("--passwords", action="store_true",
                       help="also a random password per role: users.txt (router) and <role>.password")
    certs.add_argument("--if-missing", action="store_true",
                       help="exit 0 without writing if DIR already has a CA (default: write, and fail if it has one)")
    certs.set_defaults(func=cmd_certs)


    router = command("router", "a Zenoh router (Python, mode router)")
    add_settings_arguments(router, COMMAND_SETTINGS["router"])
    router.set_defaults(func=cmd_router)

    for name, func, modes, helptext in (
        ("plant-sim", cmd_plant_sim, True, "the simulated robot (real-time or lockstep queryable)"),
        ("critic", cmd_critic, False, "the off-board critic learner (TD least squares)"),
        ("actor", cmd_actor, True, "the delta-periodic actor loop"),
    ):
        svc = command(name, helptext)
        add_settings_arguments(svc, COMMAND_SETTINGS[name])
        if modes:
            svc.add_argument("--mode", choices=["realtime", "lockstep"], default="realtime",
                             help="realtime: every delta by the clock; lockstep: the actor steps the plant "
                                  "(default: realtime)")
        _add_lifetime_arguments(svc, "stop after this long (default: until signalled; a lockstep actor stops "
                                "after one episode)")
        if name == "actor":
            svc.add_argument("--sync-critic", action="store_true",
                             help="lockstep: wait for the weights trained on the previous step")
        svc.set_defaults(func=func)

    bridge = command("robot-bridge", "a ROS 2 robot as the plant: odom in, cmd_vel out, over Zenoh")
    add_settings_arguments(bridge, COMMAND_SETTINGS["robot-bridge"])
    add_bridge_arguments(bridge)
    _add_lifetime_arguments(bridge)
    bridge.set_defaults(func=cmd_robot_bridge)

    emulator = command("tb3-emulator", "an emulated TurtleBot3 Burger speaking ROS 2 over Zenoh")
    add_settings_arguments(emulator, COMMAND_SETTINGS["tb3-emulator"])
    add_bridge_arguments(emulator)
    emulator.add_argument("--initial-pose", type=_floats_arg(3), metavar="X,Y,THETA",
                          help="start pose in the odom frame (default: the episode start, through bridge.goal)")
    emulator.add_argument("--noise", type=_floats_arg(2), default=(0.0, 0.0), metavar="SIGMA_XY,SIGMA_THETA",
                          help="std. dev. of Gaussian noise on the reported pose [m, rad] (default 0,0)")
    emulator.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    emulator.add_argument("--latency", type=float, default=0.0, help="[s] cmd_vel -> wheels delay (default: 0)")
    emulator.add_argument("--cmd-timeout", type=float, default=CMD_TIMEOUT_DEFAULT,
                          help="[s] stop when cmd_vel is older: a robot must stop when its command stream breaks; "
                          f"0: hold the last command forever, like a stock TurtleBot3 (default: {CMD_TIMEOUT_DEFAULT})")
    emulator.add_argument("--v-max", type=float, help="firmware limit [m/s] (default: the Burger's 0.22)")
    emulator.add_argument("--omega-max", type=float, help="firmware limit [rad/s] (default: the Burger's 2.84)")
    emulator.add_argument("--odom-rate", type=float, default=20.0, help="[Hz] odometry rate (default: 20)")
    emulator.add_argument("--attachment", choices=("compact", "legacy"), default="compact",
                          help="rmw_zenoh attachment format: compact (rmw_zenoh_cpp Humble >= 0.1.2, Jazzy >= 0.2.4) "
                               "or legacy (Humble 0.1.0-0.1.1, Jazzy 0.2.0-0.2.3) (default: compact)")
    emulator.add_argument("--listen", help="be the robot's Zenoh router on this endpoint (default: connect to "
                          "--router)")
    _add_lifetime_arguments(emulator)
    emulator.set_defaults(func=cmd_tb3_emulator)

    up = command("up", "router + every service as separate processes, one run",
                 "The router and every service as separate processes, one run, a live status line once a second.\n"
                 "Each service's JSON summary is written to a file (--summary-dir); --json prints the merged one.")
    add_settings_arguments(up, COMMAND_SETTINGS["up"])
    add_bridge_arguments(up)
    up.add_argument("--plant", choices=["sim", "robot"], default="sim",
                    help="sim: plant_sim; robot: robot_bridge + tb3-emulator (or the robot at --robot-endpoint) "
                         "(default: sim)")
    up.add_argument("--mode", choices=["realtime", "lockstep"], default="realtime",
                    help="realtime: every delta by the clock; lockstep: the actor steps the plant (default: realtime)")
    up.add_argument("--secure", action="store_true",
                    help="Zenoh user/password login with fresh random credentials per role, and access rules "
                         "at the router: only the actor publishes actions, the critic weights, the plant state; "
                         "a tcp/ router endpoint becomes tls/ with mutual TLS (fresh private CA)")
    up.add_argument("--json", action="store_true", help="last stdout line: the merged summary as one JSON object")
    up.add_argument("--summary-dir", type=Path, metavar="DIR",
                    help="write each service's JSON summary to DIR/<service>.json (default: a fresh directory "
                         "under the system's temporary directory, named in the summary)")
    up.set_defaults(func=cmd_up)

    bench = command("bench", "benchmarks that print a table (and JSON)")
    bench.add_argument("what", choices=["actor", "loop", "bridge"])
    bench.add_argument("--reference-horizons", default="12",
                       help="actor: N values for the IPOPT reference rows ('' = none) (default: 12)")
    bench.add_argument("--seconds", type=float, default=60.0,
                       help="loop: real-time run length [s]; bridge: both phases together (default: 60)")
    bench.add_argument("--critic-load", action="store_true",
                       help="loop: the critic fits a replay of M = 1000 every step")
    add_settings_arguments(bench, COMMAND_SETTINGS["bench"])
    add_bridge_arguments(bench)
    bench.add_argument("--json", action="store_true", help="last stdout line: one JSON object")
    bench.add_argument("--steps", type=int, default=300,
                       help="closed-loop steps per row (>= 300 for p99) (default: 300)")
    bench.add_argument("--horizons", default="6,12,30", help="comma-separated N values (default: 6,12,30)")
    bench.add_argument("--agents", default="mpc,rlq,rlqv,rlqv+",
                       help="comma-separated agents (default: mpc,rlq,rlqv,rlqv+)")
    bench.add_argument(
        "--baseline-steps", type=int, default=30, help="steps of the slow SLSQP baseline per row (default: 30)"
    )
    bench.set_defaults(func=cmd_bench)

    status = command("status", "the actor's live status line once a second (step, pose, J, weights, deadlines)",
                     "The actor's live status line once a second, read from srl/<robot>/status/actor by a "
                     "monitor session\n(any running system: srl up, the containers); until Ctrl-C or --seconds.")
    add_settings_arguments(status, COMMAND_SETTINGS["status"])
    status.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    status.add_argument("--connect-timeout", type=float, default=30.0,
                        help="[s] wait this long for the router (default: 30)")
    status.set_defaults(func=cmd_status)

    # srl experiment paper (services/experiment.py): the paper's grid of runs, ratios and plots
    from services.experiment import add_experiment_arguments, cmd_experiment

    experiment = command("experiment", "the paper's experiment: grid of starts, cost ratios, plots")
    add_experiment_arguments(experiment)
    experiment.set_defaults(func=cmd_experiment)

    # srl health (services/health.py): readiness of a service, for container healthchecks
    from services.health import add_health_parser

    add_health_parser(sub)
    for action in sub._choices_actions:  # every subcommand's --help opens with what it does
        subparser = sub.choices[action.dest]
        if not subparser.description:
            subparser.description = (action.help or "")[:1].upper() + (action.help or "")[1:] + "."
    return parser


def _add_lifetime_arguments(parser: argparse.ArgumentParser,
                            run_help: str = "stop after this long (default: until signalled)") -> None:
    """--run-seconds and --connect-timeout, as every long-running service process takes them."""
    parser.add_argument("--run-seconds", type=float, help=run_help)
    parser.add_argument("--connect-timeout", type=float, default=30.0,
                        help="[s] wait this long for the router (default: 30)")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (UsageError, SecurityError, PlantConflictError) as error:
        print(f"srl: error: {error}", file=sys.stderr)
        return 2
    except SignalledError as stopped:
        print(f"srl: interrupted ({stopped}): stopped", file=sys.stderr)
        return 128 + stopped.signum
    except KeyboardInterrupt as error:  # also common.actor.BuildInterrupted (a signal during the JIT build)
        import signal

        signum = getattr(error, "signum", signal.SIGINT)
        print(f"srl: interrupted ({signal.Signals(signum).name}): stopped", file=sys.stderr)
        return 128 + signum
    except BrokenPipeError:
        # the reader went away (srl run | head): no traceback; as a shell reports SIGPIPE
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 141


def entry(argv: Sequence[str] | None = None) -> None:
    """The ``srl`` command: :func:`main`, then, in a process that used Zenoh, an exit that
    skips the interpreter's finalization.

    Zenoh runs Python callbacks on its own native (Rust) threads. A thread that asks for the
    GIL while the interpreter finalizes is ended by CPython with ``pthread_exit``, and that
    forced unwinding through Rust frames aborts the whole process (SIGABRT, exit -6) after its
    work is done and reported: seen once in the test suite, an actor that had printed its
    summary. Such a process therefore runs its ``atexit`` handlers (logging, multiprocessing),
    flushes its streams and leaves with ``os._exit``: nothing of
    ours is left to finalize (every service has closed its Zenoh session by then).
    """
    import os

    try:
        code: int | str | None = main(argv)
    except SystemExit as done:
        code = done.code
    if "zenoh" in sys.modules and (code is None or isinstance(code, int)):
        import atexit
        import contextlib

        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):  # closed, or a broken pipe: nothing more to say
                stream.flush()
        os._exit(code or 0)
    sys.exit(code)


if __name__ == "__main__":
    entry()
