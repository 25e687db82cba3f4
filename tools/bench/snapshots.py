"""Critic weights the paper's loop really learned, for ``srl bench actor``.

The bench's ``learned`` weights are seeded noise on the initial ones; these are snapshots of
what the critic fitted in the paper's Algorithm 1 (:func:`common.config.assembly.run_episode`, in
process, the paper's method, the packaged settings otherwise) for each agent and horizon, from
one start of the paper's grid, at a few steps. They are stored in ``critic_snapshots.json``
beside this module so that the benchmark's problem does not move with the actor under test;
``python -m tools.bench.snapshots`` regenerates the file (deterministic: the in-process loop
repeats bit for bit; the actor is built without JIT so that no compiler enters the numbers), and
``tests/test_bench_actor.py`` regenerates one snapshot and compares.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from common.config.assembly import run_episode
from common.config.settings import Settings, with_method
from common.math.agents import learns

SNAPSHOT_FILE = Path(__file__).with_name("critic_snapshots.json")
SNAPSHOT_AGENTS = ("rlq", "rlqv", "rlqv+")
SNAPSHOT_HORIZONS = (6, 12, 30)
# (-1, -2): the paper grid's hardest start (RL-Q at N = 6 does not park from it,
# docs/experiment.md); at steps 50 and 150 the fitted Q quadratic is indefinite at N = 6.
SNAPSHOT_START = (-1.0, -2.0)
SNAPSHOT_STEPS = (50, 150)


def snapshot_settings(base: Settings, agent: str, horizon: int) -> Settings:
    """The settings an episode of the snapshots runs with: the paper's method, no JIT."""
    actor = with_method(base, "paper", agent=agent, horizon=horizon, jit=False).actor
    episode = base.episode.model_copy(update={"start": SNAPSHOT_START, "duration": (max(SNAPSHOT_STEPS) + 1) * 0.1})
    return base.model_copy(update={"actor": actor, "episode": episode})


def learn_snapshots(
    base: Settings, agent: str, horizon: int, steps: tuple[int, ...] = SNAPSHOT_STEPS
) -> dict[str, Any]:
    """One episode of Algorithm 1; the weights the actor used at each of ``steps``."""
    if not learns(agent):
        raise ValueError(f"{agent} learns no critic")
    settings = snapshot_settings(base, agent, horizon)
    episode = run_episode(settings)
    return {
        str(k): {"q": [float(x) for x in episode.q_weights[k]], "v": [float(x) for x in episode.v_weights[k]]}
        for k in steps
    }


def generate(base: Settings) -> dict[str, Any]:
    """Every snapshot of the file, with what made it."""
    snapshots = {
        agent: {str(n): learn_snapshots(base, agent, n) for n in SNAPSHOT_HORIZONS} for agent in SNAPSHOT_AGENTS
    }
    actor = snapshot_settings(base, SNAPSHOT_AGENTS[0], SNAPSHOT_HORIZONS[0]).actor
    return {
        "description": (
            "critic weights (q: 15, v: 6) the in-process Algorithm 1 learned, paper's method, per agent and N, "
            "from one start of the paper grid, at the given steps (the weights the actor used at that step)"
        ),
        "generator": "python -m tools.bench.snapshots",
        "start": list(SNAPSHOT_START),
        "steps": list(SNAPSHOT_STEPS),
        "actor": {
            "multistart": actor.multistart,
            "multistart_starts": actor.multistart_starts,
            "multistart_iterations": actor.multistart_iterations,
            "multistart_margin": actor.multistart_margin,
            "multistart_flips": actor.multistart_flips,
            "newton_iterations": actor.newton_iterations,
            "jit": False,
        },
        "critic": base.critic.model_dump(mode="json", exclude={"checkpoint", "resume", "robots"}),
        "snapshots": snapshots,
    }


def load_snapshots(path: Path = SNAPSHOT_FILE) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(path.read_text())
    return data


def snapshot_weights(data: dict[str, Any], agent: str, horizon: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(step, q, v) of every snapshot of ``agent`` at ``horizon`` (none for another N or mpc)."""
    found = data["snapshots"].get(agent, {}).get(str(horizon), {})
    return [
        (int(k), np.array(w["q"], dtype=float), np.array(w["v"], dtype=float))
        for k, w in sorted(found.items(), key=lambda kv: int(kv[0]))
    ]


def main() -> int:
    data = generate(Settings.load())
    SNAPSHOT_FILE.write_text(json.dumps(data, indent=1) + "\n")
    print(f"wrote {SNAPSHOT_FILE}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
