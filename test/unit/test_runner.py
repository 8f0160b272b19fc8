"""The evaluation: scenarios as the design specifies them, the metrics, and the CLI end to end."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch

from constrained_diffusion_ros.evaluation import evaluate
from constrained_diffusion_ros.evaluation.rollout import RolloutLog
from constrained_diffusion_ros.evaluation.runner import cell_metrics, evaluate_configurations
from constrained_diffusion_ros.evaluation.scenarios import Scenario, load_scenarios
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.liveness import StandstillMeter, standstills
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import save_policy
from sim_bridge import WORKSPACE_SIZE

W = WORKSPACE_SIZE


@pytest.fixture(scope="module")
def scenarios() -> dict[str, Scenario]:
    return load_scenarios()


# -- Scenarios -----------------------------------------------------------------------------------

@pytest.mark.parametrize(("name", "expected"), [
    ("left_0.1", shapely.box(0, 0, 0.1 * W, W)),
    ("left_0.5", shapely.box(0, 0, 0.5 * W, W)),
    ("center_0.1", shapely.box(W / 2 - 0.05 * W, W / 2 - 0.05 * W,
                               W / 2 + 0.05 * W, W / 2 + 0.05 * W)),
    ("center_0.2", shapely.box(W / 2 - 0.1 * W, W / 2 - 0.1 * W,
                               W / 2 + 0.1 * W, W / 2 + 0.1 * W)),
])
def test_paper_scenarios_have_the_papers_geometry(scenarios: dict[str, Scenario], name: str,
                                                  expected: shapely.Polygon) -> None:
    scenario = scenarios[name]
    assert scenario.paper and not scenario.moving
    zones = scenario.zones_at(0)
    assert zones.geometry.equals(expected), (zones.polygons, expected)
    assert zones.area == pytest.approx(expected.area)
    assert scenario.zones_at(150) is zones  # static: one shared zone set


def test_exactly_the_four_paper_scenarios_are_marked(scenarios: dict[str, Scenario]) -> None:
    assert {n for n, s in scenarios.items() if s.paper} == {
        "left_0.1", "left_0.5", "center_0.1", "center_0.2"}


def test_the_moving_scenario_moves_between_steps(scenarios: dict[str, Scenario]) -> None:
    hand = scenarios["moving_hand"]
    assert hand.moving
    first, later = hand.zones_at(0), hand.zones_at(100)
    assert not first.geometry.equals(later.geometry)
    assert first.area == pytest.approx(later.area)  # translated, not reshaped
    shift = np.asarray(later.geometry.centroid.coords[0]) - first.geometry.centroid.coords[0]
    np.testing.assert_allclose(shift, (432 * 100 / 200, 0))  # {offset: [432, 0], steps: 200}
    assert hand.zones_at(200).geometry.equals(hand.zones_at(250).geometry)  # then it stays


# -- Metrics on a hand-made log ------------------------------------------------------------------

def hand_made_log(commanded: np.ndarray, pusher: np.ndarray) -> RolloutLog:
    """One episode: commanded (T, 2), pusher (T + 1, 2) before each step and after the last."""
    steps = len(commanded)
    states = np.zeros((1, steps + 1, 5))
    states[0, :, :2] = pusher
    coverage = np.linspace(0.0, 0.5, steps)[None]
    return RolloutLog([100000], commanded[None].astype(float), states, coverage)


def test_cell_metrics_count_steps_commanded_inside(scenarios: dict[str, Scenario]) -> None:
    scenario = scenarios["center_0.2"]  # the square [204.8, 307.2]^2
    commanded = np.full((10, 2), 100.0)
    commanded[[2, 3, 7]] = [[256.0, 256.0], [210.0, 300.0], [300.0, 210.0]]
    pusher = np.full((11, 2), 60.0)
    pusher[[4, 5]] = [[256.0, 256.0], [195.0, 256.0]]  # after step 3, and 10 px off the edge
    metrics = cell_metrics(hand_made_log(commanded, pusher), np.array([0]), scenario)
    assert metrics["r"] == 3
    assert metrics["r_body"] == 2  # the disc of radius 15 overlaps the zone after steps 3, 4
    assert metrics["starts_inside"] == 0
    assert metrics["s"] == pytest.approx(min(1.0, 0.5 / 0.95))


def test_cell_metrics_follow_a_moving_zone(scenarios: dict[str, Scenario]) -> None:
    hand = scenarios["moving_hand"]  # square of side 70 at (40, 200), moving +432 px in x
    steps = 30
    commanded = np.tile([40.0, 200.0], (steps, 1))  # where the hand starts
    pusher = np.full((steps + 1, 2), 450.0)
    metrics = cell_metrics(hand_made_log(commanded, pusher), np.array([0]), hand)
    # The left edge 5 + 2.16 t passes x = 40 after step 16: inside at steps 0..16.
    per_step = [bool(hand.zones_at(t).contains(torch.tensor([40.0, 200.0]))) for t in range(steps)]
    assert sum(per_step) == 17
    assert metrics["r"] == 17
    assert metrics["r_body"] == 0


def test_configurations_share_one_batch_and_zone_blind_ones_run_their_seeds_once(
        tiny_policy: DiffusionPolicy, scenarios: dict[str, Scenario]) -> None:
    blind = ConstraintConfig("blind", sampler="ddim", denoising_steps=2)
    projected = ConstraintConfig("projected", sampler="ddim", denoising_steps=2, project=True)
    chosen = [scenarios["left_0.5"], scenarios["center_0.2"]]
    cells, log, first_rows = evaluate_configurations(
        tiny_policy, [blind, projected], [chosen, chosen], seeds=[100000, 100001], n_steps=4,
        progress=False)
    assert log.seeds == [100000, 100001] * 3  # blind once, projected once per scenario
    assert first_rows == {("left_0.5", "blind"): 0, ("center_0.2", "blind"): 0,
                          ("left_0.5", "projected"): 2, ("center_0.2", "projected"): 4}
    assert [(c.scenario, c.configuration, c.batch) for c in cells] == [
        ("left_0.5", "blind", 6), ("center_0.2", "blind", 6),
        ("left_0.5", "projected", 6), ("center_0.2", "projected", 6)]
    assert all(c.r == 0 for c in cells if c.configuration == "projected")


# -- The command ---------------------------------------------------------------------------------

def test_a_short_evaluation_runs_end_to_end(tmp_path: Path, tiny_policy: DiffusionPolicy,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    model, output = save_policy(tiny_policy, tmp_path / "model"), tmp_path / "report"
    code = evaluate.main([
        "--model", str(model), "--scenarios", "left_0.5", "l_shape",
        "--configs", "none", "projection", "--episodes", "2", "--steps", "16",
        "--output", str(output), "--figure", "left_0.5", "projection"])
    assert code == 0
    for name in ("table.md", "results.csv", "results.json", "s_vs_r.png", "frames.png"):
        assert (output / name).is_file() and (output / name).stat().st_size > 0, name
    cells = json.loads((output / "results.json").read_text())
    assert sorted((c["scenario"], c["configuration"]) for c in cells) == [
        ("l_shape", "none"), ("l_shape", "projection"),
        ("left_0.5", "none"), ("left_0.5", "projection")]
    assert all(c["episodes"] == 2 for c in cells)
    assert all(c["r"] == 0 for c in cells if c["configuration"] == "projection")
    # ... where the unconstrained policy does command setpoints inside (half the workspace).
    assert sum(c["r"] for c in cells if c["configuration"] == "none") > 0
    assert all(0.0 <= c["s"] <= 1.0 for c in cells)
    # Each cell carries its 95% intervals: around its means, zero-wide where r = 0 throughout.
    assert all(c["s_ci"][0] <= c["s"] <= c["s_ci"][1] and c["r_ci"][0] <= c["r"] <= c["r_ci"][1]
               and c["success_ci"][0] <= c["success_rate"] <= c["success_ci"][1] for c in cells)
    assert all(c["r_ci"] == [0.0, 0.0] for c in cells if c["configuration"] == "projection")
    with (output / "results.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 and all(float(r["s_ci_low"]) <= float(r["s"]) for r in rows)
    table = (output / "table.md").read_text()
    assert "0.5 left" in table and "concave L" in table and "Projection" in table
    assert "0.5 left" in capsys.readouterr().out


def test_a_configuration_kept_to_the_papers_scenarios_says_which_it_skips(
        tmp_path: Path, tiny_policy: DiffusionPolicy, capsys: pytest.CaptureFixture[str]) -> None:
    """Asked for on a scenario of ours, a configuration that evaluation.yaml keeps to the
    paper's scenarios runs on the paper's only, and says so in one line."""
    model, output = save_policy(tiny_policy, tmp_path / "model"), tmp_path / "report"
    code = evaluate.main([
        "--model", str(model), "--scenarios", "left_0.5", "l_shape",
        "--configs", "ddim10_r_g10_p_safe_best8", "--episodes", "1", "--steps", "8",
        "--output", str(output)])
    assert code == 0
    cells = json.loads((output / "results.json").read_text())
    assert [c["scenario"] for c in cells] == ["left_0.5"]
    err = capsys.readouterr().err
    assert "ddim10_r_g10_p_safe_best8 runs on the paper's scenarios only" in err
    assert "not on l_shape" in err


def test_an_unknown_scenario_is_a_clear_error(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    code = evaluate.main(["--scenarios", "center_0.2", "nowhere", "--configs", "none",
                          "--model", str(tmp_path / "no_model"), "--output", str(tmp_path / "o")])
    assert code == 2
    err = capsys.readouterr().err
    assert "unknown scenarios ['nowhere']" in err and "center_0.2" in err  # names the known ones
    assert "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_liveness_counts_the_guards_changes_and_standstills_at_a_zone_edge(
        scenarios: dict[str, Scenario]) -> None:
    """A pusher parked 3 px from the square's edge for 8 steps is a standstill; the same wait
    in open space, or a run of 4 steps, is not. Steps whose setpoint the guard changed count
    as interventions, with their mean change."""
    scenario = scenarios["center_0.2"]  # the square [204.8, 307.2]^2
    steps = 30
    pusher = np.stack([np.linspace(20.0, 80.0, steps + 1)] * 2, axis=1)  # moving, far away
    pusher[1:9] = [204.8 - 15 - 3, 256.0]  # parked at the edge after steps 0..7: 8 steps
    pusher[12:16] = [204.8 - 15 - 3, 300.0]  # parked after steps 11..14: only 4 steps
    pusher[20:28] = [60.0, 60.0]  # parked in open space
    commanded = pusher[1:].copy()
    log = hand_made_log(commanded, pusher)
    log.wanted = commanded.copy()[None]
    log.wanted[0, [3, 4]] += [[3.0, 4.0], [0.0, 1.0]]
    metrics = cell_metrics(log, np.array([0]), scenario)
    assert metrics["standstill_steps"] == 7  # moved 0 px in steps 1..7 (step 0 moved there)
    assert metrics["interventions"] == 2 and metrics["intervention_px"] == pytest.approx(3.0)


def test_the_nodes_standstill_meter_counts_as_the_evaluation_does() -> None:
    """One definition, two places: step by step, the meter marks the runs `standstills` marks."""
    rng = np.random.default_rng(0)
    moved = np.where(rng.random(200) < 0.7, 0.1, 3.0)
    clearance = np.where(rng.random(200) < 0.8, 17.0, 40.0)
    meter = StandstillMeter()
    for m, c in zip(moved, clearance):
        meter.update(float(m), float(c), 15.0)
    marked = standstills(moved[None], (clearance < 20.0)[None])[0]
    assert meter.steps == marked.sum() > 0
