"""The paper's agents, one row each: their names, what each objective is made of and what it learns.

Settings (``actor.agent``), the command line's choices and help, the actor's objective
(common/math/actor_search.py), the benchmarks, the experiment's tables and plots and the
generated Variants page (docs/reference/variants.md) all read :data:`AGENT_ROWS`; nothing else names
an agent's properties. A new agent is a row (docs/extending.md): here, or from the user's own
file with :func:`register_agent` (``SRL_PLUGINS``, common/process/plugins.py). ``mpc`` minimizes the stage
costs alone (no critic); ``rlq`` stacks learned Q-critics; ``rlqv`` adds the learned value critic
at the horizon end; ``rlqv+`` is rlqv complemented with the stage costs (the paper's Remark on
the complemented stack).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.math.rows import add_row

Agent = str  # a name of AGENT_ROWS (built in or registered)

# How the stage cost delta r(s_i, u_i) enters the stacked objective at stage i = 1 .. N - 1:
# "each" once per stage (MPC), "remaining" (N - i) times (the complemented stack), "none" not at all.
StageCosts = Literal["each", "remaining", "none"]


@dataclass(frozen=True)
class AgentRow:
    """One agent: its name in tables and plots, the terms of its stacked objective and where it
    comes from. ``q_critics``: each stage's term is the learned Q-critic ``Qhat(s_i, u_i; w)``;
    ``value_critic``: the learned ``Jhat(s_N; v)`` ends the stack; ``stage_costs``: how the
    stage cost enters (:data:`StageCosts`); ``paper``: one of the paper's comparison;
    ``objective``: the objective as one line (help texts and docs)."""

    title: str
    q_critics: bool
    value_critic: bool
    stage_costs: StageCosts
    paper: bool
    objective: str

    @property
    def learns(self) -> bool:
        """It has critics to fit (a critic learner serves it)."""
        return self.q_critics or self.value_critic


AGENT_ROWS: dict[Agent, AgentRow] = {
    "mpc": AgentRow("MPC", False, False, "each", True, "sum_i delta r(s_i, u_i)"),
    "rlq": AgentRow("RL-Q", True, False, "none", True, "sum_i Qhat(s_i, u_i; w)"),
    "rlqv": AgentRow("RL-QV", True, True, "none", True, "sum_i Qhat(s_i, u_i; w) + Jhat(s_N; v)"),
    "rlqv+": AgentRow(
        "RL-QV+", True, True, "remaining", False, "sum_i [Qhat(s_i, u_i; w) + (N - i) delta r(s_i, u_i)] + Jhat(s_N; v)"
    ),
}
AGENTS: tuple[Agent, ...] = tuple(AGENT_ROWS)  # srl's own rows (agent_names(): with the registered ones)
# the paper's comparison (rlqv+ is ours to add with --agents)
PAPER_AGENTS: tuple[Agent, ...] = tuple(name for name, row in AGENT_ROWS.items() if row.paper)
# the agent every other is measured against (J / J_MPC in the experiment's tables and plots)
REFERENCE_AGENT: Agent = "mpc"


def agent_names() -> tuple[Agent, ...]:
    """Every agent's name: srl's rows, then those registered in this process."""
    return tuple(AGENT_ROWS)


def agent_row(agent: str) -> AgentRow:
    """The row of ``agent``; an unknown name is a one-line ValueError naming the known ones."""
    try:
        return AGENT_ROWS[agent]
    except KeyError:
        raise ValueError(f"unknown agent {agent!r}; choose one of {', '.join(AGENT_ROWS)}") from None


def register_agent(name: str, row: AgentRow) -> None:
    """Add an agent: ``actor.agent = name`` then minimizes ``row``'s objective in every consumer of
    this process (the actor, the critic, the experiment, the benchmarks). A name that is taken, or
    not 1-32 of a-z 0-9 _ + starting with a letter, raises ValueError."""
    add_row(AGENT_ROWS, "agent", name, row, extra="+")


def learns(agent: str) -> bool:
    """Does this agent have critics to fit (everything but mpc)?"""
    return agent_row(agent).learns


def uses_value_critic(agent: str) -> bool:
    """Does this agent's objective end with the learned value critic V?"""
    return agent_row(agent).value_critic


def stage_cost_weights(agent: str, horizon: int) -> list[float]:
    """How many times ``delta r(s_i, u_i)`` enters the objective at each stage i = 1 .. N - 1
    (:data:`StageCosts`): all 1 (MPC), ``N - i`` (complemented), all 0 (none)."""
    kind = agent_row(agent).stage_costs
    if kind == "each":
        return [1.0] * (horizon - 1)
    if kind == "remaining":
        return [float(horizon - i) for i in range(1, horizon)]
    return [0.0] * (horizon - 1)


def agents_text() -> str:
    """``mpc: sum_i delta r(s_i, u_i); rlq: ...``: the rows as one line (help texts, descriptions)."""
    return "; ".join(f"{name}: {row.objective}" for name, row in AGENT_ROWS.items())


def fit_due(step: int, update_every: int) -> bool:
    """The critic is fitted (and its weights published) after every ``update_every``-th transition."""
    return step % update_every == 0


def parse_agents(text: str, option: str = "--agents") -> tuple[Agent, ...]:
    """``"mpc, rlqv,rlqv"`` -> ``("mpc", "rlqv")``: comma-separated, each once, in order."""
    names = tuple(dict.fromkeys(a.strip() for a in str(text).split(",") if a.strip()))
    known = agent_names()
    unknown = [a for a in names if a not in known]
    if unknown:
        raise ValueError(f"{option}: unknown agent(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    if not names:
        raise ValueError(f"{option}: at least one of {', '.join(known)} (comma-separated), got {text!r}")
    return names


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
