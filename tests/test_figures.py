"""The guide's figures (tools/docs/figures.py, docs/img/*.png): the command draws each one, into a
temporary directory here, never docs/img/; the data behind each is what the code and the benchmark
JSON say, and a JSON the figures cannot draw is refused by name.
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import matplotlib.image
import numpy as np
import pytest

from common.contracts import keys
from tests.harness import ROOT
from tools.docs import figures

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
NAMES = [spec.name for spec in figures.FIGURES]


def fleet_data() -> dict[str, Any]:
    return json.loads((ROOT / figures.BENCHMARK_DATA / "fleet.json").read_text())


def actor_data() -> dict[str, Any]:
    return json.loads((ROOT / figures.BENCHMARK_DATA / "actor.json").read_text())


def check_png(path: Path) -> None:
    """A PNG by its magic bytes, that matplotlib reads back, of a size a guide page can show."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    assert 10_000 < len(data) < 600_000, (path, len(data))
    assert b"matplotlib" not in data.lower(), f"{path}: a software version in the metadata"
    image = matplotlib.image.imread(path)
    height, width = image.shape[:2]
    assert 900 <= width <= 2000 and 500 <= height <= 1600, (path, image.shape)
    assert image[..., :3].std() > 0.05, f"{path}: a blank image"


@pytest.mark.slow
def test_the_command_draws_every_figure_into_the_directory_it_is_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "img"
    assert figures.main(["--out", str(out), "--duration", "3"]) == 0
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted(f"{name}.png" for name in NAMES)
    for path in out.iterdir():
        check_png(path)
    assert capsys.readouterr().out.count("figures: wrote ") == len(NAMES)
    # the same data, the same bytes: a rerun changes no checked-in image for nothing
    again = tmp_path / "again"
    assert figures.main(["--out", str(again), "architecture", "fleet-scaling"]) == 0
    for name in ("architecture.png", "fleet-scaling.png"):
        assert (again / name).read_bytes() == (out / name).read_bytes()


@pytest.mark.integration
def test_python_m_tools_docs_figures_is_the_command(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "tools.docs.figures", "--out", str(tmp_path), "architecture"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["architecture.png"]
    check_png(tmp_path / "architecture.png")
    refused = subprocess.run(
        [sys.executable, "-m", "tools.docs.figures", "--out", str(tmp_path / "x"), "no-such-figure"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert refused.returncode == 2
    assert "no figure no-such-figure" in refused.stderr
    assert not (tmp_path / "x").exists()


def test_the_default_directory_is_docs_img_and_every_checked_in_figure_is_one_the_command_draws() -> None:
    assert figures.build_parser().parse_args([]).out == ROOT / "docs" / "img"
    checked_in = {p.stem for p in (ROOT / figures.IMAGES).glob("*.png")}
    assert checked_in <= set(NAMES), f"docs/img/ holds figures nothing draws: {checked_in - set(NAMES)}"


# -- the parking path ------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_path_is_the_readme_run_and_the_parked_circle_is_the_codes() -> None:
    from common.math.parking import FINAL_DISTANCE_M

    run = figures.EpisodeRun()
    assert run.command() == "srl run --agent rlqv --horizon 12 --start 2,2 --duration 30"
    assert run.command() in (ROOT / "README.md").read_text()
    data = figures.run_path(figures.EpisodeRun(duration=3.0))
    assert data.steps == 30 and data.states.shape == (31, 3)
    assert data.states[0, :2].tolist() == [2.0, 2.0]
    assert data.target_radius == FINAL_DISTANCE_M
    assert data.arrival_radius is not None and data.arrival_radius < data.target_radius
    assert not data.at_target, "3 s from (2, 2) at 0.22 m/s cannot be at the target: the verdict is computed"
    assert data.final_distance > 2.0


# -- the fleet's scaling ---------------------------------------------------------------------------


def test_the_fleet_points_are_the_jsons_rows() -> None:
    data = fleet_data()
    points = figures.fleet_points(data)
    assert len(points) == len(data["rows"])
    layouts = {p.layout for p in points}
    assert layouts <= set(figures.LAYOUTS), "a layout the figure has no name for"
    for row in data["rows"]:
        (point,) = [p for p in points if (p.layout, p.robots) == (row["layout"], row["robots"])]
        assert point.cpu_ms_per_robot_tick == row["cpu_ms_per_robot_tick"]
        assert point.missed_deadlines == row["fleet"]["missed_deadlines"]
    footnote = figures.run_footnote(data)
    assert data["run"]["commit"][:10] in footnote and data["run"]["cpu_model"] in footnote
    assert "load average" in footnote


@pytest.mark.parametrize("rows", [None, [], "rows"])
def test_a_fleet_json_without_rows_is_refused_by_name(rows: Any) -> None:
    data = fleet_data()
    data["rows"] = rows
    with pytest.raises(figures.FigureDataError, match=r"fleet\.json: no rows"):
        figures.fleet_figure(data)


def test_a_fleet_row_without_a_number_is_refused_naming_the_row_and_the_field() -> None:
    data = copy.deepcopy(fleet_data())
    del data["rows"][1]["cpu_ms_per_robot_tick"]
    with pytest.raises(figures.FigureDataError, match=r"row 1 .*cpu_ms_per_robot_tick"):
        figures.fleet_points(data)
    assert figures.fleet_points(fleet_data())  # the control: the file itself draws


def test_a_json_with_no_run_record_says_so_in_the_footnote() -> None:
    data = fleet_data()
    data.pop("run")
    assert "no record of its run" in figures.run_footnote(data)


def test_a_missing_benchmark_file_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(figures.FigureDataError, match=r"fleet\.json: no such file"):
        figures.read_data(tmp_path / "fleet.json")


# -- the actor's solve time ------------------------------------------------------------------------


def test_the_solve_bars_are_the_n12_rows_and_one_baseline_per_agent_and_weights() -> None:
    data = actor_data()
    bars = figures.solve_bars(data, 12)
    rows = [r for r in data["rows"] if r["horizon"] == 12]
    assert len([b for b in bars if b.solver != "SLSQP baseline"]) == len(rows)
    labels = {b.label for b in bars}
    assert len([b for b in bars if b.solver == "SLSQP baseline"]) == len(labels)
    for row in rows:
        label = row["agent"] + ("" if row["weights"] == "n/a" else f" {row['weights']}")
        (bar,) = [b for b in bars if b.label == label and b.solver == row["solver"]]
        assert (bar.median_ms, bar.p99_ms) == (row["median_ms"], row["p99_ms"])
        assert bar.median_ms <= bar.p99_ms
    assert {"mpc", "rlqv trained@150"} <= labels


def test_an_actor_json_without_the_horizon_or_rows_is_refused() -> None:
    with pytest.raises(figures.FigureDataError, match="no row at N = 7"):
        figures.solve_bars(actor_data(), 7)
    with pytest.raises(figures.FigureDataError, match=r"actor\.json: no rows"):
        figures.solve_bars({"rows": []})


# -- the architecture ------------------------------------------------------------------------------


def every_key_name() -> set[str]:
    """The names of common.contracts.keys that are a Topic, a Service or a pattern of one robot."""
    names = set()
    for name, value in vars(keys).items():
        if isinstance(value, keys.Topic | keys.Service):
            names.add(name)
    return names


def test_every_key_the_figure_draws_is_one_of_common_contracts_keys_and_reads_as_its_pattern() -> None:
    for link in figures.LINKS:
        for name in link.keys:
            value = getattr(keys, name)
            pattern = getattr(value, "pattern", value)
            shown = figures.key_pattern(name)
            assert shown == pattern.replace("{", "<").replace("}", ">")
            assert figures.key_pattern(name) in figures.link_label(link) or link.every_robot
    assert figures.key_pattern("WEIGHTS") == "srl/<robot>/critic/weights"
    assert figures.key_pattern("STATE", every_robot=True) == keys.every_robot(keys.STATE)


def test_the_figure_draws_every_topic_and_service_of_the_wire() -> None:
    """A new key in common/contracts/keys.py is a new arrow, or this fails (the liveliness
    tokens too); the batches are the same topics, named in the figure's footnote."""
    assert every_key_name() <= figures.drawn_keys(), every_key_name() - figures.drawn_keys()
    assert "ALIVE" in figures.drawn_keys()


def test_a_key_left_out_of_the_figure_is_seen(monkeypatch: pytest.MonkeyPatch) -> None:
    """The negative control of the test above: without the arrow of the actions, ACTION is missed."""
    monkeypatch.setattr(figures, "LINKS", tuple(link for link in figures.LINKS if "ACTION" not in link.keys))
    assert every_key_name() - figures.drawn_keys() == {"ACTION"}


def test_a_name_that_is_not_a_key_is_refused() -> None:
    for name in ("NO_SUCH_KEY", "BATCH_CHUNK", "SERVICES"):
        with pytest.raises(figures.FigureDataError, match=f"keys.{name} is not a key pattern"):
            figures.key_pattern(name)


def test_every_link_joins_processes_of_the_table_and_every_process_is_on_a_floor_of_the_code() -> None:
    names = {p.name for p in figures.PROCESSES}
    for link in figures.LINKS:
        for end in (link.source, link.target):
            assert end in names or (end in figures.GROUPS and set(figures.GROUPS[end]) <= names), end
        assert link.kind in figures.LINK_STYLE
        assert link.keys or link.text, "an arrow without a label"
    for process in figures.PROCESSES:
        if process.floor == "services":
            assert (ROOT / "services" / process.name).is_dir(), process.name
        assert process.floor in figures.FLOOR_COLOR
    for name, bottom, top, _ in figures.FLOORS:
        assert (ROOT / name).is_dir() and bottom < top


def test_the_common_floors_drawn_are_the_architecture_tests() -> None:
    from tests.test_architecture import COMMON_FLOORS

    assert tuple(name for name, _ in figures.COMMON_FLOORS) == COMMON_FLOORS


# -- the live view: the layout srl view ships, drawn from the messages it serves -----------------
def test_the_live_views_panels_tile_the_layout_in_its_order() -> None:
    from tools.docs.live_view import ROBOT, panels
    from tools.recording.view import foxglove_layout

    found = panels(json.loads(foxglove_layout([ROBOT]))["content"])
    assert [p.kind for p in found] == ["ThreeDee", "Plot", "Plot", "Plot", "Plot"]
    assert sum(p.box[2] * p.box[3] for p in found) == pytest.approx(1.0)
    scene, *plots = found
    assert scene.box[0] == 0.0 and all(p.box[0] == pytest.approx(scene.box[2]) for p in plots)
    assert [p.box[1] for p in plots] == sorted((p.box[1] for p in plots), reverse=True), "plots top to bottom"


def test_the_live_view_reads_the_layouts_series_from_the_recorders_messages() -> None:
    from tools.docs.live_view import LiveViewError, view_data

    data = view_data(duration=2.0)
    times, costs = data.series("/tb3_0/srl/transition.stage_cost")
    assert len(costs) == 20 and times[0] == 0.0 and np.all(costs > 0)
    _, first = data.series("/tb3_0/srl/critic_weights.q_weights[0]")
    assert np.all(np.isfinite(first))
    assert data.last("/tb3_0/path").poses, "the path the 3D panel draws"
    # negative controls: a series the recorder's messages do not have is refused by name
    with pytest.raises(LiveViewError, match="no field 'no_such_field'"):
        data.series("/tb3_0/srl/transition.no_such_field")
    with pytest.raises(LiveViewError, match="serves no /tb3_0/nothing"):
        data.series("/tb3_0/nothing.x")
