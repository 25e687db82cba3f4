"""The sampled systems' table (common/math/systems.py): the unicycle is one row of it, and a
system the user defines in their own file -- here a double integrator, defined below and nowhere
in srl -- is built into the actor's problem, the critic and the in-process plant, and Algorithm 1
stabilizes it, with no change to srl's modules."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.config.settings import Settings
from common.math.actor import StackedActor
from common.math.actor_problem import ActorProblem
from common.math.dynamics import exact_step, unicycle_rhs
from common.math.features import quadratic_weights_for_diag
from common.math.loop import ExactPlant, LocalCritic, run_algorithm1
from common.math.systems import (
    BUILT_IN_SYSTEMS,
    PENDULUM_LENGTH,
    PENDULUM_MASS,
    SYSTEMS,
    UNICYCLE,
    System,
    gymnasium_id,
    name_and_unit,
    register_system,
    system_row,
    vector,
)
from tests.harness import ROOT
from tools.experiment.report import read_runs_csv

NAME = "double_integrator"
DELTA = 0.1


def double_integrator(state: Any, action: Any) -> Any:
    """A cart on a line: position and speed, pushed by a bounded acceleration."""
    return vector(state[1], action[0])


DOUBLE_INTEGRATOR = System(
    what="a cart on a line pushed by a bounded acceleration",
    states=("p [m]", "v [m/s]"),
    actions=("a [m/s^2]",),
    rhs=double_integrator,
    action_max=(1.0,),
    cost_diag=(1.0, 0.5, 0.05),
    start=(1.0, 0.0),
)


@pytest.fixture
def registered() -> Iterator[System]:
    register_system(NAME, DOUBLE_INTEGRATOR)
    try:
        yield DOUBLE_INTEGRATOR
    finally:
        del SYSTEMS[NAME]  # other tests of this process see srl's rows only


def test_the_unicycle_row_is_the_paper_robot_and_the_settings_defaults() -> None:
    settings = Settings.load()
    assert BUILT_IN_SYSTEMS == ("unicycle", "dynamic_unicycle", "pendulum", "cartpole", "two_tank")
    assert system_row("unicycle") is UNICYCLE and settings.system is UNICYCLE
    assert (UNICYCLE.state_dim, UNICYCLE.action_dim, UNICYCLE.q_features, UNICYCLE.v_features) == (3, 2, 15, 6)
    rng = np.random.default_rng(0)
    for _ in range(20):
        state, action = rng.normal(size=3), rng.normal(size=2)
        assert np.array_equal(UNICYCLE.rhs(state, action), unicycle_rhs(state, action))
        assert np.array_equal(UNICYCLE.step(state, action, DELTA), exact_step(state, action, DELTA))
    assert UNICYCLE.cost_diag == tuple(settings.r_diag)
    assert UNICYCLE.action_max == (settings.plant.v_max, settings.plant.omega_max)
    assert np.array_equal(np.array(UNICYCLE.start), settings.start_state())
    assert UNICYCLE.distance(np.array([0.03, 0.04, 2.0])) == pytest.approx(0.05)  # the heading aside


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"states": ()}, "at least one state"),
        ({"action_max": (1.0, 2.0)}, "action_max: 1 positive"),
        ({"action_max": (0.0,)}, "action_max: 1 positive"),
        ({"cost_diag": (1.0, 1.0)}, "cost_diag: 3 finite"),
        ({"cost_diag": (1.0, -1.0, 1.0)}, "cost_diag: 3 finite"),
        ({"start": (1.0, math.nan)}, "start: 2 finite"),
        ({"wheeled": True}, "wheeled"),
        ({"stabilized": 0.0}, "stabilized"),
        ({"substeps": 0}, "substeps"),
    ],
)
def test_a_system_that_cannot_be_is_refused_in_one_line(changes: dict[str, Any], message: str) -> None:
    fields = {name: getattr(DOUBLE_INTEGRATOR, name) for name in DOUBLE_INTEGRATOR.__dataclass_fields__}
    with pytest.raises(ValueError, match=message) as refused:
        System(**(fields | changes))
    assert "\n" not in str(refused.value)


def test_a_system_name_is_checked_and_never_replaces_a_row(registered: System) -> None:
    with pytest.raises(ValueError, match="exists already"):
        register_system("unicycle", DOUBLE_INTEGRATOR)
    with pytest.raises(ValueError, match="1-32 of"):
        register_system("Double Integrator", DOUBLE_INTEGRATOR)
    with pytest.raises(ValueError, match=r"unknown system 'pendulum9' \(unicycle, .*, two_tank, double_integrator\)"):
        system_row("pendulum9")
    assert system_row(NAME) is registered


def test_without_its_row_no_problem_names_the_system() -> None:
    # the negative control of the tests below: the system is the row, not a string srl knows
    with pytest.raises(ValueError, match="unknown system 'double_integrator'"):
        ActorProblem("mpc", 6, DELTA, DOUBLE_INTEGRATOR.cost_diag, DOUBLE_INTEGRATOR.action_max, system=NAME)


def test_a_system_without_a_closed_form_is_integrated_by_rk4_substeps(registered: System) -> None:
    # the double integrator's exact sample-and-hold: p + v h + a h^2 / 2, v + a h
    rng = np.random.default_rng(1)
    for _ in range(20):
        (p, v), a = rng.normal(size=2), rng.normal()
        exact = np.array([p + v * DELTA + a * DELTA**2 / 2, v + a * DELTA])
        np.testing.assert_allclose(registered.step(np.array([p, v]), np.array([a]), DELTA), exact, atol=1e-14)


def test_the_wheel_box_is_refused_for_a_system_without_wheels(registered: System) -> None:
    with pytest.raises(ValueError, match="double_integrator has no wheels"):
        ActorProblem("mpc", 6, DELTA, registered.cost_diag, registered.action_max, system=NAME, wheel_speed_max=6.67)


@pytest.mark.parametrize(("agent", "srl"), [("mpc", False), ("rlqv", False), ("rlqv", True), ("rlq", True)])
def test_algorithm1_stabilizes_the_users_own_system_in_process(registered: System, agent: str, srl: bool) -> None:
    """The user's system through every floor Algorithm 1 uses: the actor's CasADi problem (its
    dimensions, its predictor, its box), the critics' features and TD fit (sized by the
    weights), the plant (RK4 substeps), the loop. 12 s from p = 1 m at rest, with the settings'
    critic (discount, ridge, weight box, started at the discounted stage cost) and the paper's
    actor, or srl's (``srl``: the argmin and the convexified critics)."""
    system, n, settings = registered, registered.state_dim, Settings.load()
    problem = ActorProblem(
        agent,
        8,
        DELTA,
        system.cost_diag,
        system.action_max,
        system=NAME,
        jit=False,
        multistart=srl,
        convex_critics=srl,
    )
    discount = settings.discount
    scale = DELTA / (1.0 - discount)
    critic = LocalCritic(
        scale * quadratic_weights_for_diag(system.cost_diag),
        scale * quadratic_weights_for_diag(system.cost_diag[:n]),
        discount,
        settings.critic.ridge,
        settings.critic.bounds,
        30,
        1,
        learn=agent != "mpc",
    )
    (episode,) = run_algorithm1(
        StackedActor(problem),
        [ExactPlant(system)],
        [critic],
        [np.array(system.start)],
        120,
        DELTA,
        system.cost_diag,
    )
    actions = np.array(episode.actions)
    assert actions.shape == (120, 1) and np.all(np.abs(actions) <= system.action_max[0] + 1e-9)
    assert episode.solver_failures == 0
    assert system.distance(episode.final_state) < system.stabilized, episode.final_state
    assert np.array(episode.states).shape == (121, 2)
    fitted = not np.array_equal(episode.q_weights[-1], episode.q_weights[0])
    assert fitted == (agent != "mpc") and episode.q_weights[-1].shape == (6,) and episode.v_weights[-1].shape == (3,)


# -- the built-in systems, through srl run -----------------------------------------------------


def run_json(*argv: str, capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    from tools.cli import main

    assert main(["run", *argv, "--no-jit", "--json"]) == 0
    return dict(json.loads(capsys.readouterr().out.strip().splitlines()[-1]))


@pytest.mark.parametrize(
    ("system", "agent"),
    [("pendulum", "rlqv"), ("cartpole", "rlqv"), ("two_tank", "rlqv"), ("dynamic_unicycle", "rlqv")],
)
def test_srl_run_stabilizes_each_built_in_system_from_its_start(
    system: str, agent: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """20 s from the row's start, the settings' actor and critic (RL-QV at the row's horizon: N =
    12, the dynamic robot's 20): the summary says how close, in the system's own terms."""
    row = system_row(system)
    summary = run_json("--system", system, "--agent", agent, "--duration", "20", capsys=capsys)
    assert summary["system"] == system and summary["steps"] == 200 and summary["horizon"] == row.horizon
    assert summary["start_state"] == list(row.start)
    assert len(summary["final_state"]) == row.state_dim
    assert summary["final_distance"] == row.distance(np.array(summary["final_state"]))
    assert summary["final_distance"] < row.stabilized
    assert summary["settings"]["cost"]["r_diag"] == list(row.cost_diag)  # the row's own, [] in srl.toml


def test_a_start_of_the_wrong_size_and_the_services_are_refused_in_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from tools.cli import main

    cases = [
        (["run", "--system", "cartpole", "--start", "1,2"], "episode.start: 4 numbers, cartpole's state"),
        (["run", "--system", "pendulum", "--record", "p.mcap"], "--record: carries the robot's pose"),
    ]
    for argv, message in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    monkeypatch.setenv("SRL_PLANT__SYSTEM", "two_tank")
    for argv in (  # a TurtleBot3's services carry the robot's pose (plant_sim, actor and critic any system's)
        ["robot-bridge", "--connect-timeout", "1"],
        ["tb3-emulator", "--connect-timeout", "1"],
        ["up", "--plant", "robot", "--duration", "1"],
        ["experiment", "fleet", "--grid", "1"],
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "system two_tank runs in process" in err and err.count("\n") == 1, err
    from tools.gym.envs import env_settings

    # an environment's id names its system: the variable does not turn the robot's into two tanks
    assert env_settings(None, "ideal").plant.system == "unicycle"


@pytest.mark.parametrize("name", BUILT_IN_SYSTEMS)
def test_each_rows_model_is_one_function_for_numpy_and_casadi(name: str) -> None:
    """The actor predicts with the CasADi graph of the same ``f`` the plant integrates in numpy."""
    import casadi as ca

    row = system_row(name)
    s, u = ca.SX.sym("s", row.state_dim), ca.SX.sym("u", row.action_dim)
    graph = ca.Function("f", [s, u], [row.rhs(s, u)])
    rng = np.random.default_rng(2)
    for _ in range(10):
        state, action = rng.normal(size=row.state_dim), rng.normal(size=row.action_dim)
        numeric = row.rhs(state, action)
        assert numeric.shape == (row.state_dim,)
        np.testing.assert_allclose(np.array(graph(state, action)).ravel(), numeric, rtol=1e-12, atol=1e-12)
    assert np.all(row.rhs(np.zeros(row.state_dim), np.zeros(row.action_dim)) == 0.0)  # the goal is at rest


def test_the_pendulums_torque_holds_it_up_to_28_degrees_and_no_further() -> None:
    row = system_row("pendulum")
    hold = PENDULUM_MASS * 9.81 * PENDULUM_LENGTH / 2  # [N m] to hold it horizontal
    limit = math.asin(row.action_max[0] / hold)
    assert math.degrees(limit) == pytest.approx(28.4, abs=0.1)
    for theta, falls in ((0.9 * limit, False), (1.1 * limit, True)):
        accel = row.rhs(np.array([theta, 0.0]), np.array([-row.action_max[0]]))[1]
        assert (accel > 0) == falls


def test_srl_run_runs_a_registered_system(
    registered: System, capsys: pytest.CaptureFixture[str], tmp_path: Any
) -> None:
    """The command line offers the row registered in this process (as SRL_PLUGINS registers one
    before the parser is built) and runs it with its own box, cost and start; --plot draws its
    states and actions by their names."""
    figure = tmp_path / "run.png"
    summary = run_json("--system", NAME, "--duration", "12", "--plot", str(figure), capsys=capsys)
    assert summary["system"] == NAME and summary["start_state"] == [1.0, 0.0]
    assert summary["final_distance"] < registered.stabilized
    assert summary["plot"] == str(figure) and figure.stat().st_size > 10_000


@pytest.mark.integration
def test_the_example_system_runs_through_srl_plugins() -> None:
    """examples/double_integrator.py, a user's file named in SRL_PLUGINS: ``srl run --system
    double_integrator`` stabilizes it; without the plugin the name is refused with one line."""
    from tests.harness import srl

    argv = ["run", "--system", NAME, "--duration", "12", "--no-jit", "--json"]
    done = srl(*argv, env={"SRL_PLUGINS": "examples/double_integrator.py"})
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["system"] == NAME and summary["final_distance"] < DOUBLE_INTEGRATOR.stabilized
    refused = srl(*argv, env={"SRL_PLUGINS": ""})
    assert refused.returncode == 2 and "invalid choice: 'double_integrator'" in refused.stderr


@pytest.mark.integration
def test_the_experiment_runs_the_users_system_in_its_worker_processes(tmp_path: Any) -> None:
    """SRL_PLUGINS reaches the experiment's workers (spawned interpreters): the user's system runs
    there as a built-in one does."""
    from tests.harness import srl

    out = tmp_path / "di"
    plugin = {"SRL_PLUGINS": "examples/double_integrator.py", "SRL_ACTOR__JIT": "false"}
    done = srl("experiment", "paper", "--system", NAME, "--grid", "2", "--horizons", "6", "--agents", "mpc,rlqv",
               "--duration", "12", "--workers", "1", "--no-progress", "--no-plots", "--out", str(out),
               env=plugin, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["experiment"]["system"] == NAME and summary["runs_completed"] == 8
    assert all(g["parked"] == g["runs"] for g in summary["groups"])  # every run stabilized within 0.05
    # its start box spans p only (v's width is 0): 2 x 2 starts along p, none twice
    starts = sorted({(r["start_x"], r["start_y"]) for r in read_runs_csv(out / "runs.csv")})
    assert starts == [(p, 0.0) for p in np.linspace(-1.0, 1.0, 4)]


# -- Gymnasium ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", [name for name in BUILT_IN_SYSTEMS if name != "unicycle"])
def test_each_systems_gymnasium_environment_passes_both_checkers(name: str) -> None:
    """``srl/<System>-v0``: Gymnasium's checker (and, through ``make``, its passive checker) on the
    system's own spaces; a step's reward is minus its stage cost, a given start is the state."""
    import warnings

    import gymnasium
    from gymnasium.utils.env_checker import check_env

    import tools.gym  # noqa: F401 - registers the ids

    row = system_row(name)
    env = gymnasium.make(gymnasium_id(name))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=True)
    assert not [w for w in caught if "infinity" not in str(w.message) and "normalized" not in str(w.message)]
    assert env.observation_space.shape == (row.state_dim,)
    assert env.action_space.high.tolist() == list(row.action_max)
    state, _ = env.reset(seed=3)
    box = np.array(row.start_box or [abs(c) for c in row.start])
    assert state.shape == (row.state_dim,) and np.all(np.abs(state) <= box)
    start = np.array(row.start)
    state, _ = env.reset(options={"start": start})
    assert np.array_equal(state, start)
    action = np.array(row.action_max) / 2
    following, reward, terminated, truncated, info = env.step(action)
    r = np.array(row.cost_diag)
    assert reward == -info["cost"] and info["cost"] == pytest.approx(
        DELTA * float(r @ np.concatenate([start, action]) ** 2)
    )
    np.testing.assert_array_equal(following, row.step(start, action, DELTA))
    assert not terminated and not truncated
    with pytest.raises(ValueError, match=f"a start is {row.state_dim} finite numbers"):
        env.reset(options={"start": [1.0] * (row.state_dim + 1)})


def test_the_gymnasium_environment_runs_a_registered_system(registered: System) -> None:
    from gymnasium.utils.env_checker import check_env

    from tools.gym.envs import SrlEnv

    env = SrlEnv(system=NAME, starts="box")
    check_env(env, skip_render_check=True)
    state, _ = env.reset(seed=1)
    assert state.shape == (2,) and env.action_space.shape == (1,)


# -- the experiment -------------------------------------------------------------------------------


def test_the_starts_of_another_system_span_its_start_box_and_never_the_goal() -> None:
    from tools.experiment.grid import make_starts

    pendulum = system_row("pendulum")
    lattice = make_starts("paper", 3, 2.0, 0, pendulum)
    assert [s.values for s in lattice] == [
        (theta, omega) for omega in (-0.5, 0.0, 0.5) for theta in (-0.4, 0.0, 0.4) if (theta, omega) != (0.0, 0.0)
    ]
    assert math.isnan(lattice[0].alpha) and (lattice[0].x, lattice[0].y) == (-0.4, -0.5)  # runs.csv's columns
    held_out = make_starts("held-out", 3, 2.0, 7, system_row("cartpole"))
    assert len(held_out) == 9 and all(len(s.values) == 4 and s.values[2:] == (0.0, 0.0) for s in held_out)
    assert all(abs(s.values[0]) <= 0.5 and abs(s.values[1]) <= 0.2 for s in held_out)
    assert held_out == make_starts("held-out", 3, 2.0, 7, system_row("cartpole"))  # seeded


@pytest.mark.integration
def test_srl_experiment_paper_runs_another_system(tmp_path: Any) -> None:
    """``srl experiment paper --system pendulum``: its starts, J/J_mpc per agent and N, how many
    stabilized, the claims, the figures; over the Zenoh transport the same runs; ``--extent`` (the
    robot's) and ``--record`` refused."""
    from tests.harness import srl

    out = tmp_path / "pendulum"
    argv = ["experiment", "paper", "--system", "pendulum", "--grid", "2", "--horizons", "6", "--agents", "mpc,rlqv"]
    done = srl(*argv, "--duration", "10", "--workers", "1", "--no-progress", "--out", str(out),
               env={"SRL_ACTOR__JIT": "false"}, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["experiment"]["system"] == "pendulum" and summary["runs_completed"] == 8
    assert summary["park_tolerance_m"] == system_row("pendulum").stabilized
    rlqv = next(g for g in summary["groups"] if g["agent"] == "rlqv")
    assert rlqv["ratios"] == 4 and rlqv["parked"] <= 4 and math.isfinite(rlqv["median_ratio_percent"])
    markdown = (out / "summary.md").read_text()
    assert "system pendulum" in markdown and "| stabilized |" in markdown and "--system=pendulum" in markdown
    assert {"ratio_N6.png", "trajectories.png"} <= set(summary["plots"])
    states = np.load(out / "trajectories.npz")["states"]
    assert states.shape == (8, 101, 2)
    # over the lockstep services (a router, a plant and a critic per worker): the same runs, bit for bit
    zenoh = srl(*argv, "--duration", "10", "--workers", "1", "--no-progress", "--out", str(tmp_path / "zenoh"),
                "--transport", "zenoh", env={"SRL_ACTOR__JIT": "false"}, timeout=300)  # fmt: skip
    assert zenoh.returncode == 0, zenoh.stderr[-2000:]
    costs = [[row["accumulated_cost"] for row in read_runs_csv(d / "runs.csv")] for d in (out, tmp_path / "zenoh")]
    assert costs[0] == costs[1] and len(costs[0]) == 8
    for extra, says in ((["--extent", "1"], "--extent"), (["--record", str(tmp_path / "r.mcap")], "--record")):
        refused = srl(*argv, *extra, "--out", str(tmp_path / "no"), timeout=120)
        assert refused.returncode == 2 and says in refused.stderr and "runs in process" in refused.stderr


# -- the systems' pages (tools/docs/systems.py) ------------------------------------------------
def test_every_built_in_system_has_a_page_with_its_box_and_its_kept_results() -> None:
    from tools.docs.systems import data_dir, pages

    found = pages(ROOT)
    assert sorted(found) == sorted(Path("docs/reference/systems") / f"{name}.md" for name in BUILT_IN_SYSTEMS)
    for name in BUILT_IN_SYSTEMS:
        page, system = found[Path("docs/reference/systems") / f"{name}.md"], SYSTEMS[name]
        for entry in (*system.states, *system.actions, f"< {system.stabilized:g}", f"`{gymnasium_id(name)}`"):
            assert entry in page, (name, entry)
        summary = json.loads((ROOT / data_dir(name) / "summary.json").read_text())
        assert summary["experiment"].get("system", "unicycle") == name  # the kept results are the system's
        assert f"`{summary['experiment']['command']}`" in page and "| rlqv | 12 | " in page
        assert ("exact" in page) == (system.exact_step is not None)


def test_a_pages_step_error_is_the_integrators_and_small() -> None:
    from tools.docs.systems import plant_step, step_error

    for name in ("pendulum", "cartpole", "two_tank", "dynamic_unicycle"):
        error = step_error(SYSTEMS[name])
        assert 0 < error < 1e-5, (name, error)  # RK4 over a tenth of a second, in 10 steps
        assert f"{error:.1e}" in plant_step(SYSTEMS[name])
    coarse = dataclasses.replace(SYSTEMS["pendulum"], substeps=1)  # the negative control: one RK4 step
    assert step_error(coarse) > 100 * step_error(SYSTEMS["pendulum"])


def test_srl_docs_systems_keeps_each_experiments_summary_and_figures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tools.docs.systems import KEPT, run_experiments

    calls = []

    def fake_srl(argv: list[str]) -> int:  # what srl experiment paper writes, without running it
        calls.append(argv)
        print(f"# srl experiment paper ... results in {argv[-1]}/")  # its own output, kept back
        out = Path(argv[argv.index("--out") + 1])
        out.mkdir()
        for name in (*KEPT, "runs.csv", "summary.md", "trajectories.npz"):
            (out / name).write_text(f"{name} of call {len(calls)}")
        return 0

    written = run_experiments(tmp_path, fake_srl)
    said = capsys.readouterr()
    assert "results in" not in said.out + said.err and "srl docs: srl experiment paper --system pendulum: " in said.err
    others = [name for name in BUILT_IN_SYSTEMS if not SYSTEMS[name].wheeled]
    assert [argv[argv.index("--system") + 1] for argv in calls] == others
    assert sorted(written) == sorted(f"docs/paper/systems/{n}/{k}" for n in others for k in KEPT)
    assert not (tmp_path / "docs/paper/systems/pendulum/summary.md").exists()  # never a page of its own
    assert not any(Path(argv[argv.index("--out") + 1]).exists() for argv in calls)  # the scratch removed
    before = (tmp_path / "docs/paper/systems/pendulum/summary.json").read_text()

    def failing(argv: list[str]) -> int:
        if "cartpole" in argv:
            print("srl experiment: error: no cores left")
            return 3
        return fake_srl(argv)

    with pytest.raises(RuntimeError, match="cartpole exited 3: srl experiment: error: no cores left"):
        run_experiments(tmp_path, failing, ("pendulum", "cartpole"))  # pendulum ran, cartpole failed: nothing kept
    assert (tmp_path / "docs/paper/systems/pendulum/summary.json").read_text() == before


def test_srl_docs_refuses_systems_with_check(capsys: pytest.CaptureFixture[str]) -> None:
    from tools.cli import main

    assert main(["docs", "--check", "--systems"]) == 2
    error = capsys.readouterr().err.strip()
    assert "does not go with --check" in error and len(error.splitlines()) == 1


def test_a_problem_and_a_system_refuse_a_bad_box_or_cost_in_the_same_words() -> None:
    assert name_and_unit("x [m]") == ("x", "m") and name_and_unit("h") == ("h", "")
    for field, bad in (("action_max", (0.22,)), ("cost_diag", (1.0, 1.0))):
        problem = {"agent": "mpc", "horizon": 4, "sampling_time": 0.1, "cost_diag": UNICYCLE.cost_diag}
        problem |= {"action_max": UNICYCLE.action_max, field: bad}
        with pytest.raises(ValueError) as from_problem:
            ActorProblem(**problem)
        with pytest.raises(ValueError) as from_row:
            dataclasses.replace(UNICYCLE, **{field: bad})
        assert str(from_problem.value) == str(from_row.value) and str(from_row.value).startswith(f"{field}: ")


# -- another system through the lockstep services (srl up --mode lockstep --system) ---------------
@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("name", ["pendulum", "dynamic_unicycle"])  # one action; two
def test_the_lockstep_services_run_another_system_as_in_process_bit_for_bit(name: str) -> None:
    """``srl run --transport zenoh`` is ``srl up --mode lockstep``: a router, the plant, the critic
    and the actor, each a process, carrying the system's messages (common/contracts/wire.py).
    Its states, costs and J are the in-process run's, to the last bit."""
    from tests.harness import free_port, srl

    argv = ["run", "--system", name, "--duration", "3", "--no-jit", "--json", "--trajectory"]
    local = srl(*argv)
    assert local.returncode == 0, local.stderr[-2000:]
    remote = srl(*argv, "--transport", "zenoh", "--router", f"tcp/127.0.0.1:{free_port()}", timeout=240)
    assert remote.returncode == 0, remote.stderr[-3000:]
    one, other = (json.loads(done.stdout.strip().splitlines()[-1]) for done in (local, remote))
    assert other["transport"] == "zenoh" and other["system"] == name
    assert other["trajectory"] == one["trajectory"] and len(one["trajectory"][0]) == SYSTEMS[name].state_dim
    assert other["accumulated_cost"] == one["accumulated_cost"] and other["final_distance"] == one["final_distance"]
    assert f"system {name}" in remote.stdout and "distance to the goal" in remote.stdout


@pytest.mark.integration
@pytest.mark.slow
def test_srl_up_lockstep_runs_a_users_system_and_says_how_close_it_came(tmp_path: Path) -> None:
    """examples/double_integrator.py through SRL_PLUGINS in every service process: ``srl up --mode
    lockstep --system double_integrator`` stabilizes it and says so in its own terms."""
    from tests.harness import free_port, srl

    env = {"SRL_PLUGINS": "examples/double_integrator.py", "SRL_ACTOR__JIT": "false"}
    done = srl(
        "up", "--mode", "lockstep", "--system", NAME, "--duration", "12", "--json", "--router",
        f"tcp/127.0.0.1:{free_port()}", "--robot", "di1", "--summary-dir", str(tmp_path / "up"),
        env=env, timeout=240,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["system"] == NAME and summary["steps"] == 120
    assert summary["final_distance"] < DOUBLE_INTEGRATOR.stabilized
    assert summary["critic"]["transitions_received"] == 120  # every transition reached the off-board critic
    assert summary["weights_version"] > 1  # and its fits came back
    assert f"stabilized (< {DOUBLE_INTEGRATOR.stabilized:g})" in done.stderr + done.stdout
    assert "p = " in done.stderr + done.stdout  # the state by its names


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timing  # no deadline missed: a real-time bound, run alone
def test_srl_up_in_real_time_runs_a_users_system_from_its_start_and_stabilizes_it(tmp_path: Path) -> None:
    """``srl up --system double_integrator`` (real time, the default; the row from SRL_PLUGINS in
    every service process): the plant waits at the start for the actor's first action (a system a
    zero action does not hold would be gone before its actor is built), the actor ticks on time,
    every transition reaches the critic, and the run ends stabilized, said in the system's terms."""
    from tests.harness import free_port, srl

    env = {"SRL_PLUGINS": "examples/double_integrator.py", "SRL_ACTOR__JIT": "false"}
    done = srl(
        "up", "--system", NAME, "--duration", "12", "--json", "--router", f"tcp/127.0.0.1:{free_port()}",
        "--robot", "di2", "--summary-dir", str(tmp_path / "up"), env=env, timeout=240,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["mode"] == "realtime" and summary["system"] == NAME
    assert summary["start_state"] == list(DOUBLE_INTEGRATOR.start)  # it waited for its actor
    assert summary["loop"]["missed_deadlines"] == 0, summary["loop"]
    assert summary["final_distance"] < DOUBLE_INTEGRATOR.stabilized, summary["final_state"]
    assert summary["truth"]["final_distance"] == summary["final_distance"]  # the simulator's truth
    assert summary["critic"]["transitions_received"] == summary["steps"] >= 100
    assert summary["weights_version"] > 1
    assert f"stabilized (< {DOUBLE_INTEGRATOR.stabilized:g})" in done.stderr + done.stdout


def test_a_fleet_of_another_system_starts_at_its_start_and_in_its_start_box() -> None:
    """fleet_starts: the robot's fleet on the circle; another system's first robot at the row's
    start, the others drawn in its start box, the same every call."""
    from common.math.fleet import circle_starts, fleet_starts

    assert fleet_starts(UNICYCLE, 4, 1.5) == circle_starts(4, 1.5)
    row = system_row("pendulum")
    starts = fleet_starts(row, 5, 1.5)
    assert starts[0] == row.start and len(set(starts)) == 5 and starts == fleet_starts(row, 5, 9.0)
    assert all(len(s) == 2 and all(abs(c) <= w for c, w in zip(s, row.box_of_starts, strict=True)) for s in starts)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timing  # no deadline missed, and a swing that a starved solve can spoil: run alone
def test_srl_up_runs_a_fleet_of_another_system_in_one_plant_host_and_one_actor_host(tmp_path: Path) -> None:
    """``srl up --system pendulum --robots 3``: one plant host and one actor host of three
    pendulums (the same hosts as the robots'), each from its own start; every one stabilized with
    no deadline missed, every transition at the critic, the table saying so in the system's terms."""
    from tests.harness import free_port, srl

    done = srl(
        "up", "--system", "pendulum", "--robots", "3", "--duration", "12", "--json", "--router",
        f"tcp/127.0.0.1:{free_port()}", "--summary-dir", str(tmp_path / "up"), timeout=240,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    fleet = summary["fleet"]
    assert summary["system"] == "pendulum" and fleet["robots"] == 3
    # on a failure, each robot's row whole (pytest cuts a long list) and what the actor logged
    actor = json.loads((tmp_path / "up" / "actor.json").read_text())
    counters = {robot: run["counters"] for robot, run in actor["per_robot"].items()}
    said = json.dumps([fleet["rows"], summary["per_robot_final"], counters, actor["counters"]]) + done.stderr[-4000:]
    assert fleet["missed_deadlines"] == 0 and fleet["parked"] == 3, said
    assert all(row["final_distance_m"] < system_row("pendulum").stabilized for row in fleet["rows"]), said
    assert summary["critic"]["transitions_received"] == fleet["steps"]
    finals = summary["per_robot_final"]
    assert all(len(state) == 2 for state in finals.values())
    assert "system pendulum from its start and its start box" in done.stdout + done.stderr


@pytest.mark.integration
def test_what_carries_the_robots_pose_refuses_another_system_in_one_line(tmp_path: Path) -> None:
    from tests.harness import free_port, srl

    router = f"tcp/127.0.0.1:{free_port()}"
    for extra, says in (
        (["--mode", "lockstep", "--record", str(tmp_path / "r.mcap")], "--record"),
        (["--plant", "robot"], "--plant robot"),
        (["--plant", "physics"], "--plant physics"),
    ):
        refused = srl("up", "--system", "pendulum", "--duration", "1", "--router", router, *extra, timeout=60)
        errors = [line for line in refused.stderr.splitlines() if "error" in line.lower()]
        assert refused.returncode == 2 and len(errors) == 1, (extra, refused.stderr[-2000:])
        assert says in errors[0] and "srl up --system pendulum" in errors[0], errors[0]
        assert "Traceback" not in refused.stderr


def test_another_systems_critic_keeps_a_checkpoint_of_its_own() -> None:
    """The robot's checkpoint is never read (nor set aside) by another system's critic."""
    from services.critic.service import checkpoint_path

    robot = checkpoint_path(Settings.load())
    pendulum = checkpoint_path(Settings.load(plant={"system": "pendulum"}))
    assert robot is not None and pendulum is not None and pendulum != robot
    assert pendulum.name == robot.stem + "-pendulum" + robot.suffix
