"""Scenarios whose zones come from a keep-out grid or a plug-in area: how they load, what they
refuse, and that the shipped policy keeps out of them in closed loop as it does of drawn ones."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch

from constrained_diffusion_ros.evaluation.evaluated_configurations import load_evaluated
from constrained_diffusion_ros.evaluation.rollout import RolloutLog
from constrained_diffusion_ros.evaluation.runner import cell_metrics, evaluate_configurations
from constrained_diffusion_ros.evaluation.scenarios import Scenario, load_scenarios
from constrained_diffusion_ros.examples.camera import CameraZones
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.zones import ZoneSet
from constrained_diffusion_ros.zones.plugins import PLUGIN_MODULES_ENV


@pytest.fixture(scope="module")
def scenarios() -> dict[str, Scenario]:
    return load_scenarios()


def write_scenarios(directory: Path, text: str) -> Path:
    path = directory / "scenarios.yaml"
    path.write_text(textwrap.dedent(text))
    return path


# -- Loading -------------------------------------------------------------------------------------

def test_the_grid_scenario_is_the_center_square_on_4px_cells(
        scenarios: dict[str, Scenario]) -> None:
    grid, drawn = scenarios["center_0.2_grid"], scenarios["center_0.2"]
    zones = grid.zones_at(0)
    assert isinstance(zones, ZoneSet) and not grid.moving and not grid.paper
    assert zones.geometry.equals(shapely.box(204, 204, 308, 308))  # cells with centres inside
    assert zones.geometry.hausdorff_distance(drawn.zones_at(0).geometry) <= 4.0  # one cell
    assert grid.zones_at(150) is zones


def test_the_camera_scenario_queries_the_plugin_and_publishes_its_polygons(
        scenarios: dict[str, Scenario]) -> None:
    camera = scenarios["camera_center"]
    area = camera.zones_at(0)
    assert isinstance(area.plugin, CameraZones) and camera.zones_at(150) is area
    assert not camera.moving
    assert len(camera.polygons) == 1
    np.testing.assert_allclose(camera.polygons_at(0)[0], area.polygons[0])
    square = scenarios["center_0.2"].zones_at(0).geometry
    assert shapely.Polygon(camera.polygons[0]).hausdorff_distance(square) < 1.5


def test_a_grid_from_a_pgm_file_relative_to_the_scenarios_file(tmp_path: Path) -> None:
    pixels = np.full((8, 8), 255, dtype=np.uint8)  # white: free
    pixels[2:4, 5:8] = 0  # black: keep-out, rows 2-3 (y), columns 5-7 (x)
    pixels[6, 0] = 100  # 61% dark: kept out only below the default threshold of 65
    (tmp_path / "masks").mkdir()
    (tmp_path / "masks" / "mask.pgm").write_bytes(b"P5 8 8 255\n" + pixels.tobytes())
    path = write_scenarios(tmp_path, """
        from_file:
          zones:
            - grid: {file: masks/mask.pgm, resolution: 64, origin: [10, 0]}
        lower_threshold:
          zones:
            - grid: {file: masks/mask.pgm, resolution: 64, threshold: 50}
        """)
    loaded = load_scenarios(path)
    # Columns 5-7 from x = 10 reach x = 522: clipped to the workspace at 512.
    assert loaded["from_file"].zones_at(0).geometry.equals(shapely.box(330, 128, 512, 256))
    assert loaded["lower_threshold"].zones_at(0).area == pytest.approx(2 * 3 * 64**2 + 64**2)


@pytest.mark.parametrize(("entry", "message"), [
    ("zones: [{grid: {from_scenario: later, resolution: 4}}]", "no scenario with polygons"),
    ("zones: [{grid: {from_scenario: base, file: m.pgm, resolution: 4}}]", "exactly one of"),
    ("zones: [{grid: {from_scenario: base}}]", "grid lacks 'resolution'"),
    ("zones: [{grid: {from_scenario: base, resolution: 4, colour: red}}]", "unknown grid keys"),
    ("zones: [{grid: {from_scenario: base, resolution: 4, origin: [600, 0]}}]",
     "no keep-out cell inside the workspace"),
    ("zones: [{grid: {file: missing.pgm, resolution: 4}}]", "missing.pgm"),
    ('plugin: {class: "no_such_package.areas:Area"}', "'no_such_package.areas' is not one "
                                                      "plug-ins may come from"),
    ('plugin: {class: "constrained_diffusion_ros.examples.camera:CameraZones"}', "bad parameters"),
    ("plugin: {module: constrained_diffusion_ros.examples.camera}", "plugin is {class"),
    ('{plugin: {class: "x:Y"}, zones: [{square: {center: [1, 1], side: 1}}]}', "both zones"),
])
def test_malformed_grid_and_plugin_scenarios_are_refused_naming_the_scenario(
        tmp_path: Path, entry: str, message: str) -> None:
    path = write_scenarios(tmp_path, f"""
        base:
          zones: [{{square: {{center: [256, 256], side: 100}}}}]
        broken: {entry if entry.startswith("{") else "{" + entry + "}"}
        later:
          zones: [{{square: {{center: [256, 256], side: 100}}}}]
        """)
    with pytest.raises(ValueError, match=message) as raised:
        load_scenarios(path)
    assert "scenario 'broken'" in str(raised.value)


def test_a_plugin_without_polygons_is_measured_through_its_own_queries(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An area that only knows its signed distance (no polygons to draw or publish) is still a
    scenario the evaluation scores: the metrics ask the area itself."""
    (tmp_path / "user_areas.py").write_text(textwrap.dedent("""
        import torch
        from constrained_diffusion_ros.zones import RestrictedArea

        class Disc(RestrictedArea):
            def __init__(self, centre, radius):
                self.centre, self.radius = torch.tensor(centre, dtype=torch.float64), radius

            def signed_distance(self, points):
                points = torch.as_tensor(points)
                return ((points - self.centre.to(points)).norm(dim=-1)
                        - self.radius).to(points.dtype)
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(PLUGIN_MODULES_ENV, "user_areas")  # a user's module, allowed by the user
    path = write_scenarios(tmp_path, """
        disc:
          plugin: {class: "user_areas:Disc", parameters: {centre: [100, 100], radius: 30}}
        """)
    disc = load_scenarios(path)["disc"]
    assert disc.polygons == () and disc.polygons_at(10) == []
    commanded = np.array([[100.0, 100.0], [100.0, 125.0], [300.0, 300.0], [100.0, 135.0]])
    pusher = np.array([[300.0, 300.0], [300.0, 300.0], [100.0, 140.0], [300.0, 300.0],
                       [300.0, 300.0]])
    states = np.zeros((1, 5, 5))
    states[0, :, :2] = pusher
    log = RolloutLog([100000], commanded[None], states, np.zeros((1, 4)))
    metrics = cell_metrics(log, np.array([0]), disc)
    assert metrics["r"] == 2  # (100, 100) and (100, 125) lie inside the disc
    assert metrics["r_body"] == 1  # the pusher at (100, 140), 10 px out, overlaps it
    assert bool(disc.zones_at(0).contains(torch.tensor([100.0, 120.0])))


# -- Closed loop with the shipped policy ---------------------------------------------------------

def test_the_shipped_policy_keeps_out_of_grid_and_camera_zones_as_of_drawn_ones(
        scenarios: dict[str, Scenario]) -> None:
    """The strongest DDIM configuration on the drawn square and on the same square given as a
    4 px keep-out grid and as a zone drawn in a camera image: nothing commanded inside, the
    pusher's disc never overlaps (no scene starts inside). The unconstrained policy, in the same
    batch, does command setpoints inside each of them, so the zones are in its way."""
    torch.set_num_threads(1)
    policy = load_policy(default_model_dir())
    evaluated = load_evaluated(config_dir())
    configs = [evaluated[name].config for name in ("ddim10_none", "ddim10_r_g10_p_safe")]
    chosen = [scenarios[name] for name in ("center_0.2", "center_0.2_grid", "camera_center")]
    cells, _, _ = evaluate_configurations(policy, configs, [chosen, chosen],
                                          seeds=range(100000, 100004), n_steps=60,
                                          progress=False)
    by_cell = {(c.configuration, c.scenario): c for c in cells}
    for scenario in chosen:
        blind, safe = (by_cell[(c.name, scenario.name)] for c in configs)
        assert blind.r > 0, blind
        assert safe.episodes == 4 and safe.starts_inside == 0, safe
        assert safe.r == 0 and safe.r_body == 0 and safe.path_crossings == 0, safe
