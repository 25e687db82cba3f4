"""The paper's agents, defined once: their names and what each one learns.

``mpc`` minimizes the stage costs alone (no critic); ``rlq`` stacks learned Q-critics;
``rlqv`` adds the learned value critic at the horizon end; ``rlqv+`` is rlqv complemented with
the stage costs (the paper's complemented variant). Settings, the command line, the actor, the
benchmarks and the experiment all take their vocabulary from here.
"""

from __future__ import annotations

from typing import Literal, get_args

Agent = Literal["mpc", "rlq", "rlqv", "rlqv+"]
AGENTS: tuple[Agent, ...] = get_args(Agent)
# the paper's comparison (rlqv+ is ours to add with --agents)
PAPER_AGENTS: tuple[Agent, ...] = ("mpc", "rlq", "rlqv")


def learns(agent: str) -> bool:
    """Does this agent have critics to fit (everything but mpc)?"""
    return agent != "mpc"


def uses_value_critic(agent: str) -> bool:
    """Does this agent's objective end with the learned value critic V?"""
    return agent in ("rlqv", "rlqv+")


def fit_due(step: int, update_every: int) -> bool:
    """The critic is fitted (and its weights published) after every ``update_every``-th transition."""
    return step % update_every == 0


def parse_agents(text: str, option: str = "--agents") -> tuple[Agent, ...]:
    """``"mpc, rlqv,rlqv"`` -> ``("mpc", "rlqv")``: comma-separated, each once, in order."""
    names = tuple(dict.fromkeys(a.strip() for a in str(text).split(",") if a.strip()))
    unknown = [a for a in names if a not in AGENTS]
    if unknown:
        raise ValueError(f"{option}: unknown agent(s) {', '.join(unknown)}; choose from {', '.join(AGENTS)}")
    if not names:
        raise ValueError(f"{option}: at least one of {', '.join(AGENTS)} (comma-separated), got {text!r}")
    return tuple(a for agent in names for a in AGENTS if a == agent)


def parse_horizons(text: str, option: str = "--horizons", allow_empty: bool = False) -> tuple[int, ...]:
    """``"12,6"`` -> ``(12, 6)``: comma-separated integers N >= 2, each once, in order."""
    items = [h.strip() for h in str(text).split(",") if h.strip()]
    if not items and allow_empty:
        return ()
    try:
        horizons = tuple(dict.fromkeys(int(h) for h in items))
    except ValueError:
        raise ValueError(f"{option}: comma-separated integers N >= 2, got {text!r}") from None
    if not horizons or any(h < 2 for h in horizons):
        raise ValueError(f"{option}: comma-separated integers N >= 2, got {text!r}")
    return horizons
