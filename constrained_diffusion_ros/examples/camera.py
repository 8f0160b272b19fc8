"""A worked example of a plug-in area in another space: zones drawn in a camera's image.

An operator marks keep-out regions on the image of a camera that looks obliquely at the table;
the planner works in workspace px. A homography H (3x3) maps the image of the table plane to
the workspace: (x w, y w, w) = H (u, v, 1). It maps straight lines to straight lines, so a
polygon drawn in the image maps to the polygon through its mapped vertices, exactly, as long as
the polygon stays on the table's side of the horizon line (where w = 0 and points map to
infinity); beyond it an edge would wrap through infinity, so such a zone is refused. The mapped
polygons become an exact `ZoneSet`, which answers every query.

It lives outside the ROS-free core, as a user's own package would, and uses only the public
`zones` API. Loaded by a scenario as a plug-in (`zones.plugins.load_area`):
`plugin: {class: "constrained_diffusion_ros.examples.camera:CameraZones",
parameters: {config_file: camera_zones.yaml}}`, or by its entry point name `camera_zones`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from torch import Tensor

from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.planning.constraint_configs import read_yaml
from constrained_diffusion_ros.zones import Bounds, RestrictedArea, ZoneSet, validate_polygon

WORKSPACE_CENTRE = (256.0, 256.0)  # PushT's 512 x 512 workspace: a point every camera sees
HORIZON_MARGIN = 1e-6  # w relative to w at the table point: closer to the horizon is refused


def apply_homography(matrix: ArrayLike, points: ArrayLike) -> np.ndarray:
    """Points (..., 2) mapped by a 3x3 homography (no check of the horizon: see CameraZones)."""
    h, p = np.asarray(matrix, dtype=np.float64), np.asarray(points, dtype=np.float64)
    mapped = p @ h[:, :2].T + h[:, 2]
    return mapped[..., :2] / mapped[..., 2:]


class CameraZones(RestrictedArea):
    """Zones drawn as polygons in camera image px, kept out of in workspace px.

    `config_file` (YAML, safe-loaded; a relative path is taken from the package's config
    directory) holds `image_to_workspace` (the 3x3 homography), `zones` (polygons [[u, v], ...]
    in image px) and optionally `table_point` (a workspace point the camera sees, default the
    workspace centre: it tells which side of the horizon is the table). Every query goes to the
    exact `ZoneSet` of the mapped polygons.
    """

    def __init__(self, config_file: str | Path) -> None:
        path = Path(config_file)
        if not path.is_absolute():
            path = config_dir() / path
        document = read_yaml(path)
        if not isinstance(document, dict):
            raise ValueError(f"{path}: expected a mapping with image_to_workspace and zones")
        unknown = sorted(set(document) - {"image_to_workspace", "zones", "table_point"})
        if unknown:
            raise ValueError(f"{path}: unknown keys {unknown}")
        self.path = path
        self.homography = self._matrix(document.get("image_to_workspace"))
        x, y = map(float, document.get("table_point", WORKSPACE_CENTRE))
        seen = np.linalg.solve(self.homography, [x, y, 1.0])  # H seen = (x, y, 1): w = 1 / seen[2]
        if not abs(seen[2]) > 1e-12 * np.abs(seen).max():
            raise ValueError(f"{path}: table_point ({x}, {y}) is at infinity in the image")
        self._table_w = 1.0 / seen[2]
        zones = document.get("zones") or []
        if not isinstance(zones, list) or not zones:
            raise ValueError(f"{path}: zones must be a non-empty list of image polygons")
        self.image_polygons = [np.asarray(validate_polygon(z, f"{path.name} zone {i} (image)")
                                          .exterior.coords)[:-1] for i, z in enumerate(zones)]
        self.polygons = [self._to_workspace(p, i) for i, p in enumerate(self.image_polygons)]
        self.zones = ZoneSet.from_polygons(self.polygons)

    def _matrix(self, value: object) -> np.ndarray:
        try:
            matrix = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            matrix = np.zeros(0)
        if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
            raise ValueError(f"{self.path}: image_to_workspace must be a finite 3x3 matrix")
        if abs(np.linalg.det(matrix)) < 1e-12 * np.abs(matrix).max() ** 3:
            raise ValueError(f"{self.path}: image_to_workspace is singular")
        return matrix

    def _w(self, image_points: np.ndarray) -> np.ndarray:
        return np.asarray(image_points, dtype=np.float64) @ self.homography[2, :2] \
            + self.homography[2, 2]

    def _to_workspace(self, image_polygon: np.ndarray, index: int) -> np.ndarray:
        """The exact workspace polygon of an image polygon on the table side of the horizon."""
        side = self._w(image_polygon) / self._table_w
        if not (side > HORIZON_MARGIN).all():
            beyond = np.flatnonzero(~(side > HORIZON_MARGIN)).tolist()
            raise ValueError(f"{self.path.name} zone {index}: vertices {beyond} lie on or beyond "
                             "the horizon line, where the image shows no point of the table")
        mapped = apply_homography(self.homography, image_polygon)
        validate_polygon(mapped, f"{self.path.name} zone {index} (workspace)")
        return mapped

    def to_workspace(self, image_points: ArrayLike) -> np.ndarray:
        """Image px (..., 2) -> workspace px (..., 2)."""
        return apply_homography(self.homography, image_points)

    def to_image(self, workspace_points: ArrayLike) -> np.ndarray:
        """Workspace px (..., 2) -> image px (..., 2)."""
        return apply_homography(np.linalg.inv(self.homography), workspace_points)

    # -- every query answered by the exact zone set ----------------------------------------------

    def contains(self, points: Tensor) -> Tensor:
        return self.zones.contains(points)

    def signed_distance(self, points: Tensor) -> Tensor:
        return self.zones.signed_distance(points)

    def outward_direction(self, points: Tensor) -> Tensor:
        return self.zones.outward_direction(points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        return self.zones.project_out(points, margin)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self.zones.segment_clear_fraction(starts, ends)

    def crosses(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self.zones.crosses(starts, ends)

    def _inflated(self, radius: float) -> RestrictedArea:
        return self.zones.inflate(radius)

    def _bounded(self, workspace: Bounds) -> RestrictedArea:
        return self.zones.bounded(workspace)

    def __repr__(self) -> str:
        return f"CameraZones({self.path.name}: {len(self.polygons)} zones, {self.zones!r})"
