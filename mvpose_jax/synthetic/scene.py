"""The rig's floor and capture area, and host-side (numpy) camera geometry for the generator.

Nothing here needs settings for a user's own calibration:

* Up: the calibration's ``up`` or, without one, `cameras.up_vector`'s inference: cameras are
  mounted level (no roll), so their image x axes are horizontal and up is the direction most
  perpendicular to all of them. One camera, or cameras with parallel x axes, cannot show the tilt
  about those axes: such rigs need ``up`` in the calibration.
* Floor height: cameras are mounted to watch people standing on a floor below them, so the floor
  is the height at which a standing person is seen whole, and large enough, by the most cameras
  over the largest area. `estimate_floor_height` scans candidate heights below the lowest camera;
  for each it counts, on a grid of floor cells, the cameras that see a 1.75 m person standing
  there from feet to head inside the image and at least 30 % of the image height tall. The area
  seen by ``min(3, C)`` cameras has a broad plateau over the height; the floor is the middle of the
  heights within 5 % of the best. On the shipped presets this finds the documented floors
  (panoptic5 y = 0 within 2 cm, arplab6 z = 0 within 9 cm). A ``floor_height`` in `SceneConfig`
  overrides it.
* Capture area: floor cells where at least ``min_views`` cameras see the whole standing person
  (and it is at least ``min_person_height`` of the image tall), at least ``camera_clearance`` from
  every camera and, when the cameras surround the space, inside their horizontal convex hull less
  ``hull_margin``.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np

from mvpose_jax.cameras import Rig, up_vector
from mvpose_jax.errors import InputError
from mvpose_jax.synthetic.config import SceneConfig

# The reference person of the floor and area searches: feet (ankles) and top of the head, metres.
_PROBE_HEIGHTS = (0.05, 1.75)
# The floor search wants the person large (30 % of the image height): a rig is aimed at where
# people are, not at the far end of the room.
_FLOOR_PROBE_MIN_HEIGHT = 0.3
# Depth below which a point counts as behind a camera, metres.
MIN_DEPTH = 0.1


@dataclasses.dataclass(frozen=True)
class CameraModel:
    """The rig's cameras as float64 numpy arrays (host-side projection). C cameras."""

    K: np.ndarray  # (C, 3, 3)
    dist: np.ndarray  # (C, 5) k1 k2 p1 p2 k3
    R: np.ndarray  # (C, 3, 3) cam_from_world
    t: np.ndarray  # (C, 3)
    size: np.ndarray  # (C, 2) width, height in px
    centres: np.ndarray  # (C, 3) camera centres, world
    max_radius2: np.ndarray  # (C,) squared undistorted normalised radius of the image corners

    @staticmethod
    def from_rig(rig: Rig) -> CameraModel:
        K = np.asarray(rig.K, np.float64)
        dist = np.asarray(rig.dist, np.float64)
        R = np.asarray(rig.R, np.float64)
        t = np.asarray(rig.t, np.float64)
        size = np.asarray(rig.size, np.float64)
        centres = -np.einsum("cji,cj->ci", R, t)
        # Beyond the image corners a distortion polynomial can fold points back into the image;
        # points further from the axis than the corners never count as seen.
        corners = np.stack(
            [np.zeros_like(size), size * [1, 0], size * [0, 1], size], axis=1
        )  # (C, 4, 2)
        xy = _undistort(K, dist, corners)
        max_r2 = (xy**2).sum(-1).max(-1) * 1.1
        return CameraModel(K, dist, R, t, size, centres, max_r2)

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera frames (C, ..., 3)."""
        flat = points.reshape(-1, 3)
        out = np.matmul(flat[None], self.R.transpose(0, 2, 1)) + self.t[:, None]  # (C, N, 3)
        return out.reshape((-1,) + points.shape)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Projects world points into every camera (same model as `cameras.project_points`).

        Args:
          points: (..., 3) world points, metres.
        Returns:
          px (C, ..., 2) distorted pixels, depth (C, ...) metres, in_image (C, ...) bool (in
          front of the camera, inside the image and within the corners' field of view).
        """
        p = self.to_camera(points)
        return self.project_camera_points(p)

    def project_camera_points(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like `project` for points already in each camera's frame, p: (C, ..., 3)."""
        shape = (-1,) + (1,) * (p.ndim - 2)
        z = p[..., 2]
        # Same clamp as cameras.project_points, so that the two agree everywhere.
        z_safe = np.maximum(z, 1e-3)
        x, y = p[..., 0] / z_safe, p[..., 1] / z_safe
        d = self.dist
        k1, k2, p1, p2, k3 = (d[:, i].reshape(shape) for i in range(5))
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        K = self.K
        u = (
            K[:, 0, 0].reshape(shape) * xd
            + K[:, 0, 1].reshape(shape) * yd
            + K[:, 0, 2].reshape(shape)
        )
        v = K[:, 1, 1].reshape(shape) * yd + K[:, 1, 2].reshape(shape)
        px = np.stack([u, v], axis=-1)
        w, h = self.size[:, 0].reshape(shape), self.size[:, 1].reshape(shape)
        inside = (
            (z > MIN_DEPTH)
            & (r2 < self.max_radius2.reshape(shape))
            & (u >= 0)
            & (u < w)
            & (v >= 0)
            & (v < h)
        )
        return px, z, inside


@dataclasses.dataclass(frozen=True)
class SceneGeometry:
    """Floor frame and capture area of a rig.

    World point of floor coordinates (a, b) at height s above the floor:
    ``origin + a * e1 + b * e2 + s * up``.

    Attributes:
      up: (3,) unit world up.
      e1, e2: (3,) unit floor axes; (e1, e2, up) is right-handed.
      origin: (3,) point on the floor below the mean camera centre.
      floor_height: floor height along ``up``, metres.
      cells: (N, 2) floor coordinates of the capture-area cells' centres.
      cell_views: (N,) number of cameras that see a standing person whole in each cell.
      cell_size: side of a cell, metres.
      cameras: the rig as a `CameraModel`.
    """

    up: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    origin: np.ndarray
    floor_height: float
    cells: np.ndarray
    cell_views: np.ndarray
    cell_size: float
    cameras: CameraModel

    @property
    def basis(self) -> np.ndarray:
        """(3, 3) rows e1, e2, up."""
        return np.stack([self.e1, self.e2, self.up])

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Floor coordinates (..., 3) = (a, b, height) -> world points (..., 3)."""
        return self.origin + local @ self.basis

    def area(self) -> float:
        """Capture area, square metres."""
        return float(len(self.cells) * self.cell_size**2)

    def contains(self, ab: np.ndarray) -> np.ndarray:
        """Whether floor points (..., 2) fall in a capture-area cell: (...,) bool."""
        key = np.round(np.asarray(ab) / self.cell_size).astype(np.int64)
        return np.isin(_cell_keys(key), self._keys)

    @property
    def _keys(self) -> np.ndarray:
        return _cell_keys(np.round(self.cells / self.cell_size).astype(np.int64))


def _cell_keys(idx: np.ndarray) -> np.ndarray:
    return idx[..., 0] * 1_000_003 + idx[..., 1]


_CACHE: dict[tuple[str, SceneConfig], SceneGeometry] = {}


def scene_geometry(rig: Rig, config: SceneConfig = SceneConfig()) -> SceneGeometry:
    """Floor frame and capture area of a rig (cached per rig and config).

    Raises:
      InputError when no floor cell is seen by enough cameras (give ``floor_height`` or lower
      ``min_views``).
    """
    key = (_rig_key(rig), config)
    if key not in _CACHE:
        _CACHE[key] = _build_geometry(rig, config)
    return _CACHE[key]


def estimate_floor_height(rig: Rig, up: np.ndarray | None = None) -> float:
    """Floor height along ``up`` seen best by the rig (see the module docstring), metres."""
    cams = CameraModel.from_rig(rig)
    up = up_vector(rig) if up is None else np.asarray(up, np.float64)
    e1, e2 = _floor_axes(up)
    heights = cams.centres @ up
    lowest = heights.min()
    need = min(3, cams.num_cameras)

    extent = float(np.abs((cams.centres - cams.centres.mean(0)) @ np.stack([e1, e2]).T).max()) + 6.0

    def score(h: float, cell: float) -> float:
        views = _visible_views(
            cams, _floor_origin(cams, up, h), up, e1, e2, cell, _FLOOR_PROBE_MIN_HEIGHT, extent
        )
        # Area seen by min(3, C) cameras; the area seen by 2 breaks ties.
        return float((views >= need).sum() + 1e-3 * (views >= 2).sum()) * cell**2

    # Coarse scan from 3.5 m to 0.2 m below the lowest camera, then a fine one around the best.
    coarse = np.arange(lowest - 3.5, lowest - 0.2 + 1e-9, 0.1)
    scores = np.array([score(h, 0.2) for h in coarse])
    if scores.max() == 0:
        raise InputError(
            "cannot estimate the floor: no camera sees a standing person whole; give floor_height",
            field="floor_height",
        )
    best = coarse[int(np.argmax(scores))]
    fine = np.arange(best - 0.5, best + 0.5 + 1e-9, 0.05)
    fine_scores = np.array([score(h, 0.1) for h in fine])
    # The score has a broad, slightly noisy plateau: take the middle of the heights within 5 % of
    # the best, which is stable against grid sampling.
    good = fine[fine_scores >= 0.95 * fine_scores.max()]
    return float(0.5 * (good.min() + good.max()))


# --------------------------------------------------------------------------- helpers


def _rig_key(rig: Rig) -> str:
    h = hashlib.sha1()
    for a in (rig.K, rig.dist, rig.R, rig.t, rig.size):
        h.update(np.ascontiguousarray(np.asarray(a, np.float64)).tobytes())
    h.update(repr((rig.names, rig.up)).encode())
    return h.hexdigest()


def _floor_axes(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # e1: the world axis most perpendicular to up, made perpendicular; e2 = up x e1.
    axis = np.eye(3)[np.argmin(np.abs(up))]
    e1 = axis - (axis @ up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return e1, e2


def _visible_views(
    cams: CameraModel,
    origin,
    up,
    e1,
    e2,
    cell: float,
    min_height: float,
    extent: float,
    return_grid: bool = False,
):
    """Number of cameras that see a standing person whole on each cell of a floor grid.

    The grid spans ``[-extent, extent]^2`` floor coordinates around ``origin`` (on the floor).
    """
    n = int(np.ceil(extent / cell))
    g = np.arange(-n, n + 1) * cell  # cell centres are multiples of the cell size
    a, b = np.meshgrid(g, g, indexing="ij")
    ab = np.stack([a.ravel(), b.ravel()], -1)  # (N, 2)
    hs = np.asarray(_PROBE_HEIGHTS)
    pts = (
        origin + ab[:, None, 0:1] * e1 + ab[:, None, 1:2] * e2 + hs[None, :, None] * up
    )  # (N, 2, 3)
    px, _, inside = cams.project(pts)  # (C, N, 2, 2), (C, N, 2)
    tall = np.linalg.norm(px[:, :, 1] - px[:, :, 0], axis=-1) >= min_height * cams.size[:, 1:2]
    views = (inside.all(-1) & tall).sum(0)
    return (views, ab) if return_grid else views


def _floor_origin(cams: CameraModel, up: np.ndarray, floor_h: float) -> np.ndarray:
    centre = cams.centres.mean(0)
    return centre - (centre @ up - floor_h) * up


def _build_geometry(rig: Rig, config: SceneConfig) -> SceneGeometry:
    cams = CameraModel.from_rig(rig)
    if config.up is not None:
        up = np.asarray(config.up, np.float64)
        up = up / np.linalg.norm(up)
    else:
        up = up_vector(rig)
    e1, e2 = _floor_axes(up)
    floor_h = (
        config.floor_height if config.floor_height is not None else estimate_floor_height(rig, up)
    )
    if config.floor_offset_m:
        floor_h = floor_h + config.floor_offset_m
    origin = _floor_origin(cams, up, floor_h)
    cam_ab = np.stack([(cams.centres - origin) @ e1, (cams.centres - origin) @ e2], -1)
    extent = float(np.abs(cam_ab).max()) + 6.0
    views, ab = _visible_views(
        cams,
        origin,
        up,
        e1,
        e2,
        config.cell_size,
        config.min_person_height,
        extent,
        return_grid=True,
    )
    keep = views >= min(config.min_views, cams.num_cameras)
    keep &= (np.linalg.norm(ab[:, None] - cam_ab[None], axis=-1) >= config.camera_clearance).all(-1)
    inside_hull = _inside_hull(cam_ab, ab, config.hull_margin)
    if inside_hull is not None and (keep & inside_hull).sum() * config.cell_size**2 >= 1.0:
        keep &= inside_hull
    if not keep.any():
        raise InputError(
            f"no floor cell is seen whole by {config.min_views} cameras; lower min_views or give "
            "floor_height",
            field="floor_height",
        )
    return SceneGeometry(
        up, e1, e2, origin, float(floor_h), ab[keep], views[keep], config.cell_size, cams
    )


def _inside_hull(points: np.ndarray, query: np.ndarray, margin: float) -> np.ndarray | None:
    """Whether query points lie inside the convex hull of points, shrunk by margin (2D).

    Returns None when the cameras do not surround a space (hull area under 4 m^2).
    """
    hull = _convex_hull(points)
    if len(hull) < 3:
        return None
    x, y = hull[:, 0], hull[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    if area < 4.0:
        return None
    inside = np.ones(len(query), bool)
    for i in range(len(hull)):  # a handful of edges
        p, q = hull[i], hull[(i + 1) % len(hull)]
        edge = q - p
        normal = np.array([-edge[1], edge[0]]) / np.linalg.norm(edge)  # inward for CCW order
        inside &= (query - p) @ normal >= margin
    return inside


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """2D convex hull, counter-clockwise (Andrew's monotone chain)."""
    pts = sorted(map(tuple, np.asarray(points, np.float64)))
    if len(pts) < 3:
        return np.asarray(pts)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.asarray(lower[:-1] + upper[:-1])


def _undistort(K: np.ndarray, dist: np.ndarray, px: np.ndarray, iters: int = 20) -> np.ndarray:
    """Distorted pixels (C, N, 2) -> undistorted normalised coordinates (cv::undistortPoints)."""
    k1, k2, p1, p2, k3 = (dist[:, i, None] for i in range(5))
    y0 = (px[..., 1] - K[:, 1, 2, None]) / K[:, 1, 1, None]
    x0 = (px[..., 0] - K[:, 0, 2, None] - K[:, 0, 1, None] * y0) / K[:, 0, 0, None]
    x, y = x0.copy(), y0.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        icdist = 1.0 / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x, y = (x0 - dx) * icdist, (y0 - dy) * icdist
    return np.stack([x, y], -1)
