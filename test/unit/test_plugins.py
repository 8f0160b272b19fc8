"""Plug-in restricted areas: `load_area` by module path and by entry point, its one-line errors,
and the worked example, zones drawn in a camera image (`examples.camera.CameraZones`)."""

from __future__ import annotations

import contextlib
import runpy
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
import shapely
import torch
import yaml

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.examples.camera import CameraZones, apply_homography
from constrained_diffusion_ros.zones import RestrictedArea, ZoneSet
from constrained_diffusion_ros.zones.plugins import ENTRY_POINT_GROUP, load_area

REPO = Path(__file__).resolve().parents[2]
CAMERA = "constrained_diffusion_ros.examples.camera:CameraZones"
# The shipped camera's image of the workspace corners (config/camera_zones.yaml).
CORNERS = np.array([[0, 0], [512, 0], [512, 512], [0, 512]], dtype=float)
CORNERS_IN_IMAGE = np.array([[184.484, 146.033], [499.540, 162.359], [575.045, 425.581],
                             [23.147, 374.712]])
# A camera tilted so that w = 1 + v / 100: the horizon is the image row v = -100, and image
# points further down map nearer (divided by a larger w). It sees the table point (10, 20) at
# image (0, 0); the workspace centre would lie behind it.
TILTED = [[2.0, 0.0, 10.0], [0.0, 2.0, 20.0], [0.0, 0.01, 1.0]]


def camera_file(tmp_path: Path, zones: list, homography: list = TILTED, **extra: Any) -> Path:
    path = tmp_path / "camera.yaml"
    document = {"image_to_workspace": homography, "zones": zones, "table_point": [10, 20]}
    path.write_text(yaml.safe_dump(document | extra))
    return path


# -- The homography --------------------------------------------------------------------------

def test_the_homography_maps_known_points() -> None:
    shipped = CameraZones("camera_zones.yaml")  # from the package's config directory
    np.testing.assert_allclose(shipped.to_workspace(CORNERS_IN_IMAGE), CORNERS, atol=0.02)
    np.testing.assert_allclose(shipped.to_image(CORNERS), CORNERS_IN_IMAGE, atol=1e-3)
    np.testing.assert_allclose(apply_homography(TILTED, [[0, 0], [5, 5], [0, 100]]),
                               [[10, 20], [20, 30] / np.float64(1.05), [5, 110]])


def test_the_shipped_camera_zone_is_the_center_scenarios_square() -> None:
    camera = CameraZones("camera_zones.yaml")
    square = shapely.Polygon(load_scenarios()["center_0.2"].polygons[0])
    mapped = shapely.Polygon(camera.polygons[0])
    assert mapped.hausdorff_distance(square) < 1.5  # drawn in whole image pixels
    assert mapped.area == pytest.approx(square.area, rel=0.01)


def test_a_zone_drawn_in_the_image_is_kept_out_of_where_it_lies_on_the_table(
        tmp_path: Path) -> None:
    image_zone = [[100, 100], [200, 100], [200, 300], [100, 300]]
    camera = CameraZones(camera_file(tmp_path, [image_zone]))
    # (x, y) = (2u + 10, 2v + 20) / (1 + v / 100): a trapezoid, wide where v is small.
    expected = shapely.Polygon([[105, 110], [205, 110], [102.5, 155], [52.5, 155]])
    assert shapely.Polygon(camera.polygons[0]).normalize().equals_exact(
        expected.normalize(), tolerance=1e-9)
    # Straight edges stay straight: the midpoint of an image edge lands on the mapped edge.
    midpoint = torch.from_numpy(camera.to_workspace([150, 300]))
    assert abs(float(camera.signed_distance(midpoint))) < 1e-9
    inside_in_image = np.array([[150.0, 200.0], [110.0, 290.0], [190.0, 110.0]])
    outside_in_image = np.array([[150.0, 310.0], [90.0, 200.0], [210.0, 200.0]])
    points = torch.from_numpy(camera.to_workspace(np.concatenate([inside_in_image,
                                                                  outside_in_image])))
    assert camera.contains(points).tolist() == [True] * 3 + [False] * 3
    moved = camera.project_out(points, margin=2.0)
    assert not camera.contains(moved).any()
    assert (camera.signed_distance(moved) >= 2.0 - 1e-9).all()  # 1.1 px out: moved to 2 px
    torch.testing.assert_close(moved[4:], points[4:])  # points clear by the margin stay
    exact = ZoneSet.from_polygons([np.asarray(expected.exterior.coords)[:-1]])
    torch.testing.assert_close(camera.signed_distance(points), exact.signed_distance(points))
    assert camera.inflate(15.0).contains(points[3:4]).item()  # 10 image px below: 1.1 px away


def test_zones_on_or_beyond_the_horizon_are_refused(tmp_path: Path) -> None:
    crossing = [[0, -150], [50, -150], [50, 0], [0, 0]]  # the horizon is v = -100
    with pytest.raises(ValueError, match=r"zone 0: vertices \[0, 1\] lie on or beyond"):
        CameraZones(camera_file(tmp_path, [crossing]))
    beyond = [[0, -300], [50, -300], [50, -200]]  # all beyond: would map behind the camera
    with pytest.raises(ValueError, match="horizon"):
        CameraZones(camera_file(tmp_path, [[[0, 0], [9, 0], [9, 9]], beyond]))
    # The same map with H scaled by -1 is the same camera: the table side follows table_point.
    flipped = (-np.asarray(TILTED)).tolist()
    assert CameraZones(camera_file(tmp_path, [[[0, 0], [9, 0], [9, 9]]], flipped)).zones.area > 0
    with pytest.raises(ValueError, match="horizon"):
        CameraZones(camera_file(tmp_path, [beyond], flipped))
    # Taking the workspace centre, which this camera sees behind it, swaps the sides.
    assert CameraZones(camera_file(tmp_path, [beyond], table_point=[256, 256])).zones.area > 0


def test_malformed_camera_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="3x3"):
        CameraZones(camera_file(tmp_path, [[[0, 0], [9, 0], [9, 9]]], [[1, 0], [0, 1]]))
    with pytest.raises(ValueError, match="singular"):
        CameraZones(camera_file(tmp_path, [[[0, 0], [9, 0], [9, 9]]], [[1, 0, 0]] * 3))
    with pytest.raises(ValueError, match=r"zone 0 \(image\): zero area"):
        CameraZones(camera_file(tmp_path, [[[0, 0], [9, 0], [18, 0]]]))
    with pytest.raises(ValueError, match="non-empty"):
        CameraZones(camera_file(tmp_path, []))


# -- load_area ---------------------------------------------------------------------------------

def test_load_area_by_module_path_builds_the_class_with_the_parameters() -> None:
    area = load_area(CAMERA, {"config_file": "camera_zones.yaml"})
    assert isinstance(area, CameraZones) and isinstance(area, RestrictedArea)
    assert area.contains(torch.tensor([256.0, 256.0])).item()


@pytest.mark.parametrize(("spec", "parameters", "message"), [
    ("no_such_package.zones:Area", {}, "cannot import 'no_such_package.zones'"),
    ("constrained_diffusion_ros.examples.camera:NoSuchArea", {}, "has no attribute 'NoSuchArea'"),
    ("constrained_diffusion_ros.examples.camera:", {}, "expected 'package.module:Class'"),
    ("constrained_diffusion_ros.zones.geometry:rectangle",
     {"x_min": 0, "y_min": 0, "x_max": 1, "y_max": 1}, "built a ndarray, not a RestrictedArea"),
    ("constrained_diffusion_ros.examples.camera:WORKSPACE_CENTRE", {}, "tuple is not callable"),
    (CAMERA, {"config_file": "camera_zones.yaml", "fov": 60}, "bad parameters"),
    (CAMERA, {}, "bad parameters"),
    (CAMERA, {"config_file": "/nonexistent/camera.yaml"}, "cannot be built .ValueError"),
    ("no_such_entry_point", {}, f"no entry point of that name in {ENTRY_POINT_GROUP}"),
])
def test_every_failure_is_one_value_error_line_naming_the_spec(
        spec: str, parameters: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message) as raised:
        load_area(spec, parameters)
    text = str(raised.value)
    assert f"{spec!r}" in text and "\n" not in text


def setup_entry_points() -> dict[str, list[str]]:
    """setup()'s entry_points, read by running setup.py with setuptools.setup stubbed."""
    captured: dict[str, Any] = {}
    with mock.patch("setuptools.setup", lambda **kwargs: captured.update(kwargs)), \
            contextlib.chdir(REPO):
        runpy.run_path(str(REPO / "setup.py"))
    return captured["entry_points"]


def test_load_area_by_entry_point_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The entry point setup.py declares, installed as a distribution's metadata on sys.path
    (as pip or colcon would install it), found by its name."""
    declared = setup_entry_points()[ENTRY_POINT_GROUP]
    assert "camera_zones = constrained_diffusion_ros.examples.camera:CameraZones" in declared
    info = tmp_path / "camera_zones_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: camera-zones-plugin\n"
                                   "Version: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n" + "\n".join(declared)
                                           + "\nbroken = no_such_package.zones:Area\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    area = load_area("camera_zones", {"config_file": "camera_zones.yaml"})
    assert isinstance(area, CameraZones)
    with pytest.raises(ValueError, match=r"'broken': entry point .* does not load"):
        load_area("broken", {})
    with pytest.raises(ValueError, match=r"known: .*camera_zones"):
        load_area("camera", {})
