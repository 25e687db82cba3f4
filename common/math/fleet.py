"""A fleet (docs/fleets.md): which robots one host serves, and where a simulated fleet starts.

Pure: strings and numbers in, ids and states out (no settings, no transport).

* :func:`parse_robots` -- ``--robots r1,r2,...`` (explicit ids) or ``--robots K`` (``robot1`` ..
  ``robotK``); a repeated or malformed id is refused with one line (:class:`FleetError`).
* :func:`circle_starts` -- distinct starts on a circle around the target, each turned away from
  it (the paper's ``alpha_0 = atan2(y_0, x_0)``), so every robot has the same parking task;
  :func:`fleet_starts` -- those for a wheeled robot, another system's in its start box.
* :func:`host_count` and :func:`split_evenly` -- over how many actor host processes a fleet's
  robots go (a number, or ``auto``: one up to :data:`AUTO_ONE_HOST_UP_TO` robots, else one per
  core: one host's solves run in one thread) and which robots each serves (contiguous, even shares).
* :func:`ros_fleet` -- several ROS 2 robots (``--plant robot``): each srl robot id IS its robot's
  ROS namespace (``tb3_1`` <-> ``/tb3_1/odom``, ``/tb3_1/cmd_vel``), and each robot's Zenoh
  endpoint (its own router, or one shared by all). A robot id that is no ROS namespace, an
  endpoint for a robot the fleet does not have, or a robot left without an endpoint is refused
  with one line.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import TypeVar

import numpy as np

from common.math.systems import System

T = TypeVar("T")
MAX_ROBOTS = 1000  # one host; far beyond what 2 cores serve at delta = 0.1 s (docs/fleets.md)
_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # one key chunk, as common/contracts/keys.py requires
# one ROS name segment (a robot's namespace, ``tb3_1``): a letter, then letters, digits, _
_ROS_SEGMENT = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
# a Zenoh endpoint (locator): ``<protocol>/<address>``, e.g. ``tcp/192.168.1.21:7447``
_ENDPOINT = re.compile(r"^[a-z][a-z0-9]*/\S+$")
ROS_FLEET_PREFIX = "tb3_"  # ``--robots K --plant robot``: tb3_1 .. tb3_K, as TurtleBot3 multi-robot launches name them


# "auto": one actor host up to this many robots, else one per core (a host's solves use one core).
# One host is cheaper (one batch a period, one wake of every other process), but the robots of a
# host share its tick thread, so its margin for deadlines shrinks as they grow; a default serves
# every agent and horizon and keeps the margin (the runs behind the number: CHANGELOG.md);
# --actor-hosts 1 takes the cheaper layout.
AUTO_ONE_HOST_UP_TO = 50
AUTO_HOSTS_HELP = f"auto = one up to {AUTO_ONE_HOST_UP_TO} robots, else one per core"


class FleetError(ValueError):
    """A robot list that cannot be served: said in one line."""


def parse_robots(text: str, prefix: str = "robot") -> list[str]:
    """``"K"`` -> ``[prefix1 .. prefixK]``; ``"a,b,c"`` -> ``["a", "b", "c"]`` (order kept)."""
    text = text.strip()
    if text.isdigit():
        count = int(text)
        if not 1 <= count <= MAX_ROBOTS:
            raise FleetError(f"--robots {text}: a fleet has 1 to {MAX_ROBOTS} robots")
        return [f"{prefix}{i}" for i in range(1, count + 1)]
    robots = [part.strip() for part in text.split(",")]
    seen: set[str] = set()
    for robot in robots:
        if not _ID.match(robot):
            raise FleetError(f"--robots: robot id {robot!r} must be 1-64 characters of A-Z a-z 0-9 _ -")
        if robot in seen:
            raise FleetError(f"--robots: robot id {robot!r} is given twice")
        seen.add(robot)
    if len(robots) > MAX_ROBOTS:
        raise FleetError(f"--robots: {len(robots)} robots; a fleet has 1 to {MAX_ROBOTS} robots")
    return robots


def circle_starts(count: int, radius: float) -> list[tuple[float, float, float]]:
    """``count`` starts evenly on a circle of ``radius`` metres around the target (the first on
    the +x axis), each heading away from the target: ``(r cos t, r sin t, t)``."""
    if count < 1:
        raise FleetError("a fleet has at least one robot")
    if not (math.isfinite(radius) and radius > 0):
        raise FleetError(f"the start circle's radius must be a positive number of metres, got {radius}")
    starts = []
    for i in range(count):
        theta = 2.0 * math.pi * i / count
        starts.append(
            (radius * math.cos(theta), radius * math.sin(theta), math.atan2(math.sin(theta), math.cos(theta)))
        )
    return starts


def fleet_starts(system: System, count: int, radius: float) -> Sequence[tuple[float, ...]]:
    """Where ``count`` simulated robots of ``system`` start: a wheeled robot's on the circle of
    ``radius`` (:func:`circle_starts`); another system's first at its row's start, the others drawn
    uniformly in its start box (seeded: the same starts every run; ``radius`` is the robot's)."""
    if not system.wheeled:
        if count < 1:
            raise FleetError("a fleet has at least one robot")
        rng = np.random.default_rng(0)
        return [system.start, *(tuple(system.draw_start(rng).tolist()) for _ in range(count - 1))]
    return circle_starts(count, radius)


def host_count(option: str, size: int, cores: int, flag: str = "--actor-hosts") -> int:
    """How many actor host processes serve ``size`` robots: ``option`` is a number (1 to one per
    robot) or ``auto`` (one up to :data:`AUTO_ONE_HOST_UP_TO` robots, else one per core of ``cores``).
    ``flag`` names the option in the one-line refusal."""
    if option == "auto":
        return 1 if size <= AUTO_ONE_HOST_UP_TO else max(1, min(cores, size))
    try:
        hosts = int(option)
    except ValueError:
        raise FleetError(f"{flag} {option!r}: a number of actor processes, or auto") from None
    if not 1 <= hosts <= size:
        raise FleetError(f"{flag} {hosts}: 1 to one per robot ({size})")
    return hosts


def split_evenly(robots: Sequence[T], hosts: int) -> list[list[T]]:
    """``robots`` in ``hosts`` contiguous shares, as even as can be (the first ones one larger):
    a fleet's robots over its actor hosts, a host's status publishers over a period's wakes."""
    if not 1 <= hosts <= max(len(robots), 1):
        raise FleetError(f"{hosts} actor hosts for {len(robots)} robots: 1 to one per robot")
    size, extra = divmod(len(robots), hosts)
    shares, start = [], 0
    for h in range(hosts):
        end = start + size + (h < extra)
        shares.append(list(robots[start:end]))
        start = end
    return shares


def ros_fleet(robots: list[str], endpoints: str | None, shared_endpoint: str) -> dict[str, str]:
    """Each robot of a ROS 2 fleet -> its robot's Zenoh endpoint ('' = none given: emulate it).

    The robot id is the robot's ROS namespace (its topics ``/<id>/odom``, ``/<id>/cmd_vel``), so
    it must be one ROS name segment. ``endpoints``: ``id=endpoint,...`` (each robot on its own
    router, as a robot running ``rmw_zenohd``); robots not named there use ``shared_endpoint``
    (robots reached through one router). Either every robot has an endpoint, or none has one.
    """
    for robot in robots:
        if not _ROS_SEGMENT.match(robot):
            raise FleetError(
                f"robot id {robot!r} is not a ROS namespace (a letter, then letters, digits, _): "
                "with --plant robot a robot's id is its ROS namespace"
            )
    given: dict[str, str] = {}
    for part in (endpoints or "").split(","):
        if not part.strip():
            continue
        robot, sep, endpoint = (c.strip() for c in part.partition("="))
        if not sep or not _ENDPOINT.match(endpoint):
            raise FleetError(
                f"--robot-endpoints: {part.strip()!r} is not NAMESPACE=ENDPOINT (e.g. tb3_1=tcp/10.0.0.11:7447)"
            )
        if robot not in robots:
            raise FleetError(
                f"--robot-endpoints: namespace {robot!r} is not mapped to a robot of the fleet ({', '.join(robots)})"
            )
        if robot in given:
            raise FleetError(f"--robot-endpoints: namespace {robot!r} is given twice")
        given[robot] = endpoint
    if shared_endpoint and not _ENDPOINT.match(shared_endpoint):
        raise FleetError(f"--robot-endpoint {shared_endpoint!r} is not a Zenoh endpoint (e.g. tcp/10.0.0.10:7447)")
    fleet = {robot: given.get(robot, shared_endpoint) for robot in robots}
    missing = [robot for robot, endpoint in fleet.items() if not endpoint]
    if given and missing:
        raise FleetError(
            f"--robot-endpoints: no endpoint for {', '.join(missing)}: "
            "name every robot, or give --robot-endpoint for the rest"
        )
    return fleet
