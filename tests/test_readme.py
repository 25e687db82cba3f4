"""The README's commands work as written, and every one of them is run by a test or by CI.

* The first command is run as written and prints the J the README quotes next to it.
* The compose commands of "Containers" are, character for character, the ones .ci/compose-test
  runs (its ``readme_*`` lines): CI runs exactly what a user reads.
* ``COVERAGE`` says, for every command line of the README's ``bash`` blocks, which test or CI
  step runs it; a command added to the README without an entry here fails this test, and so
  does an entry whose command is no longer in the README or whose test does not exist.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.harness import ROOT, free_port

README = (ROOT / "README.md").read_text()
COMPOSE_TEST = (ROOT / ".ci" / "compose-test").read_text()
NOT_IN_CI = "(not in CI)"
# a comment: `#` after whitespace, followed by whitespace (not `"*"`, not `--start=-1,2`)
COMMENT = re.compile(r"\s+#(?:\s.*)?$")
J_IN_OUTPUT = re.compile(r"\bJ\b[^0-9\n-]*(-?[0-9]+\.[0-9]+)")

ADD_A_HOST = (
    "tests/test_tls.py::test_readme_add_a_host_steps_work (as written; two home directories for the two "
    "hosts, loopback and a free port for the addresses, `srl` = this checkout's)"
)

ACROSS_HOSTS = (
    "tests/test_netns_fleet.py::test_fleet_across_three_hosts_with_linked_routers_survives_a_partition "
    "(as written, each host a network namespace: C's address on their bridge; the actors with --run-seconds)"
)

# README command -> who runs it ("CI: ..." or a test as path::name, plus how it differs)
COVERAGE: dict[str, str] = {
    "./srl run --agent rlqv --horizon 12 --start 2,2 --duration 30": "tests/test_readme.py::test_first_command_prints_the_j_the_readme_quotes (as written)",
    "./srl test": "CI: .ci/run (as `SRL_TEST_REQUIRE_ALL=1 ./srl test`)",
    "./srl up --plant robot --duration 20": "tests/test_readme.py::test_srl_up_examples_run (a free router port, --duration 6)",
    "./srl up --plant robot --profile ros2dds --ros-distro humble --duration 20": "tests/test_readme.py::test_srl_up_examples_run (a free router port, --duration 6)",
    "./srl up --plant robot --robot-endpoint tcp/<robot-ip>:7447 --ros-distro jazzy": "tests/test_robot_bridge.py::test_up_with_a_robot_endpoint_starts_no_emulator (an emulator as the robot)",
    "srl certs --out ~/srl-secrets --hosts robot-pc --passwords": ADD_A_HOST,
    "SRL_TRANSPORT__SECURE=true SRL_TRANSPORT__USERS_FILE=~/srl-secrets/users.txt SRL_TRANSPORT__TLS_CA=~/srl-secrets/ca.pem SRL_TRANSPORT__TLS_CERT=~/srl-secrets/router.pem SRL_TRANSPORT__TLS_KEY=~/srl-secrets/router.key srl router --router tls/0.0.0.0:7447": ADD_A_HOST,
    "ssh new-host 'mkdir -m 700 -p ~/srl-secrets'": ADD_A_HOST,
    "scp ~/srl-secrets/{ca.pem,critic.pem,critic.key,critic.password} new-host:srl-secrets/": ADD_A_HOST,
    "export SRL_TRANSPORT__ROUTER=tls/robot-pc:7447 SRL_TRANSPORT__SECURE=true SRL_TRANSPORT__USER=critic": ADD_A_HOST,
    "export SRL_TRANSPORT__PASSWORD_FILE=~/srl-secrets/critic.password SRL_TRANSPORT__TLS_CA=~/srl-secrets/ca.pem": ADD_A_HOST,
    "export SRL_TRANSPORT__TLS_CERT=~/srl-secrets/critic.pem SRL_TRANSPORT__TLS_KEY=~/srl-secrets/critic.key": ADD_A_HOST,
    "srl critic": ADD_A_HOST,
    "./srl up --robots 50 --duration 30": "tests/test_fleet.py::test_a_fleet_of_three_gets_actions_approaches_and_reports_per_robot (3 robots, 8 s, run_fleet as srl up --robots runs it)",
    "./srl up --robots 25 --critic pooled --duration 30": "tests/test_readme.py::test_srl_up_examples_run (a free router port, --duration 6); tests/test_pooled_critic.py::test_a_fleet_with_a_pooled_critic_gets_the_pools_weights_and_approaches (3 robots, 8 s)",
    "./srl experiment fleet": "tests/test_pooled_critic.py::test_experiment_fleet_per_robot_gives_the_paper_experiments_j_and_pooled_beside_it (a 2 x 2 grid, 2 s, N = 6)",
    "./srl up --robots 3 --plant robot --duration 20": "tests/test_readme.py::test_srl_up_examples_run (a free router port, --duration 6); tests/test_robot_fleet.py::test_up_three_emulated_turtlebots",
    "./srl up --robots tb3_1,tb3_2 --plant robot --robot-endpoints tb3_1=tcp/<robot-1-ip>:7447,tb3_2=tcp/<robot-2-ip>:7447 --ros-distro jazzy": "tests/test_robot_fleet.py::test_fleet_on_one_shared_robot_router_keeps_robots_apart (emulators as the robots, one on its own router, two through --robot-endpoint)",
    "./srl bench fleet": "tests/test_fleet.py::test_the_fleet_bench_prints_host_and_baseline_rows_with_the_load_and_cleans_up (--robots 2 --baseline 2 --seconds 5)",
    "./srl bench fleet --robots 50 --baseline '' --seconds 600": "tests/test_fleet.py::test_the_fleet_bench_prints_host_and_baseline_rows_with_the_load_and_cleans_up (--robots 2 --baseline 2 --seconds 5); tests/test_capacity.py::test_the_rss_series_is_bounded_and_its_growth_starts_after_warm_up (the soak's growth)",
    "./srl bench capacity": "tests/test_capacity.py::test_the_capacity_bench_measures_every_component_and_the_messages (--robots 1,3 --seconds 6)",
    "SRL_TRANSPORT__ALLOW_INSECURE_NETWORK=true srl router --router tcp/0.0.0.0:7447": ACROSS_HOSTS,
    "srl critic --robots a1,a2,a3,d1,d2,d3": ACROSS_HOSTS,
    "SRL_TRANSPORT__ALLOW_INSECURE_NETWORK=true srl router --router tcp/0.0.0.0:7447 --connect tcp/192.168.1.13:7447": ACROSS_HOSTS,
    "srl plant-sim --robots a1,a2,a3": ACROSS_HOSTS,
    "srl actor --robots a1,a2,a3": ACROSS_HOSTS,
    "./srl experiment paper": "tests/test_experiment.py::test_reduced_grid_writes_every_output_consistently (a reduced grid)",
    "./srl experiment paper --starts held-out": "tests/test_experiment.py::test_held_out_grid_one_seeded_start_per_cell_never_on_the_lattice (the grid)",
    "./srl experiment paper --transport zenoh": "tests/test_experiment.py::test_zenoh_transport_gives_the_inproc_numbers (a reduced grid)",
    "./srl run --agent rlqv --horizon 12 --start 2,2 --duration 30 --record run.mcap": "tests/test_record.py::test_srl_run_and_srl_up_record_the_runs_trajectory_and_srl_plot_draws_it (--start 1.5,1 --duration 3, a temporary file)",
    "./srl plot run.mcap": "tests/test_record.py::test_srl_run_and_srl_up_record_the_runs_trajectory_and_srl_plot_draws_it (the srl up recording, --out in a temporary directory)",
    "./srl up --plant robot --duration 20 --record /tmp/robot.mcap": "tests/test_readme.py::test_srl_up_examples_run (a free router port, --duration 6); tests/test_record.py::test_srl_up_with_the_robot_records_its_odometry_and_srl_plot_replays_it",
    "./srl record /tmp/fleet.mcap": "tests/test_record.py::test_srl_record_joins_a_running_system_and_closes_the_file_on_a_signal (a free router port, a temporary file)",
    "./srl experiment paper --record paper.mcap": "tests/test_record.py::test_the_experiment_records_every_run_as_trajectories_npz_holds_it (a 2 x 2 grid, 2 s)",
    "./srl view": "tests/test_record.py::test_srl_view_serves_the_running_robots_poses_over_the_foxglove_websocket_protocol (--port 0, a free router port)",
    "./srl bench loop --record --seconds 30 --rounds 3": "tests/test_record.py::test_srl_bench_loop_record_compares_the_loop_without_and_with_a_recorder (--seconds 4 --rounds 1)",
}


def bash_commands(text: str) -> list[tuple[str, str]]:
    """(command, its comment) of every logical line of every ```bash block, continuations joined."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        logical = ""
        for line in block.splitlines():
            body = COMMENT.sub("", line)
            comment = line[len(body) :].strip()
            if body.rstrip().endswith("\\"):
                logical += body.rstrip()[:-1].strip() + " "
                continue
            logical += body.strip()
            if logical:
                commands.append((logical, comment))
            logical = ""
    return commands


def section(title: str) -> str:
    start = README.index(f"\n## {title}")
    end = README.find("\n## ", start + 1)
    return README[start : end if end > 0 else None]


def compose_test_commands() -> list[str]:
    return re.findall(r"^readme_\w+='(.*)'$", COMPOSE_TEST, flags=re.M)


def run(argv: list[str], timeout: float) -> subprocess.CompletedProcess[str]:
    """Run in a session of its own; on timeout (or any error) its whole process group is killed."""
    process = subprocess.Popen(
        argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        stdout, stderr = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
    return subprocess.CompletedProcess(argv, process.returncode, stdout, stderr)


def test_first_command_prints_the_j_the_readme_quotes() -> None:
    command, comment = bash_commands(README)[0]
    assert command.startswith("./srl run "), command
    quoted = re.search(r"J\s+(-?[0-9]+\.[0-9]+)", comment)
    assert quoted, f"the README quotes no J next to its first command: {comment!r}"
    done = run(["bash", "-c", command], timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    printed = J_IN_OUTPUT.search(done.stdout)
    assert printed, done.stdout
    decimals = len(quoted.group(1).split(".")[1])
    print(f"README: J {quoted.group(1)}; `{command}` printed J {printed.group(1)}")
    # the README quotes it to `decimals` places: equal when rounded to them
    assert round(float(printed.group(1)), decimals) == float(quoted.group(1)), (printed.group(1), quoted.group(1))


def test_the_compose_commands_ci_runs_are_the_readmes() -> None:
    readme = {command for command, _ in bash_commands(section("Containers"))}
    ci = compose_test_commands()
    assert len(ci) >= 5, ci
    assert {"docker compose up", "COMPOSE_PROFILES=demo-robot docker compose up"} <= set(ci)
    missing = [command for command in ci if command not in readme]
    assert not missing, f".ci/compose-test runs commands the README does not show: {missing}"
    not_run = [
        command
        for command, comment in bash_commands(section("Containers"))
        if command not in ci and NOT_IN_CI not in comment
    ]
    assert not not_run, f"README compose commands that .ci/compose-test does not run: {not_run}"


def test_every_readme_command_is_run_by_a_test_or_ci() -> None:
    ci = set(compose_test_commands())
    commands = bash_commands(README)
    unaccounted = [
        command
        for command, comment in commands
        if command not in COVERAGE and command not in ci and NOT_IN_CI not in comment
    ]
    assert not unaccounted, f"README commands no test or CI step runs (add them to COVERAGE): {unaccounted}"
    stale = set(COVERAGE) - {command for command, _ in commands}
    assert not stale, f"COVERAGE names commands the README no longer shows: {stale}"
    for who in COVERAGE.values():
        if who.startswith("CI:"):
            continue
        path, name = who.split(" ")[0].split("::")
        assert re.search(rf"^def {name}\(", (ROOT / path).read_text(), flags=re.M), who


@pytest.mark.slow
@pytest.mark.parametrize("command", [c for c, _ in bash_commands(README) if c.startswith("./srl up ") and "<" not in c])
def test_srl_up_examples_run(command: str, tmp_path: Path) -> None:
    """Each `./srl up` example of the README, on a free loopback port and for 6 s instead of 20;
    a recording goes to the test's own directory (not the README's /tmp path: nothing left behind,
    and no clash with another user's file there)."""
    argv = command.split()[1:]
    assert "--duration" in argv
    argv[argv.index("--duration") + 1] = "6"
    if "--record" in argv:
        argv[argv.index("--record") + 1] = str(tmp_path / Path(argv[argv.index("--record") + 1]).name)
    argv += ["--router", f"tcp/127.0.0.1:{free_port()}", "--robot", "readme", "--json"]
    done = run([sys.executable, "-m", "tools.cli", *argv], timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    if "--robots" in argv:  # a fleet (README "Fleet"): every robot acted and came closer than its 1.5 m start
        assert summary["fleet"]["robots"] == len(summary["robots"]) and summary["fleet"]["missed_deadlines"] >= 0
        for row in summary["fleet"]["rows"]:
            assert row["steps"] > 0 and row["final_distance_m"] < summary["circle_radius_m"], row
        return
    start, final = summary["start_state"], summary["final_state"]
    assert math.hypot(*final[:2]) < math.hypot(*start[:2]), (start, final)
