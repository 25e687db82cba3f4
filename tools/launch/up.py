"""``srl up``: the router and every service as child processes, one run, for one robot or a fleet.

One launcher for every size (docs/fleets.md). The robots of a run are either **the robot of the
settings** (``transport.robot`` at ``episode.start``, named to each child by the user's own flags:
``srl up``) or **a fleet** (``UpOptions.robots``: ``srl up --robots K``), started evenly on a circle
around the target (common/math/fleet.py) and named to each child by the launcher
(:func:`robot_flags`). Everything else is the same code: the router, the observers (``srl record``,
``srl view``), the plants (a plant host, one ``plant-sim`` per robot, or robots behind bridges),
the critic, the actor host(s), the watch (:func:`tools.launch.measure.measure_run`: a status line a
second, CPU and memory from /proc) and one summary (:func:`run_summary`).

Layouts of a fleet: ``host`` (the default): ONE actor host up to 50 robots, else one per core
(``--actor-hosts``, common.math.fleet.AUTO_ONE_HOST_UP_TO), ONE plant host and the critic,
whatever the fleet's size; ``process`` (the baseline of ``srl bench fleet``): one ``plant-sim``
and one ``actor`` per robot.

The children are started, watched and stopped by tools/launch/supervisor.py. The actors define the
end of the run: when they exit, the others are stopped (SIGINT, then SIGKILL after a grace period).
If any child dies first, everything is stopped and ``srl up`` exits non-zero naming it. Each child's
JSON summary is written to ``<summary_dir>/<name>.json``.

``--plant physics`` is ``plant-sim`` with ``plant.model = "physics"`` (the MuJoCo TurtleBot3,
common/math/physics.py) for every child. ``--plant robot`` starts robot bridges (and TurtleBot3
emulators, of ``plant.model``, for the robots without a robot endpoint: tools/launch/bridged.py)
instead of plants; the bridges are stopped (and have commanded zero velocity) before everything
else. Each emulated robot runs as its own Zenoh router on a free loopback port (as a real robot runs
``rmw_zenohd``) and its bridge talks to it there: when srl's router dies, the bridge still reaches
the robot and stops it (the actor's liveliness token vanishes from the bridge's srl session within
milliseconds).

Lockstep (the paper's Algorithm 1 through the services: ``plant/step`` queries, the critic
synchronous with ``sync_critic``) runs the robot of the settings only: a fleet's robots, and a robot
behind a bridge, move in real time.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from pydantic import TypeAdapter

from common.config.settings import Settings
from common.contracts.summaries import (
    ACTOR_SUMMARY,
    CriticSummary,
    FleetActorSummary,
    FleetView,
    LockstepActorSummary,
    RealtimeActorSummary,
    fleet_view,
    format_status_line,
)
from common.math.fleet import circle_starts, fleet_starts, split_evenly
from common.math.frames import Pose2D, to_goal_frame
from common.math.systems import system_row
from common.net.transport import zenoh_config
from common.process.runtime import fleet_hosts
from tools.launch.measure import RobotStatuses, RunMeasures, measure_run
from tools.launch.plants import LAYOUTS, launch_plant, with_launch_plant
from tools.launch.supervisor import (
    CHILD_SUMMARIES,
    Child,
    Logins,
    OtherSummary,
    ServiceDiedError,
    StopSignals,
    Supervisor,
    contract_summary,
    free_loopback_endpoint,
    optional_summary,
    router_reachable,
    said,
    tls_endpoint,
    write_child_summaries,
)

# settings flags a fleet sets per child itself (the router is fresh, robots and starts its own)
OWN_FLAGS = ("--router", "--robot", "--start", "--duration")
FLEET_TRANSITION_CACHE = 600  # transitions per robot kept for a late critic (60 s at delta = 0.1 s)
# [s] the slowest start seen here: 100 robots' subscriptions and tokens on a loaded 2-core machine
READY_TIMEOUT = 120.0


@dataclass(frozen=True)
class UpOptions:
    """One ``srl up`` run, as :func:`run_up` takes it.

    ``plant``: a row of tools/launch/plants.py (``sim``, ``physics``, ``robot``: the robot bridge,
    and the TurtleBot3 emulator unless a robot endpoint names a real robot; real time only: a robot
    cannot be stepped by a lockstep query). ``sync_critic``: the lockstep actor waits for the weights
    trained on the previous step. ``settings_args``: the settings flags every child gets;
    ``bridge_args``: the bridges' and emulators' own. ``secure``: fresh logins per role and mutual TLS
    (:class:`Logins`). ``on_status``: handed ``srl up``'s status line once a second (one robot: its
    actor's status, tools/launch/measure.py; a fleet: every robot's). ``record``: an ``srl record``
    child writes every robot to this MCAP file for the whole run (subscribed before the first state);
    ``view_port``: an ``srl view`` child serves the run to Foxglove on that loopback port. Neither
    runs with ``secure`` (the read-only monitor role may not read the transitions and weights).

    The fleet: ``robots`` (None: the robot of the settings), its ``layout``, the ``circle`` [m] its
    robots start on, ``actor_hosts`` (host layout), one ``pooled`` critic learner or one per robot,
    the ``robot_endpoints`` of real robots (``plant="robot"``; the others are emulated),
    ``count_messages`` (every robot message routed, by kind: ``srl bench capacity``), an
    ``outside`` client of every robot's transition key (``srl bench fleet --outside``) and the
    ``router`` endpoint (default: the settings' for the robot of the settings, else a free loopback
    port, so that fleets side by side never meet)."""

    settings_args: list[str]
    mode: str = "realtime"
    plant: str = "sim"
    duration: float = 30.0
    sync_critic: bool = False
    quiet: bool = False
    bridge_args: list[str] = field(default_factory=list)
    secure: bool = False
    on_status: Callable[[str], None] | None = None
    summary_dir: Path | None = None
    record: Path | None = None
    view_port: int | None = None
    robots: list[str] | None = None
    layout: str = "host"
    circle: float = 1.5
    actor_hosts: int = 1
    pooled: bool = False
    robot_endpoints: dict[str, str] = field(default_factory=dict)
    count_messages: bool = False
    outside: bool = False
    router: str | None = None

    @property
    def fleet(self) -> bool:
        """Robots named by the launcher (``--robots``), not the robot of the settings."""
        return self.robots is not None


def actor_hosts(option: str, size: int) -> int:
    """``--actor-hosts``: a number, or ``auto`` (common.process.runtime.fleet_hosts)."""
    return fleet_hosts(option, size, "--actor-hosts")


def host_shares(robots: list[str], hosts: int) -> dict[str, list[str]]:
    """The robots of each actor host (common.math.fleet.split_evenly): ``actor`` alone, else
    ``actor-1`` .. ``actor-H`` (one per core: one host's solves run in one thread)."""
    shares = split_evenly(robots, hosts)
    return {"actor": shares[0]} if hosts == 1 else {f"actor-{h + 1}": share for h, share in enumerate(shares)}


def exit_code(code: int | None) -> int | None:
    """A child's exit code, its stop by our SIGINT counted as a clean end (0)."""
    return 0 if code == -signal.SIGINT else code


def robot_flags(options: UpOptions, robots: list[str]) -> list[str]:
    """How a host child (plant, critic, actor of every robot) is told its robots: nothing for the
    robot of the settings (the user's flags name it and its start), ``--robots`` for a fleet."""
    return [f"--robots={','.join(robots)}"] if options.fleet else []


def run_arguments(options: UpOptions, router: str) -> list[str]:
    """Every child's settings flags: the user's; a fleet's without those it sets per child, and its router."""
    if not options.fleet:
        return list(options.settings_args)
    return [a for a in options.settings_args if a.split("=", 1)[0] not in OWN_FLAGS] + [f"--router={router}"]


def run_environment(options: UpOptions) -> dict[str, str]:
    """Every child's environment: this process's, with the settings a run of this kind takes (an
    ``SRL_`` variable the user set wins): a live view's every state tick, a fleet's critic and
    transition caches; one BLAS thread per process."""
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    # one BLAS thread per process: a pooled fit (25 robots: ~750 rows) is big enough for a BLAS to
    # start threads, which spin on a busy machine and slow every fit. OPENBLAS_NUM_THREADS is already
    # in this process's environment (tools/__init__.py); the children's other BLAS libraries too:
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(variable, "1")
    if options.view_port is not None:
        # a live view draws every state tick (transport.state_rate), not only those its actor reads
        env.setdefault("SRL_TRANSPORT__STATE_SYNC", "false")
    if options.fleet:
        env.setdefault("SRL_CRITIC__COALESCE_FITS", "true")  # a critic behind fits each robot's newest only
        # each actor host keeps this many transitions per robot for a late critic (Zenoh's publisher
        # cache): 60 s covers a critic's restart (it checkpoints every second) and partitions up to a
        # minute; the settings' 3000 would hold ~0.6 MB per robot, filled over the first 5 minutes
        env.setdefault("SRL_TRANSPORT__TRANSITION_CACHE", str(FLEET_TRANSITION_CACHE))
        env["SRL_CRITIC__POOLED"] = "true" if options.pooled else "false"
    return env


def check_options(options: UpOptions, robots: list[str], settings: Settings) -> None:
    """One line (ValueError) for a run that cannot be, before anything starts."""
    settings.robot_only(  # another system: the simulated plant, no recording or view
        "srl up",
        (f"--plant {options.plant}", launch_plant(options.plant) != launch_plant("sim")),  # a TurtleBot3's
        ("--record", options.record is not None),
        ("--view", options.view_port is not None),
    )
    if options.secure and (options.record is not None or options.view_port is not None):
        raise ValueError(
            "--record and --view do not run with --secure yet: the read-only monitor role may read "
            "only states and status, not the transitions and weights a recording carries"
        )
    if options.secure and options.count_messages:
        raise ValueError("counting every message needs to read srl/**, which no role may do with secure")
    if options.record is not None:  # a bad path is one line now, before anything starts
        from tools.recording.sinks import RecordingError, open_for_writing

        try:
            open_for_writing(options.record).close()
        except RecordingError as error:
            raise ValueError(str(error)) from None
    if options.mode != "realtime":
        if launch_plant(options.plant).behind_bridge:
            raise ValueError(
                f"--plant {options.plant} runs in real time only: lockstep steps plant_sim through its "
                "plant/step queryable, and a robot cannot be stepped; use --mode realtime"
            )
        if options.fleet:
            raise ValueError("--robots runs in real time only: lockstep steps the one robot of the settings")
    if options.layout not in LAYOUTS:
        raise ValueError(f"unknown layout {options.layout!r} ({' or '.join(LAYOUTS)})")
    if not 1 <= options.actor_hosts <= len(robots):
        raise ValueError(f"{options.actor_hosts} actor hosts for {len(robots)} robots: 1 to one per robot")


def run_up(settings: Settings, options: UpOptions) -> dict[str, Any]:
    """Start everything, run the actors' episode or ``duration``, stop everything; the run's summary
    (:func:`run_summary`).

    ``secure``: fresh random credentials for every role in a private temporary directory
    (0700, files 0600, removed at exit); the router authenticates users and enforces the role
    rules of common/net/security.py (plant/step and plant/reset in lockstep only) for every robot
    of the run, each child logs in as its role, this supervisor as ``monitor``.
    A ``tcp/`` router endpoint becomes ``tls/`` on the same address, with mutual TLS from a
    fresh private CA and one certificate per role in the same directory (common/net/certs.py).
    Each emulated robot's own router is secured as a robot's should be (docs/security.md): mutual
    TLS from a CA of its own, a login and access rules (services/robot_bridge/robot_router.py);
    only the bridges get those credentials.

    The recorder (``--clock steps`` in lockstep) and the view start before the plants and stop
    after everything but the router, so they see it all. A fleet's critic checkpoints into a
    directory of the run's own, removed at its end; the robot of the settings' where the settings say.

    SIGINT, SIGTERM and SIGHUP stop everything as Ctrl-C does, then raise :class:`Stopped`.
    """
    robots = list(options.robots) if options.robots is not None else [settings.transport.robot]
    check_options(options, robots, settings)

    router = options.router or (free_loopback_endpoint() if options.fleet else settings.transport.router)
    settings = settings.model_copy(update={"transport": settings.transport.model_copy(update={"router": router})})
    env = run_environment(options)
    settings = with_launch_plant(settings, env, options.plant)  # physics: one MuJoCo TurtleBot3 per robot
    common = run_arguments(options, router)
    started = time.monotonic()
    with StopSignals() as signals:
        supervisor = Supervisor(common, env, quiet=options.quiet, signals=signals)
        measures = _run(settings, options, supervisor, env, common, robots, started, signals)
        signals.raise_if_received()
    return run_summary(settings, options, supervisor, robots, started, measures)


def _run(
    settings: Settings,
    options: UpOptions,
    supervisor: Supervisor,
    env: dict[str, str],
    common: list[str],
    robots: list[str],
    started: float,
    signals: StopSignals,
) -> RunMeasures:
    bridged = launch_plant(options.plant).behind_bridge
    logins: Logins | None = None
    scratch: Path | None = None
    try:
        if options.fleet:  # made while the signals are watched: a signal from here on still removes it
            scratch = Path(tempfile.mkdtemp(prefix="srl-fleet-"))
            # the critic's checkpoint is written as in any run (its cost is part of the fleet's), but here
            env["SRL_CRITIC__CHECKPOINT"] = str(scratch / "critic-{robot}-{agent}-N{horizon}.json")
        login: dict[str, dict[str, str]] = {}  # role -> its login environment
        if options.secure:
            logins = Logins.create(
                settings.transport, lockstep=options.mode == "lockstep", robots=robots if options.fleet else None
            )
            login = logins.environment
            common = logins.argv(common)
            # this supervisor's own probes and status lines log in as the read-only monitor
            settings = settings.model_copy(update={"transport": logins.monitor})
        supervisor.spawn("router", ["router", *common], login.get("router"))
        supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
        spawn_observers(supervisor, options, common)  # subscribed before the first state is published
        if bridged:  # emulated or real TurtleBot3s behind bridges
            from tools.launch.bridged import spawn_robot_plants

            endpoints = spawn_robot_plants(
                supervisor,
                settings,
                common,
                robots,
                None if not options.fleet else circle_starts(len(robots), options.circle),
                options.robot_endpoints,
                options.bridge_args,
                options.layout,
                login.get("plant"),
                None if logins is None else logins.directory / "robot",  # removed with the run's logins
            )
        else:
            spawn_sim_plants(supervisor, options, common, robots, login.get("plant"), settings)
        supervisor.spawn("critic", ["critic", *common, *robot_flags(options, robots)], login.get("critic"))
        # a bridge is alive once it reaches its robot's router, which it waits for (a robot boots slowly)
        plant_timeout = READY_TIMEOUT + (settings.bridge.robot_connect_timeout if bridged else 0)
        wait_alive(supervisor, settings, robots, "plant", plant_timeout)
        if bridged:
            from tools.launch.bridged import wait_odometry

            wait_odometry(supervisor, settings, endpoints)
        wait_alive(supervisor, settings, robots, "critic", READY_TIMEOUT)
        actors = spawn_actors(supervisor, options, common, robots, login.get("actor"))
        # measured from when every robot is served
        wait_alive(supervisor, settings, robots, "actor", READY_TIMEOUT, until_ended=actors)
        measures = measure_run(
            supervisor,
            settings,
            actors,
            options.duration,
            robots,
            status_lines(options, started),
            options.count_messages,
            one=not options.fleet,
            outside=options.outside,
        )
        for actor in actors:
            if actor.process.returncode != 0:
                raise ServiceDiedError(actor.name, actor.process.returncode, actor.stderr_tail[-10:])
        return measures
    finally:
        signals.cleaning = True  # a signal from here on is remembered, never raised mid-cleanup
        for name in [name for name in supervisor.children if name.startswith("robot_bridge")]:
            supervisor.stop_one(name)  # first, so that their last zero reaches the robots
        supervisor.stop_all()
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
        if logins is not None:
            logins.remove()


def spawn_observers(supervisor: Supervisor, options: UpOptions, common: list[str]) -> None:
    """``srl record`` (step clock in lockstep) and ``srl view``, each ready before this returns."""
    observers = []
    if options.record is not None:
        clock = "steps" if options.mode == "lockstep" else "wall"
        observers.append(
            ("recorder", ["record", str(options.record), "--clock", clock, *common], "srl record: recording")
        )
    if options.view_port is not None:
        observers.append(("view", ["view", "--port", str(options.view_port), *common], "srl view: serving"))
    for name, argv, ready in observers:
        child = supervisor.spawn(name, argv, observer=True)
        supervisor.wait_for(name, said(child, ready), timeout=30)


def spawn_sim_plants(
    supervisor: Supervisor,
    options: UpOptions,
    common: list[str],
    robots: list[str],
    login: dict[str, str] | None,
    settings: Settings,
) -> None:
    """The simulated robots: one plant host for all (``host``: the robot of the settings at its
    start, or a fleet where common.math.fleet.fleet_starts puts it: evenly on the circle, another
    system's in its start box) or a plant_sim each (``process``)."""
    if options.layout == "host":
        fleet = [*robot_flags(options, robots), f"--circle={options.circle!r}"] if options.fleet else []
        supervisor.spawn("plant", ["plant-sim", "--mode", options.mode, *common, *fleet], login)
        return
    for robot, start in zip(robots, fleet_starts(settings.system, len(robots), options.circle), strict=True):
        supervisor.spawn(
            f"plant-{robot}",
            ["plant-sim", *common, f"--robot={robot}", "--start=" + ",".join(repr(c) for c in start)],
            login,
        )


def spawn_actors(
    supervisor: Supervisor, options: UpOptions, common: list[str], robots: list[str], login: dict[str, str] | None
) -> list[Child]:
    """The actors: ``actor_hosts`` hosts (``host``) or one per robot (``process``); in real time each
    runs ``duration`` seconds, in lockstep one episode."""
    run = ["--mode", options.mode]
    if options.mode == "realtime":
        run += ["--run-seconds", repr(options.duration)]
    if options.sync_critic:
        run.append("--sync-critic")
    if options.layout == "host":
        return [
            supervisor.spawn(name, ["actor", *common, *robot_flags(options, share), *run], login)
            for name, share in host_shares(robots, options.actor_hosts).items()
        ]
    return [supervisor.spawn(f"actor-{robot}", ["actor", *common, f"--robot={robot}", *run], login) for robot in robots]


def _alive_robots(session: Any, robots: list[str], service: str) -> set[str]:
    # one robot's own key: a secured router grants the monitor role that robot's keys, not srl/*
    robot = robots[0] if len(robots) == 1 else "*"
    replies = session.liveliness().get(f"srl/{robot}/alive/{service}", timeout=2.0)
    return {str(reply.ok.key_expr).split("/")[1] for reply in replies if reply.ok is not None}


def wait_alive(
    supervisor: Supervisor,
    settings: Settings,
    robots: list[str],
    service: str,
    timeout: float,
    until_ended: list[Child] | None = None,
) -> None:
    """Until every robot's ``service`` token is live (bounded by ``timeout`` s), or one of the children
    ``until_ended`` (the actors: a short run may be over before its token is seen) has ended."""
    ending = until_ended or []
    session = zenoh.open(zenoh_config(settings.transport))
    try:
        wanted, deadline = set(robots), time.monotonic() + timeout
        while time.monotonic() < deadline:
            supervisor.check(allowed_to_exit={child.name for child in ending})
            if any(child.process.poll() is not None for child in ending):
                return
            if wanted <= _alive_robots(session, robots, service):
                return
            time.sleep(0.05)
        what = service if len(robots) == 1 else f"{service} of {len(robots)} robots"
        raise TimeoutError(f"{what} not ready after {timeout:.0f} s")
    finally:
        session.close()


def status_lines(options: UpOptions, started: float) -> Callable[[float, RobotStatuses], None] | None:
    """``options.on_status`` fed a line: the robot of the settings' actor status each time a new one
    came (common.contracts.summaries.format_status_line), a fleet's every second."""
    on_status = options.on_status
    if on_status is None:
        return None
    shown = 0  # statuses seen (one robot) or whole seconds shown (a fleet)
    first_version: list[float] = []

    def show(elapsed: float, statuses: RobotStatuses) -> None:
        nonlocal shown
        if not options.fleet:
            latest = statuses.latest
            if statuses.seen > shown and latest is not None:
                shown = statuses.seen
                on_status(format_status_line(latest, time.monotonic() - started, first_version))
        elif int(elapsed) > shown:
            shown = int(elapsed)
            on_status(statuses.line(elapsed, len(options.robots or ())))

    return show


def emulator_truth(emulator: dict[str, Any] | None, settings: Settings) -> dict[str, Any] | None:
    """The emulated robot's true final pose in the goal frame (the actor saw only its odometry,
    so the actor's ``truth`` is null: the emulator is the one that knows)."""
    if not emulator or "final_pose" not in emulator:
        return None
    goal = Pose2D(*settings.bridge.goal)
    true = to_goal_frame(Pose2D(*emulator["final_pose"]), goal)
    reported = to_goal_frame(Pose2D(*emulator.get("final_odometry", emulator["final_pose"])), goal)
    return {
        "model": emulator.get("model", "ideal"),
        "final_state": [true.x, true.y, true.theta],
        "final_distance": float(math.hypot(true.x, true.y)),
        "odometry_final_state": [reported.x, reported.y, reported.theta],
        "saturated_commands": emulator.get("saturated_commands"),
    }


ActorSummary = RealtimeActorSummary | LockstepActorSummary


def actor_summaries(
    supervisor: Supervisor, options: UpOptions, robots: list[str]
) -> tuple[dict[str, ActorSummary], list[dict[str, float]]]:
    """Each robot's actor summary, and each actor process's own counters (a host's: its tick
    thread's priority), from the actor processes of either layout."""
    if not options.fleet:  # an actor of the robot of the settings prints its own summary
        summary = contract_summary(supervisor.children["actor"], ACTOR_SUMMARY)
        return {robots[0]: summary}, [dict(summary.counters)]
    if options.layout == "host":
        per_robot: dict[str, ActorSummary] = {}
        process_counters = []
        for name in host_shares(robots, options.actor_hosts):
            host_summary = FleetActorSummary.model_validate(supervisor.children[name].summary())
            per_robot.update(host_summary.per_robot)
            process_counters.append(host_summary.counters)
        return per_robot, process_counters
    each = {
        robot: RealtimeActorSummary.model_validate(supervisor.children[f"actor-{robot}"].summary()) for robot in robots
    }
    return dict(each), [summary.counters for summary in each.values()]


def run_summary(
    settings: Settings,
    options: UpOptions,
    supervisor: Supervisor,
    robots: list[str],
    started: float,
    measures: RunMeasures,
) -> dict[str, Any]:
    """The run's one summary, whatever its size: the run (mode, plant, robots, security, router), the
    critic's figures (``critic``), the CPU and memory measured, and ``fleet``: the per-robot table
    (robots in real time). A run of one robot carries that robot's actor summary at the top level
    (steps, J, start and final state, loop, staleness), and, behind a bridge, the bridge's and the
    emulator's. Each child's own summary is written to ``options.summary_dir``. A child that did not
    end cleanly raises :class:`ServiceDiedError`."""
    for name, child in supervisor.children.items():
        if exit_code(child.process.returncode) != 0:
            raise ServiceDiedError(name, child.process.returncode, child.stderr_tail[-10:])
    critic = contract_summary(supervisor.children["critic"], TypeAdapter(CriticSummary))
    per_robot, process_counters = actor_summaries(supervisor, options, robots)
    realtime = {robot: s for robot, s in per_robot.items() if isinstance(s, RealtimeActorSummary)}
    ticks = sum(s.steps for s in realtime.values())
    hurried = sum(s.counters.get("hurried_solves", 0.0) for s in realtime.values())
    summary: dict[str, Any] = {
        "mode": options.mode,
        "plant": options.plant,
        "plant_model": settings.plant.model,  # the simulated robot's model (the truth line names it)
        "robots": robots,
        "seconds": options.duration,
        "run_seconds": measures.ran,  # the span over which CPU was measured
        "secure": options.secure,
        # a tcp/ router runs secured as tls/ on the same address (Logins)
        "router": (tls_endpoint(settings.transport.router) if options.secure else None) or settings.transport.router,
        "agent": settings.actor.agent,
        "horizon": settings.actor.horizon,
        "system": settings.plant.system,
        "critic": {
            "transitions_received": critic.transitions_received,
            "weights_published": critic.weights_published,
            "fit_ms": critic.fit_ms.to_json_dict(),
            "checkpoint_ms": critic.checkpoint_ms.to_json_dict(),
            # a fleet's checkpoints are the run's own, removed at its end: nothing to resume from
            "checkpoint": None if options.fleet else critic.checkpoint,
            "restored": critic.restored,
            "batch_transitions": None if critic.batch_transitions is None else critic.batch_transitions.to_json_dict(),
            "waiting_transitions": None
            if critic.waiting_transitions is None
            else critic.waiting_transitions.to_json_dict(),
            "fits_coalesced": critic.fits_coalesced,
            "fits_at_rest": critic.fits_at_rest,
            "pooled": critic.pooled,
        },
        **measures.fields(len(supervisor.children)),
        "wall_seconds": time.monotonic() - started,
        "services": {name: child.process.pid for name, child in supervisor.children.items()},
        "exit_codes": {name: exit_code(child.process.returncode) for name, child in supervisor.children.items()},
    }
    if realtime:
        summary["fleet"] = fleet_view(realtime).to_json_dict()
        # how the actor processes ticked: how many had their tick thread real-time
        # (actor.realtime_priority), and the share of ticks solved in a hurry (late or over budget)
        summary["actor_ticks"] = {
            "processes": len(process_counters),
            "realtime": sum(counters.get("realtime_priority", 0.0) > 0 for counters in process_counters),
            "hurried_percent": 100.0 * hurried / ticks if ticks else 0.0,
        }
    if options.fleet:
        summary.update(
            {
                "layout": options.layout,
                "circle_radius_m": options.circle,
                "actor_hosts": options.actor_hosts if options.layout == "host" else len(robots),
            }
        )
    if len(robots) == 1:  # the one robot's own summary, at the top level
        (robot_summary,) = per_robot.values()
        own = robot_summary.to_json_dict()
        own.pop("transitions_tail", None)  # kept in the actor's own summary file
        summary = {**own, **summary}
    if not options.fleet:
        summary.update(child_summaries(settings, supervisor, {"critic": critic, "actor": per_robot[robots[0]]}))
    if options.record is not None:
        summary["recording"] = str(options.record)
        summary["recorder"] = next(
            (line for line in supervisor.children["recorder"].stdout_lines if line.startswith("srl record:")), None
        )
    if options.view_port is not None:
        summary["view"] = supervisor.children["view"].summary()
    if options.count_messages:  # over the same span as the CPU: [count, bytes] of each kind
        summary["messages"] = measures.messages
    if options.outside:
        summary["outside_received"] = measures.outside_received
    if options.fleet and launch_plant(options.plant).behind_bridge:
        from tools.launch.bridged import robot_fleet_summary

        summary["robot_plant"] = robot_fleet_summary(supervisor, settings, robots, options.layout)
    if options.summary_dir is not None:
        write_child_summaries(options.summary_dir, supervisor.children)
        summary["summary_dir"] = str(options.summary_dir)
        summary["per_robot_final"] = {robot: s.final_state for robot, s in realtime.items()}
        (options.summary_dir / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def child_summaries(
    settings: Settings, supervisor: Supervisor, read: dict[str, CriticSummary | ActorSummary]
) -> dict[str, Any]:
    """The robot of the settings' other children's figures: each one's resources, the bridge's and the
    emulator's summaries (with the emulator's true final pose) as far as they printed one (the
    router's may be cut by its bounded close); one that does not fit its contract raises. ``read``:
    the summaries already read (the critic's, the actor's)."""
    others: dict[str, OtherSummary] = {
        name: summary
        for name, child in supervisor.children.items()
        if name in CHILD_SUMMARIES
        and (summary := optional_summary(child, TypeAdapter(CHILD_SUMMARIES[name]))) is not None
    }
    parsed: dict[str, OtherSummary | CriticSummary | ActorSummary] = {**read, **others}
    found: dict[str, Any] = {
        "resources": {name: parsed[name].resources if name in parsed else None for name in supervisor.children}
    }
    if "robot_bridge" in supervisor.children:
        bridge = others.get("robot_bridge")
        found["bridge"] = None if bridge is None else bridge.to_json_dict()
    if "tb3_emulator" in supervisor.children:
        emulator = others.get("tb3_emulator")
        found["emulator"] = None if emulator is None else emulator.to_json_dict()
        found["emulator_truth"] = None if emulator is None else emulator_truth(found["emulator"], settings)
    return found


def format_fleet_summary(summary: dict[str, Any]) -> str:
    """A fleet's summary as ``srl up --robots`` prints it: a row per robot, the fleet's figures."""
    view = FleetView.model_validate(summary["fleet"])
    system = system_row(summary.get("system", "unicycle"))
    where = (  # a wheeled robot's fleet on the circle; another system's in its start box (fleet_starts)
        f"starts on a {summary['circle_radius_m']} m circle"
        if system.wheeled
        else f"system {summary['system']} from its start and its start box, parked: "
        f"stabilized (< {system.stabilized:g})"
    )
    lines = [
        f"srl up --robots {len(summary['robots'])} ({summary['layout']} layout): {summary['seconds']:.0f} s, "
        f"{summary['agent']} N = {summary['horizon']}, {where}"
        + (", MuJoCo TurtleBot3s (final m: their true pose)" if summary.get("plant") == "physics" else ""),
        f"  {'robot':<12} {'steps':>5} {'missed':>6} {'jitter p99':>10} {'latency p99':>11} {'staleness p99/max':>17} "
        f"{'final m' if system.wheeled else 'final':>8} parked",
    ]
    if summary.get("secure"):
        lines.insert(
            1,
            "  security       user/password login per role + access rules at the router for every robot"
            + (", mutual TLS" if str(summary.get("router", "")).startswith("tls/") else ""),
        )
        if summary.get("robot_plant"):
            from tools.launch.bridged import robot_router_line

            lines.insert(2, robot_router_line(summary["robot_plant"]))
    for row in view.rows:
        lines.append(
            f"  {row.robot:<12} {row.steps:>5} {row.missed_deadlines:>6} {row.jitter_p99_ms:>8.2f}ms "
            f"{row.latency_p99_ms:>9.2f}ms {row.staleness_p99_steps:>8.0f}/{row.staleness_max_steps:<8.0f} "
            f"{row.final_distance_m:>8.3f} {'yes' if row.parked else 'no'}"
        )
    lines.append(
        f"  fleet: {view.robots} robots, parked {view.parked}, missed deadlines {view.missed_deadlines}, "
        f"jitter p99 {view.jitter_p99_ms:.2f} ms, latency p99 {view.latency_p99_ms:.2f} ms (worst robot), "
        f"staleness p99/max {view.staleness_p99_steps:.0f}/{view.staleness_max_steps:.0f} steps, "
        f"CPU {summary['cpu_percent']:.0f} %, RSS {summary['rss_mb']:.0f} MB in {summary['processes']} processes"
    )
    phases = summary.get("cpu_phases")
    if phases:
        drive, rest = phases["driving"], phases["at_rest"]
        lines.append(
            f"  CPU while the robots drove {drive['cpu_percent']:.0f} % ({drive['seconds']:.1f} s), "
            f"once every robot had arrived {rest['cpu_percent']:.0f} % ({rest['seconds']:.1f} s: no solve, no fit"
            + (
                f"; at times only {rest['fewest_arrived']} of {len(summary['robots'])} arrived)"
                if rest["fewest_arrived"] < len(summary["robots"])
                else ")"
            )
        )
    if summary.get("actor_ticks"):
        ticks = summary["actor_ticks"]
        lines.append(
            f"  actor ticks: real-time (SCHED_FIFO) in {ticks['realtime']} of {ticks['processes']} actor processes, "
            f"{ticks['hurried_percent']:.1f} % solved in a hurry (served late or over the host's CPU budget)"
        )
    if summary.get("robot_plant"):
        from tools.launch.bridged import format_robot_lines

        lines += format_robot_lines(summary["robot_plant"])
    return "\n".join(lines)
