"""Throughput of the vector environment: ``python -m tools.gym.bench [--robots 1,16,100]``.

For each number of robots K, :class:`tools.gym.vector.SrlVectorEnv` of ``srl/Unicycle-v0`` is
stepped with random actions in the box (drawn before the clock starts) for at least
``--seconds``, in this one thread: the figure is one core's. Printed per K: ``step`` calls per
second and robot steps (environment transitions, what an RL library counts as samples) per second;
episodes end and restart inside the run (300 steps each), as they do in training.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from common.math.plant_models import PLANT_MODELS
from tools.gym.vector import SrlVectorEnv

CHUNK = 500  # step calls between clock reads


@dataclass(frozen=True)
class Throughput:
    robots: int
    calls: int
    seconds: float

    @property
    def calls_per_second(self) -> float:
        return self.calls / self.seconds

    @property
    def steps_per_second(self) -> float:
        return self.robots * self.calls / self.seconds


def measure(robots: int, seconds: float, model: str = "ideal", seed: int = 0) -> Throughput:
    """Step K robots for at least ``seconds`` of this thread's CPU time."""
    env = SrlVectorEnv(num_envs=robots, model=model, starts="disc")
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(env.low, env.high, size=(CHUNK, robots, 2))
    calls = 0
    started = time.thread_time()
    while True:
        for action in actions:
            env.step(action)
        calls += CHUNK
        elapsed = time.thread_time() - started
        if elapsed >= seconds:
            return Throughput(robots, calls, elapsed)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.gym.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="1,16,100", help="comma-separated K values (default: 1,16,100)")
    parser.add_argument("--seconds", type=float, default=2.0, help="CPU seconds per K (default: 2)")
    parser.add_argument("--model", default="ideal", choices=list(PLANT_MODELS), help="plant.model")
    args = parser.parse_args(argv)
    try:
        counts = [int(part) for part in args.robots.split(",")]
    except ValueError:
        parser.error(f"--robots: comma-separated numbers of robots, got {args.robots!r}")
    if not (args.seconds > 0):
        parser.error(f"--seconds must be > 0, got {args.seconds}")
    print(f"vector environment, plant {args.model}, one thread (CPU time)")
    print(f"{'robots':>8} {'step calls/s':>14} {'robot steps/s':>15}")
    for robots in counts:
        result = measure(robots, args.seconds, args.model)
        print(f"{robots:>8} {result.calls_per_second:>14,.0f} {result.steps_per_second:>15,.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
