"""``srl up``: the router and every service as separate child processes, one run.

The children are started, watched and stopped by tools/launch/supervisor.py. While the actor runs,
its 1 Hz status (``srl/<robot>/status/actor``) is handed to ``on_status`` (``srl up`` prints a
status line). The actor defines the end of the run: when it exits, the others are stopped
(SIGINT, then SIGKILL after a grace period). If any child dies first, everything is stopped and
``srl up`` exits non-zero naming it. Each child's JSON summary is written to
``<summary_dir>/<name>.json``.

``--plant physics`` is ``plant-sim`` with ``plant.model = "physics"`` (the MuJoCo TurtleBot3,
common/math/physics.py) for every child. ``--plant robot`` starts ``robot-bridge`` (and
``tb3-emulator``, of ``plant.model``, unless a robot endpoint is configured) instead of
``plant-sim``; the bridge is stopped (and has commanded zero velocity) before everything else. The
emulator runs as the robot's own Zenoh router on a free loopback port (as a real robot runs
``rmw_zenohd``) and the bridge talks to it there: when srl's router dies, the
bridge still reaches the robot and stops it (the actor's liveliness token vanishes from the
bridge's srl session within milliseconds).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
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
    LockstepActorSummary,
    RealtimeActorSummary,
)
from common.math.frames import Pose2D, to_goal_frame
from common.net.transport import zenoh_config
from services.robot_bridge.robot_router import RobotLogins, robot_router_reachable
from tools.launch.plants import launch_plant, with_launch_plant
from tools.launch.supervisor import (
    CHILD_SUMMARIES,
    Child,
    Logins,
    OtherSummary,
    ServiceDiedError,
    StopSignals,
    Supervisor,
    alive_probe,
    contract_summary,
    free_loopback_endpoint,
    optional_summary,
    router_reachable,
    said,
    state_probe,
    tls_endpoint,
    write_child_summaries,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class UpOptions:
    """One ``srl up`` run, as :func:`run_up` takes it.

    ``plant``: ``sim`` (plant_sim), ``physics`` (plant_sim with the MuJoCo TurtleBot3) or ``robot``
    (the robot bridge, and the TurtleBot3 emulator unless ``settings.bridge.robot_endpoint`` names a
    real robot; real time only: a robot cannot be stepped by a lockstep query).
    ``sync_critic``: the lockstep actor waits for the weights trained on the previous step.
    ``settings_args``: the settings flags every child gets; ``bridge_args``: the bridge and
    emulator's own. ``secure``: fresh logins per role and mutual TLS (:class:`Logins`).
    ``on_status``: handed the actor's status counters once a second. ``record``: an ``srl record``
    child writes every robot to this MCAP file; ``view_port``: an ``srl view`` child serves the run
    to Foxglove on that loopback port."""

    settings_args: list[str]
    mode: str
    plant: str
    duration: float
    sync_critic: bool = False
    quiet: bool = False
    bridge_args: list[str] = field(default_factory=list)
    secure: bool = False
    on_status: Callable[[dict[str, float]], None] | None = None
    summary_dir: Path | None = None
    record: Path | None = None
    view_port: int | None = None


class StatusMonitor:
    """The actor's newest 1 Hz status (``srl/<robot>/status/actor``), seen from a monitor session,
    with the plant's refusal counters (``srl/<robot>/status/plant``: the bridge's refused and
    resynchronized actions) merged in under ``plant.``."""

    def __init__(self, settings: Settings) -> None:
        from common.contracts.keys import STATUS
        from common.contracts.messages import ServiceStatus

        self.actor: dict[str, float] | None = None
        self.plant: dict[str, float] = {}
        self.seen = 0
        self.session = zenoh.open(zenoh_config(settings.transport))

        def on_sample(sample: Any) -> None:
            try:
                status = ServiceStatus.model_validate_json(sample.payload.to_bytes())
            except ValueError:
                return  # the actor's own schema: a bad one is not ours to report
            if status.service == "actor":
                self.actor = dict(status.counters)
                self.seen += 1
            else:  # only what says whether actions are being refused: the line stays short
                self.plant = {
                    f"plant.{k}": v
                    for k, v in status.counters.items()
                    if k.startswith("rejected.action") or k == "action_resyncs"
                }

        robot = settings.transport.robot
        self.subscribers = [
            self.session.declare_subscriber(STATUS.key(robot, service=service), on_sample)
            for service in ("actor", "plant")
        ]

    @property
    def latest(self) -> dict[str, float] | None:
        return None if self.actor is None else {**self.actor, **self.plant}

    def close(self) -> None:
        for subscriber in self.subscribers:
            with contextlib.suppress(zenoh.ZError):
                subscriber.undeclare()
        self.session.close()


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


def write_summaries(directory: Path, children: dict[str, Child], merged: dict[str, Any]) -> None:
    """Each child's JSON summary line to ``<name>.json`` and the merged one to ``summary.json``."""
    write_child_summaries(directory, children)
    (directory / "summary.json").write_text(json.dumps(merged, indent=1) + "\n")


def run_up(settings: Settings, options: UpOptions) -> dict[str, Any]:
    """Start everything, run one actor episode/duration, stop everything; the merged summary.

    The emulated robot is its own Zenoh router (``--listen`` on a free loopback port) and the
    bridge its client, so the bridge's path to the robot does not go through srl's router.

    ``secure``: fresh random credentials for every role in a private temporary directory
    (0700, files 0600, removed at exit); the router authenticates users and enforces the role
    rules of common/net/security.py (plant/step and plant/reset in lockstep only), each child logs in
    as its role, this supervisor as ``monitor``.
    A ``tcp/`` router endpoint becomes ``tls/`` on the same address, with mutual TLS from a
    fresh private CA and one certificate per role in the same directory (common/net/certs.py).
    The emulated robot's own router is secured as a robot's should be (docs/security.md): mutual
    TLS from a CA of its own, a login and access rules (services/robot_bridge/robot_router.py);
    only the bridge gets those credentials.

    The recorder (``--clock steps`` in lockstep) and the view start before the plant and stop
    after everything but the router, so they see it all.

    SIGINT, SIGTERM and SIGHUP stop everything as Ctrl-C does, then raise :class:`Stopped`.
    """
    if options.secure and (options.record is not None or options.view_port is not None):
        raise ValueError(
            "--record and --view do not run with --secure yet: the read-only monitor role may read "
            "only states and status, not the transitions and weights a recording carries"
        )
    if options.record is not None:  # a bad path is one line now, before anything starts
        from tools.recording.record import RecordingError, open_for_writing

        try:
            open_for_writing(options.record).close()
        except RecordingError as error:
            raise ValueError(str(error)) from None
    if launch_plant(options.plant).behind_bridge and options.mode != "realtime":
        raise ValueError(
            f"--plant {options.plant} runs in real time only: lockstep steps plant_sim through its "
            "plant/step queryable, and a robot cannot be stepped; use --mode realtime"
        )
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    settings = with_launch_plant(settings, env, options.plant)
    started = time.monotonic()
    with StopSignals() as signals:
        supervisor = Supervisor(options.settings_args, env, quiet=options.quiet, signals=signals)
        return _run_up(settings, options, supervisor, started, signals)


def _run_up(
    settings: Settings, options: UpOptions, supervisor: Supervisor, started: float, signals: StopSignals
) -> dict[str, Any]:
    mode, record, view_port = options.mode, options.record, options.view_port
    bridged = launch_plant(options.plant).behind_bridge
    common_args = [*options.settings_args]
    robot_args = [*options.settings_args, *options.bridge_args]
    logins = Logins.create(settings.transport, lockstep=mode == "lockstep") if options.secure else None
    role: dict[str, dict[str, str]] = {}  # child -> its login environment
    if logins is not None:
        users = {"plant": "plant", "robot_bridge": "plant", "critic": "critic", "actor": "actor", "router": "router"}
        role = {name: logins.environment[user] for name, user in users.items()}
        common_args, robot_args = logins.argv(common_args), logins.argv(robot_args)
        # this supervisor's own probes log in as the read-only monitor
        settings = settings.model_copy(update={"transport": logins.monitor})
    try:
        supervisor.spawn("router", ["router", *common_args], role.get("router"))
        supervisor.wait_for("router", lambda: router_reachable(settings), timeout=30)
        observers = []  # srl record / srl view: subscribed before the first state is published
        if record is not None:
            clock = "steps" if mode == "lockstep" else "wall"
            argv = ["record", str(record), "--clock", clock, *common_args]
            observers.append(("recorder", argv, "srl record: recording"))
        if view_port is not None:
            observers.append(("view", ["view", "--port", str(view_port), *common_args], "srl view: serving"))
        for name, argv, ready in observers:
            child = supervisor.spawn(name, argv)
            supervisor.wait_for(name, said(child, ready), timeout=30)
        if not bridged:
            supervisor.spawn("plant", ["plant-sim", "--mode", mode, *common_args], role.get("plant"))
        else:
            robot_endpoint = settings.bridge.robot_endpoint
            bridge_env = role.get("robot_bridge")
            if not robot_endpoint:  # the emulated robot runs its own Zenoh router, as a real one does
                robot_endpoint = free_loopback_endpoint()
                emulator_env: dict[str, str] | None = None
                probe_bridge = settings.bridge.model_copy(update={"robot_endpoint": robot_endpoint})
                if logins is not None:  # secured as a robot should be: TLS, login, access rules
                    robot_endpoint = tls_endpoint(robot_endpoint) or robot_endpoint
                    robot_logins = RobotLogins.create(logins.directory / "robot")
                    emulator_env = robot_logins.emulator_environment
                    bridge_env = {**(bridge_env or {}), **robot_logins.bridge_environment}
                    probe_bridge = robot_logins.bridge(settings.bridge, robot_endpoint)
                supervisor.spawn(
                    "tb3_emulator", ["tb3-emulator", *robot_args, "--listen", robot_endpoint], emulator_env
                )
                log.info("the emulated robot's Zenoh router: %s", robot_endpoint)
                supervisor.wait_for(
                    f"the emulated robot's router ({robot_endpoint})",
                    lambda: robot_router_reachable(probe_bridge, settings.transport),
                    timeout=30,
                )
            supervisor.spawn(
                "robot_bridge", ["robot-bridge", *robot_args, f"--robot-endpoint={robot_endpoint}"], bridge_env
            )
        supervisor.spawn("critic", ["critic", *common_args], role.get("critic"))
        # the bridge is alive once it reaches the robot's router, which it waits for (a robot boots slowly)
        plant_timeout = 60 + (settings.bridge.robot_connect_timeout if bridged else 0)
        supervisor.wait_for(
            "robot_bridge" if bridged else "plant", alive_probe(settings, "plant"), timeout=plant_timeout
        )
        if bridged:
            supervisor.wait_for(
                f"the robot's odometry (srl/{settings.transport.robot}/state from the bridge; "
                f"{settings.bridge.profile}, {settings.bridge.ros_distro}, domain "
                f"{settings.bridge.domain_id}, namespace '{settings.bridge.namespace}')",
                state_probe(settings),
                timeout=60,
            )
        supervisor.wait_for("critic", alive_probe(settings, "critic"), timeout=60)
        actor_args = ["actor", "--mode", mode, *common_args]
        if mode == "realtime":
            actor_args += ["--run-seconds", str(options.duration)]
        if options.sync_critic:
            actor_args.append("--sync-critic")
        actor = supervisor.spawn("actor", actor_args, role.get("actor"))
        on_status = options.on_status
        status = StatusMonitor(settings) if on_status is not None else None
        try:
            shown = 0
            while actor.process.poll() is None:
                supervisor.check(allowed_to_exit={"actor"})
                if on_status is not None and status is not None and status.seen > shown and status.latest is not None:
                    shown = status.seen
                    on_status(status.latest)
                time.sleep(0.05)
        finally:
            if status is not None:
                status.close()
        if actor.process.returncode != 0:
            raise ServiceDiedError("actor", actor.process.returncode, actor.stderr_tail[-10:])
    finally:
        signals.cleaning = True  # a signal from here on is remembered, never raised mid-cleanup
        if "robot_bridge" in supervisor.children:  # first, so that its last zero reaches the robot
            supervisor.stop_one("robot_bridge")
        supervisor.stop_all()
        if logins is not None:
            logins.remove()
    signals.raise_if_received()
    return merged_summary(settings, options, supervisor, started)


def merged_summary(settings: Settings, options: UpOptions, supervisor: Supervisor, started: float) -> dict[str, Any]:
    """The run's summary: the actor's, with the critic's and the other children's figures merged in;
    each child's own written to ``options.summary_dir``. A child that did not end cleanly raises."""
    mode, plant, record, view_port = options.mode, options.plant, options.record, options.view_port
    for name, child in supervisor.children.items():
        code = child.process.returncode
        if name != "actor" and code not in (0, -signal.SIGINT):
            raise ServiceDiedError(name, code, child.stderr_tail[-10:])
    # the children's summaries through their contracts (common/contracts/summaries.py): a service that
    # printed none, or one that does not fit, is said here, not met later as a missing key
    actor_summary = contract_summary(supervisor.children["actor"], ACTOR_SUMMARY)
    critic_summary = contract_summary(supervisor.children["critic"], TypeAdapter(CriticSummary))
    # the others as far as they printed one (the router's may be cut by its bounded close)
    others: dict[str, OtherSummary] = {
        name: summary
        for name, child in supervisor.children.items()
        if name in CHILD_SUMMARIES
        and (summary := optional_summary(child, TypeAdapter(CHILD_SUMMARIES[name]))) is not None
    }
    parsed: dict[str, OtherSummary | CriticSummary | RealtimeActorSummary | LockstepActorSummary] = {
        "actor": actor_summary,
        "critic": critic_summary,
        **others,
    }
    merged = actor_summary.to_json_dict()
    merged.pop("transitions_tail", None)  # kept in actor.json
    if launch_plant(plant).behind_bridge:
        bridge = others.get("robot_bridge")
        merged["bridge"] = None if bridge is None else bridge.to_json_dict()
        if "tb3_emulator" in supervisor.children:
            emulator = others.get("tb3_emulator")
            merged["emulator"] = None if emulator is None else emulator.to_json_dict()
            merged["emulator_truth"] = None if emulator is None else emulator_truth(merged["emulator"], settings)
    merged.update(
        {
            "services": {name: child.process.pid for name, child in supervisor.children.items()},
            "exit_codes": {name: child.process.returncode for name, child in supervisor.children.items()},
            "mode": mode,
            "plant": plant,
            "plant_model": settings.plant.model,  # the simulated robot's model (the truth line names it)
            "secure": options.secure,
            "router": settings.transport.router,
            "transitions_received": critic_summary.transitions_received,
            "critic_weights_published": critic_summary.weights_published,
            "critic_fit_ms": critic_summary.fit_ms.to_json_dict(),
            "critic_checkpoint": critic_summary.checkpoint,
            "critic_restored": critic_summary.restored,
            "wall_seconds": time.monotonic() - started,
            "resources": {name: parsed[name].resources if name in parsed else None for name in supervisor.children},
        }
    )
    if record is not None:
        merged["recording"] = str(record)
        merged["recorder"] = next(
            (line for line in supervisor.children["recorder"].stdout_lines if line.startswith("srl record:")), None
        )
    if view_port is not None:
        merged["view"] = supervisor.children["view"].summary()
    if options.summary_dir is not None:
        merged["summary_dir"] = str(options.summary_dir)
        write_summaries(options.summary_dir, supervisor.children, merged)
    return merged
