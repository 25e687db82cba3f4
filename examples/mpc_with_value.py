"""An agent of your own, in one file: MPC that ends its horizon with the learned value critic.

Its objective is ``sum_i delta r(s_i, u_i) + Jhat(s_N; v)``: the stage costs of MPC, and the
critic learner fits the value critic for it as for RL-QV. Run it by naming this file in
``SRL_PLUGINS`` (common/process/plugins.py)::

    SRL_PLUGINS=examples/mpc_with_value.py ./srl run --agent mpcv --horizon 12 --start 2,2 --duration 30
"""

from __future__ import annotations

from common.math.agents import AgentRow, register_agent

ROW = AgentRow(
    title="MPC+V",
    q_critics=False,
    value_critic=True,
    stage_costs="each",
    paper=False,
    objective="sum_i delta r(s_i, u_i) + Jhat(s_N; v)",
)


def register() -> None:
    register_agent("mpcv", ROW)
