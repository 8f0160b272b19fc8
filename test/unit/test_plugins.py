"""Plug-in restricted areas: `load_area` by module path and by entry point, its one-line errors,
and the worked example, zones drawn in a camera image (`examples.camera.CameraZones`)."""

from __future__ import annotations

import contextlib
import importlib
import inspect
import os
import pickle
import runpy
import subprocess
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar
from unittest import mock

import numpy as np
import pytest
import shapely
import torch
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.examples.camera import CameraZones, apply_homography
from constrained_diffusion_ros.zones import RestrictedArea, ZoneSet
from constrained_diffusion_ros.zones.plugins import (
    ENTRY_POINT_GROUP,
    PLUGIN_MODULES_ENV,
    CheckedArea,
    ZoneCheckError,
    load_area,
    probe_points,
)

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


@pytest.fixture(autouse=True, scope="module")
def allowed_here() -> Iterator[None]:
    """The modules these tests name, allowed as a user would allow them: the checks after the
    allow-list are tested on them (`test_a_module_is_imported_only_if_allowed` tests the list)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(PLUGIN_MODULES_ENV, ",".join(
            ["no_such_package", HERE, *(module.__name__ for module in STDLIB)]))
        yield


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
    assert isinstance(area, CheckedArea) and isinstance(area.plugin, CameraZones)
    assert area.polygons is area.plugin.polygons  # what the class offers besides, read through
    assert area.contains(torch.tensor([256.0, 256.0])).item()


@pytest.mark.parametrize(("spec", "parameters", "message"), [
    ("no_such_package.zones:Area", {}, "cannot import 'no_such_package.zones'"),
    ("constrained_diffusion_ros.examples.camera:NoSuchArea", {}, "has no attribute 'NoSuchArea'"),
    ("constrained_diffusion_ros.examples.camera:", {}, "expected 'package.module:Class'"),
    ("constrained_diffusion_ros.zones.geometry:rectangle",
     {"x_min": 0, "y_min": 0, "x_max": 1, "y_max": 1}, "names a function, not a RestrictedArea"),
    ("constrained_diffusion_ros.examples.camera:WORKSPACE_CENTRE", {},
     "names a tuple, not a RestrictedArea subclass"),
    ("constrained_diffusion_ros.zones:RestrictedArea", {}, r"abstract \(implement signed_dist"),
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
    assert isinstance(area.plugin, CameraZones)
    with pytest.raises(ValueError, match=r"'broken': entry point .* does not load"):
        load_area("broken", {})
    with pytest.raises(ValueError, match=r"known: .*camera_zones"):
        load_area("camera", {})


# -- A scenario file names a class, never a call (issue 26) -----------------------------------

CALLED: list[str] = []  # what of this module a spec ran


class NotAnArea:
    """A class that is not a RestrictedArea: building it would run its __init__."""

    def __init__(self, **parameters: Any) -> None:
        CALLED.append("NotAnArea")


def make_area(**parameters: Any) -> RestrictedArea:
    """A factory function that returns a good area: refused all the same, being a call."""
    CALLED.append("make_area")
    return ZoneSet.from_polygons([[[0, 0], [9, 0], [9, 9]]])


class Answers(RestrictedArea):
    """An area whose signed distance is `answer(points)`: the probe's bad answers."""

    answer: Any = staticmethod(lambda p: p[..., 0] - 256.0)

    def signed_distance(self, points: Tensor) -> Tensor:
        return self.answer(points)


class NaNArea(Answers):
    answer = staticmethod(lambda p: torch.where(p[..., 0] > 300, torch.nan, p[..., 0]))


class NegInfArea(Answers):
    answer = staticmethod(lambda p: torch.full(p.shape[:-1], -torch.inf, dtype=p.dtype))


class InfArea(Answers):
    """Nothing anywhere, as an empty ZoneSet answers: +inf is a distance, and accepted."""

    answer = staticmethod(lambda p: torch.full(p.shape[:-1], torch.inf, dtype=p.dtype))


class PointShapeArea(Answers):
    answer = staticmethod(lambda p: p - 256.0)  # (..., 2), not (...)


class FlatArea(Answers):
    answer = staticmethod(lambda p: p.reshape(-1, 2)[:, 0] - 256.0)  # only (N, 2) batches


class RaisingArea(Answers):
    @staticmethod
    def answer(p: Tensor) -> Tensor:
        raise RuntimeError("model weights\nnot loaded")


class NumpyArea(Answers):
    answer = staticmethod(lambda p: p[..., 0].numpy() - 256.0)


class IntegerArea(Answers):
    answer = staticmethod(lambda p: p[..., 0].long() - 256)


class Float64OnlyArea(Answers):
    """A model that takes only float64, when the shield asks in float32."""

    @staticmethod
    def answer(p: Tensor) -> Tensor:
        if p.dtype != torch.float64:
            raise TypeError(f"expected float64, got {p.dtype}")
        return p[..., 0] - 256.0


class FloatContainsArea(Answers):
    def contains(self, points: Tensor) -> Tensor:
        return (self.signed_distance(points) < 0).double()


class RecordingArea(Answers):
    """Keeps every point it was asked about."""

    asked: ClassVar[list[Tensor]] = []

    def signed_distance(self, points: Tensor) -> Tensor:
        RecordingArea.asked.append(points.reshape(-1, 2).double())
        return super().signed_distance(points)


class LazyMeta(type):
    @property
    def area(cls) -> type[RestrictedArea]:  # reading Holder.area would run this
        CALLED.append("Holder.area")
        return InfArea


class Holder(metaclass=LazyMeta):
    pass


HERE = __name__  # this module as the test run imported it: a plug-in package of its own


@pytest.fixture
def victims(tmp_path: Path) -> Iterator[dict[str, str]]:
    """Paths a command would create or remove; checked untouched after the test."""
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "kept").write_text("kept")
    paths = {"pwned": str(tmp_path / "pwned"), "victim": str(victim)}
    CALLED.clear()
    yield paths
    assert not Path(paths["pwned"]).exists(), "a scenario's command ran"
    assert (victim / "kept").exists(), "a scenario's command removed a directory"
    assert not CALLED, f"{CALLED} ran"


ATTACKS = [  # (spec, parameters with {pwned} / {victim} filled in, what the refusal says)
    ("os:system", {"command": "touch {pwned}"}, "names a builtin_function_or_method, not a "
                                                "RestrictedArea subclass"),
    ("builtins:eval", {}, "names a builtin_function_or_method, not a RestrictedArea"),
    ("builtins:exec", {}, "names a builtin_function_or_method, not a RestrictedArea"),
    ("subprocess:run", {"args": ["touch", "{pwned}"]}, "names a function, not a Restricted"),
    ("subprocess:Popen", {"args": ["touch", "{pwned}"]}, "names class Popen, not a Restricted"),
    ("shutil:rmtree", {"path": "{victim}"}, "names a function, not a RestrictedArea"),
    ("builtins:open", {"file": "{pwned}", "mode": "w"}, "names a builtin_function_or_method"),
    ("pathlib:Path.touch", {"self": "{pwned}"}, "names a function, not a RestrictedArea"),
    ("os.path:join", {}, "names a function, not a RestrictedArea subclass"),
    ("os:path.join", {}, "names a function, not a RestrictedArea subclass"),
    ("constrained_diffusion_ros.zones.geometry:rectangle", {}, "names a function, not a Rest"),
    (f"{HERE}:make_area", {}, "names a function, not a RestrictedArea subclass"),
    ("collections:OrderedDict", {}, "names class OrderedDict, not a RestrictedArea subclass"),
    (f"{HERE}:NotAnArea", {}, "names class NotAnArea, not a RestrictedArea subclass"),
    (f"{HERE}:Holder.area", {}, "names a property, not a RestrictedArea subclass"),
    (f"{HERE}:Answers.answer", {}, "names a staticmethod, not a RestrictedArea subclass"),
    (f"{HERE}:NaNArea", {}, r"signed_distance returned NaN at \(384, 0\) for torch.float64 "
                            r"points of shape \(30, 2\)"),
    (f"{HERE}:NegInfArea", {}, r"signed_distance returned -inf at \(0, 0\)"),
    (f"{HERE}:PointShapeArea", {}, r"signed_distance returned shape \(30, 2\) for torch.float64 "
                                   r"points of shape \(30, 2\), expected \(30,\)"),
    (f"{HERE}:FlatArea", {}, r"returned shape \(30,\) for torch.float64 points of shape "
                             r"\(5, 6, 2\), expected \(5, 6\)"),
    (f"{HERE}:RaisingArea", {}, r"signed_distance failed on torch.float64 points of shape "
                                r"\(30, 2\) \(RuntimeError: model weights not loaded\)"),
    (f"{HERE}:NumpyArea", {}, "signed_distance returned a ndarray, not a torch.Tensor"),
    (f"{HERE}:IntegerArea", {}, "returned dtype torch.int64 .*expected a floating-point"),
    (f"{HERE}:Float64OnlyArea", {}, r"failed on torch.float32 points .*TypeError: expected fl"),
    (f"{HERE}:FloatContainsArea", {}, "contains returned dtype torch.float64 .*expected torch"
                                      ".bool"),
]


@pytest.mark.parametrize(("spec", "parameters", "message"), ATTACKS,
                         ids=[spec.rpartition(":")[2] for spec, _, _ in ATTACKS])
def test_a_spec_that_is_not_a_sound_restricted_area_is_refused_before_it_runs(
        spec: str, parameters: dict, message: str, victims: dict[str, str]) -> None:
    """Found by finding 2 of issue 26: "os:system" ran the scenario's command, and only then
    was its result refused. Every row is one line naming the spec, and nothing named ran."""
    filled = {k: [w.format(**victims) for w in v] if isinstance(v, list) else
              v.format(**victims) if isinstance(v, str) else v for k, v in parameters.items()}
    with pytest.raises(ValueError, match=message) as raised:
        load_area(spec, filled)
    text = str(raised.value)
    assert text.startswith(f"restricted area {spec!r}: ") and "\n" not in text


def test_attribute_paths_are_read_without_running_module_getattr(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, victims: dict[str, str]) -> None:
    """A module-level __getattr__ (PEP 562) is code: the spec's attribute must be in the module
    itself. The module's own import runs, as every plug-in's does."""
    name = f"lazy_plugin_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{name}.py").write_text(
        "import pathlib\n"
        "def __getattr__(name):\n"
        f"    pathlib.Path({victims['pwned']!r}).touch()\n"
        "    raise AttributeError(name)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.setenv(PLUGIN_MODULES_ENV, name)
    with pytest.raises(ValueError, match=f"module '{name}' has no attribute 'Area'"):
        load_area(f"{name}:Area", {})


def test_entry_points_are_held_to_the_same_rule(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, victims: dict[str, str]) -> None:
    """An installed distribution's entry point naming a function is refused unrun too."""
    info = tmp_path / "evil_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: evil-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        f"[{ENTRY_POINT_GROUP}]\nshell = os:system\nrunner = subprocess:run\n"
        f"module = os\nfine = {HERE}:InfArea\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match="'shell': names a builtin_function_or_method, not a "):
        load_area("shell", {"command": f"touch {victims['pwned']}"})
    with pytest.raises(ValueError, match="'runner': names a function, not a RestrictedArea"):
        load_area("runner", {"args": ["touch", victims["pwned"]]})
    with pytest.raises(ValueError, match=r"'module': entry point 'os' does not load .*module"):
        load_area("module", {})
    assert isinstance(load_area("fine", {}).plugin, InfArea)


IMPORTED = "imported"  # what a module of test_a_module_is_imported_only_if_allowed prints


def plugin_module(tmp_path: Path, name: str) -> None:
    """`name` (dotted: packages made too), whose import prints IMPORTED; it defines `Area`."""
    *packages, last = name.split(".")
    folder = tmp_path
    for package in packages:
        folder = folder / package
        folder.mkdir(exist_ok=True)
        (folder / "__init__.py").touch()
    (folder / f"{last}.py").write_text(
        f"print({IMPORTED!r})\n"
        "import torch\n"
        "from constrained_diffusion_ros.zones import RestrictedArea\n"
        "class Area(RestrictedArea):\n"
        "    def signed_distance(self, points):\n"
        "        return torch.full(points.shape[:-1], torch.inf, dtype=points.dtype)\n")


def load_in_a_child(tmp_path: Path, spec: str, allowed: str | None = None
                    ) -> subprocess.CompletedProcess:
    """`load_area(spec)` in a fresh interpreter with `tmp_path` on its path, which prints the
    refusal (or "built") and the modules of the spec it imported."""
    environment = {k: v for k, v in os.environ.items() if k != PLUGIN_MODULES_ENV}
    if allowed is not None:
        environment[PLUGIN_MODULES_ENV] = allowed
    environment["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(REPO)])
    module = spec.partition(":")[0]
    code = ("import sys\n"
            "from constrained_diffusion_ros.zones.plugins import load_area\n"
            "try:\n"
            f"    load_area({spec!r})\n"
            "    print('built')\n"
            "except ValueError as error:\n"
            "    print(error)\n"
            f"print('imported:', sorted(m for m in sys.modules if m == {module!r} or "
            f"m.startswith({module.partition('.')[0]!r})))\n")
    return subprocess.run([sys.executable, "-c", code], env=environment, capture_output=True,
                          text=True, timeout=120, check=True)


def test_a_module_is_imported_only_if_allowed(tmp_path: Path) -> None:
    """Found by finding 7 of issue 41: "this:s" printed the Zen of Python, the module imported
    before its attribute was checked. A module not allowed is refused in one line before
    anything is imported; allowed are this package's, those an installed distribution names in
    an entry point of the group, and those listed in the environment variable (a package
    listed allows its submodules)."""
    refused = load_in_a_child(tmp_path, "this:s")
    line, imported = refused.stdout.splitlines()
    assert line == ("restricted area 'this:s': module 'this' is not one plug-ins may come from, "
                    "so it was not imported (allowed: constrained_diffusion_ros, modules named "
                    "by entry points in constrained_diffusion_ros.restricted_areas, and those "
                    f"listed in ${PLUGIN_MODULES_ENV})")
    assert imported == "imported: []" and not refused.stderr  # no Zen of Python, no traceback
    for name in ("user_zones", "user_pkg.zones", "declared.zones"):
        plugin_module(tmp_path, name)
    assert load_in_a_child(tmp_path, "user_zones:Area").stdout.splitlines()[1:] == \
        ["imported: []"]
    assert load_in_a_child(tmp_path, "user_zones:Area", "other, user_zones").stdout.splitlines(
        ) == [IMPORTED, "built", "imported: ['user_zones']"]
    assert load_in_a_child(tmp_path, "user_pkg.zones:Area", "user_pkg").stdout.splitlines() == \
        [IMPORTED, "built", "imported: ['user_pkg', 'user_pkg.zones']"]
    assert "not one plug-ins may come from" in load_in_a_child(  # a prefix of a name is not it
        tmp_path, "user_pkg.zones:Area", "user_pk").stdout
    info = tmp_path / "declared-1.0.dist-info"  # an installed distribution's entry point
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: declared\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\nzones = declared.zones:Area\n")
    assert load_in_a_child(tmp_path, "declared.zones:Area").stdout.splitlines() == \
        [IMPORTED, "built", "imported: ['declared', 'declared.zones']"]
    assert load_in_a_child(tmp_path, "zones").stdout.splitlines()[1] == "built"


def test_the_probe_covers_the_workspace_it_is_given() -> None:
    """5 x 5 over the workspace, one point off the grid, and one past each wall; and areas
    with nothing in them (+inf everywhere, as an empty ZoneSet) are accepted."""
    points = probe_points((0.0, 0.0, 512.0, 512.0))
    assert points.shape == (30, 2) and points.dtype == torch.float64
    assert {tuple(p) for p in points[:25].tolist()} == {
        (x, y) for x in (0, 128, 256, 384, 512) for y in (0, 128, 256, 384, 512)}
    assert points[25].tolist() == pytest.approx([153.6, 358.4])
    assert points[26:].tolist() == [[-16, 256], [528, 256], [256, -16], [256, 528]]
    RecordingArea.asked.clear()
    assert isinstance(load_area(f"{HERE}:RecordingArea", workspace=(100, 50, 200, 90)).plugin,
                      RecordingArea)
    asked = torch.cat(RecordingArea.asked)
    assert asked.amin(dim=0).tolist() == [84, 50 - 16] and asked.amax(dim=0).tolist() == [216,
                                                                                          106]
    assert torch.isinf(load_area(f"{HERE}:InfArea").signed_distance(points)).all()
    empty = ZoneSet.from_polygons([])
    assert torch.isposinf(empty.signed_distance(points)).all()  # what InfArea stands for


# -- A check that turns bad in use (issue 41) ---------------------------------------------------

class TurnsNaN(RestrictedArea):
    """A disc of radius 50 at (256, 256) whose distances turn NaN after `after` queries: it
    passes the load probe (8 queries), and fails later."""

    def __init__(self, after: int = 8) -> None:
        self.after, self.calls = after, 0

    def signed_distance(self, points: Tensor) -> Tensor:
        self.calls += 1
        distance = (points - 256.0).norm(dim=-1) - 50.0
        return distance if self.calls <= self.after else torch.full_like(distance, torch.nan)


class TurnsRaising(TurnsNaN):
    def signed_distance(self, points: Tensor) -> Tensor:
        if self.calls >= self.after:
            raise RuntimeError("camera\nunplugged")
        return super().signed_distance(points)


class OwnContains(TurnsNaN):
    """Answers `contains` itself: a float tensor once it has turned."""

    def contains(self, points: Tensor) -> Tensor:
        inside = self.signed_distance(points) < 0
        return inside if self.calls <= self.after else inside.double()


def test_a_check_that_turns_bad_in_use_raises_naming_the_spec_and_the_fault() -> None:
    """Found by finding 5 of issue 41: a plug-in that turned NaN after the load probe was never
    named; a NaN distance compares false, so the planner took the zone for absent or planned
    NaN waypoints. Every answer is checked in use as the probe checks it, the derived areas'
    too, and the fault is one line naming the spec."""
    spec = f"{HERE}:TurnsNaN"
    area = load_area(spec, {"after": 9})
    points = torch.tensor([[256.0, 256.0], [400.0, 256.0], [300.0, 256.0]])
    torch.testing.assert_close(area.signed_distance(points), torch.tensor([-50.0, 94.0, -6.0]))
    for query in (area.signed_distance, area.contains, area.inflate(5.0).contains,
                  area.bounded((0.0, 0.0, 512.0, 512.0)).signed_distance,
                  area.select_rows(torch.tensor([0])).near(points, 10.0).contains,
                  lambda p: area.project_out(p, 2.0)):
        with pytest.raises(ZoneCheckError) as raised:
            query(points)
        assert str(raised.value) in (f"zone check {spec!r}: signed_distance returned NaN at "
                                     f"(256, 256) for torch.{dtype} points of shape (3, 2)"
                                     for dtype in ("float32", "float64"))  # project_out's
    raising = load_area(f"{HERE}:TurnsRaising", {"after": 8})
    with pytest.raises(ZoneCheckError, match=r"signed_distance failed \(RuntimeError: camera "
                                             r"unplugged\)$"):
        raising.crosses(points, points + 1.0)
    own = load_area(f"{HERE}:OwnContains", {"after": 9})
    assert own.contains(points).tolist() == [True, False, True]
    with pytest.raises(ZoneCheckError, match=r"contains returned dtype torch.float64 for "
                                             r"torch.float32 points of shape \(3, 2\), expected "
                                             r"torch.bool"):
        own.contains(points)


def test_a_checked_area_answers_as_its_plug_in_and_stays_checked_in_a_planning_process(
        ) -> None:
    """The camera overrides every query and derives exact zone sets: checked, it answers bit
    for bit as it does alone, and pickled (as it goes to a planning process) it is checked
    still."""
    area = load_area(CAMERA, {"config_file": "camera_zones.yaml"})
    camera = area.plugin
    points = torch.rand(4, 7, 2, dtype=torch.float64) * 512
    for checked, alone in ((area, camera), (area.bounded((0, 0, 512, 512)).inflate(15.0),
                                            camera.bounded((0, 0, 512, 512)).inflate(15.0))):
        assert torch.equal(checked.signed_distance(points), alone.signed_distance(points))
        assert torch.equal(checked.project_out(points, 3.0), alone.project_out(points, 3.0))
        assert torch.equal(checked.segment_clear_fraction(points, points.flip(0)),
                           alone.segment_clear_fraction(points, points.flip(0)))
    copy = pickle.loads(pickle.dumps(load_area(f"{HERE}:TurnsNaN", {"after": 8})))
    assert isinstance(copy, CheckedArea) and isinstance(copy.plugin, TurnsNaN)
    with pytest.raises(ZoneCheckError, match="returned NaN"):
        copy.contains(points)


# The property: any stdlib attribute, with any parameters, is refused without being called.
STDLIB = [importlib.import_module(m) for m in (
    "os", "os.path", "subprocess", "shutil", "builtins", "pathlib", "importlib", "functools",
    "collections", "io", "tempfile", "sys", "signal", "socket", "pickle", "runpy", "ctypes")]
AFTER_A_CALL = ("bad parameters", "cannot be built", "built a")  # load_area's words


class Tripwire(Mapping[str, Any]):
    """Parameters that raise as soon as they are unpacked into a call, before the callee runs:
    a call of the named object is seen, and (on a regression) nothing drawn is ever run."""

    def __init__(self, keys: list[str]) -> None:
        self._keys, self.unpacked = keys, False

    def keys(self) -> Any:  # `f(**mapping)` asks for the keys first
        self.unpacked = True
        raise RuntimeError("the spec's object was called")

    def __getitem__(self, key: str) -> Any:
        self.unpacked = True
        raise RuntimeError("the spec's object was called")

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


@st.composite
def stdlib_specs(draw: st.DrawFn) -> str:
    """"module:attribute" or "module:attribute.member" over STDLIB, members read statically."""
    module = draw(st.sampled_from(STDLIB))
    attribute = draw(st.sampled_from(sorted(dir(module))))
    target = inspect.getattr_static(module, attribute)
    members = sorted(m for m in dir(target) if isinstance(m, str)) \
        if isinstance(target, type) else []
    if members and draw(st.booleans()):
        attribute = f"{attribute}.{draw(st.sampled_from(members))}"
    return f"{module.__name__}:{attribute}"


@settings(max_examples=150, deadline=None)
@given(spec=stdlib_specs(),
       keys=st.lists(st.sampled_from(["command", "args", "path", "file", "source", "x"]),
                     max_size=3, unique=True))
def test_no_stdlib_object_is_ever_called(spec: str, keys: list[str]) -> None:
    parameters = Tripwire(keys)
    with pytest.raises(ValueError) as raised:
        load_area(spec, parameters)
    text = str(raised.value)
    assert not parameters.unpacked, f"{spec} was called"
    assert text.startswith(f"restricted area {spec!r}: ") and "\n" not in text
    assert not any(phrase in text for phrase in AFTER_A_CALL), text
