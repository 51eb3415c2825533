"""Calibrated camera rigs and their geometry, as pure jit-able functions.

Camera model (OpenCV's, everywhere): ``x_cam = R @ x_world + t`` in metres; the normalised point
``(x, y) = x_cam[:2] / x_cam[2]`` is distorted with k1 k2 p1 p2 k3 (cv::projectPoints) and mapped
to pixels by K. Functions over a rig put the camera axis first: ``(C, ...)``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from mvpose_jax import compiled
from mvpose_jax.errors import InputError

# Depth below which a point counts as behind the camera (metres). Projection clamps the depth to
# it so that points behind a camera give large but finite pixels and finite gradients.
MIN_DEPTH = 1e-2

# The distortion polynomial is a fit valid over the image only; far outside it r^6 terms explode
# (a point 1 m off-axis at 1 cm depth would land at ~1e19 px and overflow float32 losses). The
# radial factor is therefore evaluated at most at this multiple of the image corners' squared
# normalised radius: exact (OpenCV) over the image and well beyond, finite everywhere.
MAX_R2_FACTOR = 4.0

# Iterations of the fixed-point undistortion. OpenCV's cv::undistortPoints stops after 5 by default;
# with the strong barrel distortion of real rigs (k1 ~ -0.28) that leaves ~0.02 px near the image
# corners, so we iterate to float32 convergence (20 cover strong radial+tangential models). ``num_iters=5``
# reproduces OpenCV's default.
UNDISTORT_ITERS = 20
# Steps between the undistortion's convergence checks (a check costs about a step).
_UNDISTORT_BLOCK = 4


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Rig:
    """Calibrated cameras. Shapes: C cameras. Build with `make_rig` (it validates).

    ``names`` and ``up`` are static (part of the jit cache key, not traced).
    """

    K: jax.Array  # (C, 3, 3) intrinsics, pixels
    dist: jax.Array  # (C, 5) k1 k2 p1 p2 k3
    R: jax.Array  # (C, 3, 3) cam_from_world rotation
    t: jax.Array  # (C, 3) cam_from_world translation, metres
    size: jax.Array  # (C, 2) image (width, height), pixels
    names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    # World up direction (unit), or None when the calibration does not say (see `up_vector`).
    up: tuple[float, float, float] | None = dataclasses.field(
        default=None, metadata=dict(static=True)
    )

    @property
    def num_cameras(self) -> int:
        return len(self.names)

    def select(self, cameras: Sequence[str | int]) -> Rig:
        """Returns the rig of the given cameras (names or indices), in that order."""
        idx = [self.camera_index(c) for c in cameras]
        if idx == list(range(self.num_cameras)):
            return self  # every camera in order (the pipeline's usual case): nothing to gather

        def take(a):
            if isinstance(a, jax.core.Tracer):
                return jnp.asarray(a)[np.asarray(idx)]
            # Concrete arrays: numpy's indexing, then one transfer. jax's op-by-op gather costs
            # about 1 ms an array to dispatch, 5 ms a rig: most of a live stream's set-up.
            return jnp.asarray(np.asarray(a)[idx])

        return Rig(
            take(self.K),
            take(self.dist),
            take(self.R),
            take(self.t),
            take(self.size),
            tuple(self.names[i] for i in idx),
            self.up,
        )

    def camera_index(self, camera: str | int) -> int:
        """Index of a camera given by name or index; raises InputError if unknown."""
        if isinstance(camera, (int, np.integer)) and not isinstance(camera, bool):
            if 0 <= camera < self.num_cameras:
                return int(camera)
        elif camera in self.names:
            return self.names.index(camera)
        raise InputError(f"unknown camera; the rig has {list(self.names)}", camera=camera)


def make_rig(
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    size: np.ndarray,
    names: Sequence[str],
    up: Sequence[float] | None = None,
    *,
    file: object = None,
) -> Rig:
    """Validates calibration arrays and builds a `Rig` (float32 arrays).

    Args:
      K: (C, 3, 3); dist: (C, 5) or (C, 4) (k3 = 0); R: (C, 3, 3); t: (C, 3); size: (C, 2) wh.
      names: C unique camera names.
      up: optional world up vector (3,), normalised here.
      file: where the numbers came from, for error messages.
    Raises:
      InputError naming file, camera and field: wrong shapes, non-finite numbers, a singular or
      malformed K, a non-orthonormal or reflecting R, non-positive image sizes, duplicate names.
    """
    names = tuple(str(n) for n in names)
    num = len(names)
    if num == 0:
        raise InputError("calibration has no cameras", file=file, field="cameras")
    if len(set(names)) != num:
        raise InputError(f"duplicate camera names {list(names)}", file=file, field="name")
    fields = {}
    for field, value, shape in (
        ("K", K, (3, 3)),
        ("dist", dist, None),
        ("R", R, (3, 3)),
        ("t", t, (3,)),
        ("size", size, (2,)),
    ):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise InputError(f"not an array of numbers ({e})", file=file, field=field) from None
        if arr.ndim == 0 or arr.shape[0] != num:
            raise InputError(
                f"expected {num} entries (one per camera), got shape {arr.shape}",
                file=file,
                field=field,
            )
        if field == "dist":
            if arr.ndim != 2 or arr.shape[1] not in (4, 5):
                raise InputError(
                    f"expected 4 or 5 coefficients [k1, k2, p1, p2(, k3)], got shape {arr.shape[1:]}",
                    file=file,
                    field=field,
                )
            arr = np.pad(arr, ((0, 0), (0, 5 - arr.shape[1])))
        elif arr.shape[1:] != shape:
            raise InputError(f"expected shape {shape}, got {arr.shape[1:]}", file=file, field=field)
        for c in range(num):
            if not np.all(np.isfinite(arr[c])):
                raise InputError(
                    "contains NaN or infinity", file=file, camera=names[c], field=field
                )
        fields[field] = arr
    for c, name in enumerate(names):
        k = fields["K"][c]
        if not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
            raise InputError(
                "K must be upper triangular with last row [0, 0, 1]",
                file=file,
                camera=name,
                field="K",
            )
        if k[0, 0] <= 0 or k[1, 1] <= 0 or abs(np.linalg.det(k)) < 1e-9:
            raise InputError(
                "K is singular (focal lengths must be positive)", file=file, camera=name, field="K"
            )
        r = fields["R"][c]
        err = np.abs(r @ r.T - np.eye(3)).max()
        if err > 1e-4:
            raise InputError(
                f"R is not orthonormal (max |R R^T - I| = {err:.3g})",
                file=file,
                camera=name,
                field="R",
            )
        if np.linalg.det(r) < 0:
            raise InputError("R is a reflection (det < 0)", file=file, camera=name, field="R")
        if np.any(fields["size"][c] <= 0):
            raise InputError("image size must be positive", file=file, camera=name, field="size")
    up_t = None
    if up is not None:
        u = np.asarray(up, dtype=np.float64)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
            raise InputError("up must be a finite non-zero 3-vector", file=file, field="up")
        up_t = tuple(float(x) for x in u / np.linalg.norm(u))
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return Rig(
        f32(fields["K"]),
        f32(fields["dist"]),
        f32(fields["R"]),
        f32(fields["t"]),
        f32(fields["size"]),
        names,
        up_t,
    )


# --------------------------------------------------------------------------- per-camera kernels


def _distort(dist: jax.Array, xy: jax.Array, r2_max: jax.Array) -> jax.Array:
    """OpenCV's distortion of normalised points. dist: (5,); xy: (..., 2) -> (..., 2).

    ``r2_max`` bounds the squared radius at which the polynomial is evaluated (MAX_R2_FACTOR).
    """
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    rc = jnp.minimum(r2, r2_max)
    radial = 1.0 + rc * (k1 + rc * (k2 + rc * k3))
    # Same terms as cv::projectPoints for the 5-coefficient model.
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


def _to_pixels(K: jax.Array, xy: jax.Array) -> jax.Array:
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    return jnp.stack([u, v], axis=-1)


def _from_pixels(K: jax.Array, px: jax.Array) -> jax.Array:
    y = (px[..., 1] - K[1, 2]) / K[1, 1]
    x = (px[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return jnp.stack([x, y], axis=-1)


def _cam_from_world(R: jax.Array, t: jax.Array, points: jax.Array) -> jax.Array:
    return jnp.einsum("ij,...j->...i", R, points) + t.reshape((1,) * (points.ndim - 1) + (3,))


def _max_r2(K: jax.Array, size: jax.Array) -> jax.Array:
    """MAX_R2_FACTOR times the largest squared normalised radius of the image corners."""
    corners = jnp.stack(
        [jnp.zeros(2), size * jnp.array([1.0, 0.0]), size * jnp.array([0.0, 1.0]), size]
    )
    return MAX_R2_FACTOR * jnp.max(jnp.sum(jnp.square(_from_pixels(K, corners)), axis=-1))


def _project_one(K, dist, R, t, size, points):
    p_cam = _cam_from_world(R, t, points)
    z = p_cam[..., 2:3]
    # Double-where: points behind the camera get a clamped depth, so no inf/NaN, even in grads.
    z_safe = jnp.where(z > MIN_DEPTH, z, MIN_DEPTH)
    return _to_pixels(K, _distort(dist, p_cam[..., :2] / z_safe, _max_r2(K, size)))


def _undistort_one(K, dist, px, num_iters):
    # cv::undistortPoints' fixed-point iteration (cvUndistortPointsInternal), 5-coefficient model.
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    xy0 = _from_pixels(K, px)
    x0, y0 = xy0[..., 0], xy0[..., 1]

    def step(x, y):
        r2 = x * x + y * y
        icdist = 1.0 / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        nx, ny = (x0 - dx) * icdist, (y0 - dy) * icdist
        # OpenCV falls back to the distorted point when the radial factor turns negative.
        ok = icdist > 0
        return jnp.where(ok, nx, x0), jnp.where(ok, ny, y0)

    block = math.gcd(num_iters, _UNDISTORT_BLOCK)

    def body(state):
        i, x, y, _ = state
        for _ in range(block - 1):
            x, y = step(x, y)
        nx, ny = step(x, y)
        return i + block, nx, ny, jnp.any((nx != x) | (ny != y))

    # ``num_iters`` steps, in blocks, stopped early once a block's last step changes no point:
    # from there on every step would return the same numbers, so the result is the fixed
    # count's, bit for bit. A real lens's few percent of distortion settles within the first
    # block (a live frame's undistortion is most of its epipolar distances' arithmetic); strong
    # distortion in float32 can alternate between neighbouring values and run every step.
    state = (jnp.int32(0), x0, y0, jnp.bool_(True))
    _, x, y, _ = jax.lax.while_loop(lambda s: (s[0] < num_iters) & s[3], body, state)
    return jnp.stack([x, y], axis=-1)


# --------------------------------------------------------------------------- public functions


def world_to_camera(rig: Rig, points: jax.Array) -> jax.Array:
    """Points in every camera's frame. points: (..., 3) metres -> (C, ..., 3)."""
    return jax.vmap(_cam_from_world, in_axes=(0, 0, None))(rig.R, rig.t, points)


def project_points(rig: Rig, points: jax.Array) -> jax.Array:
    """Projects world points into every camera, lens distortion included (cv2.projectPoints).

    Args:
      points: (..., 3) world points, metres.
    Returns:
      (C, ..., 2) distorted pixel coordinates. Points behind a camera (depth <= MIN_DEPTH) are
      projected at depth MIN_DEPTH: finite, far off the image; test `point_depths` to mask them.
      Far outside the image the radial factor is frozen (MAX_R2_FACTOR) to stay finite.
    """
    return jax.vmap(_project_one, in_axes=(0, 0, 0, 0, 0, None))(
        rig.K, rig.dist, rig.R, rig.t, rig.size, points
    )


def project_points_per_camera(rig: Rig, points: jax.Array) -> jax.Array:
    """Like `project_points`, with each camera's own points. points: (C, ..., 3) -> (C, ..., 2)."""
    return jax.vmap(_project_one)(rig.K, rig.dist, rig.R, rig.t, rig.size, points)


def point_depths(rig: Rig, points: jax.Array) -> jax.Array:
    """Depth along each camera's optical axis. points: (..., 3) -> (C, ...) metres."""
    return world_to_camera(rig, points)[..., 2]


@compiled.jit(static_argnames="num_iters")
def undistort_normalized(rig: Rig, px: jax.Array, *, num_iters: int = UNDISTORT_ITERS) -> jax.Array:
    """Distorted pixels to undistorted normalised image coordinates (cv2.undistortPoints, P=None).

    Args:
      px: (C, ..., 2) pixels of each camera.
      num_iters: fixed-point iterations (OpenCV uses 5).
    Returns:
      (C, ..., 2) normalised coordinates (x/z, y/z in the camera frame).
    """
    return jax.vmap(_undistort_one, in_axes=(0, 0, 0, None))(rig.K, rig.dist, px, num_iters)


@compiled.jit(static_argnames="num_iters")
def undistort_points(rig: Rig, px: jax.Array, *, num_iters: int = UNDISTORT_ITERS) -> jax.Array:
    """Distorted pixels to undistorted pixels (cv2.undistortPoints with P=K).

    Args:
      px: (C, ..., 2) pixels of each camera.
    Returns:
      (C, ..., 2) pixels of an ideal pinhole camera with the same K.
    """
    xy = undistort_normalized(rig, px, num_iters=num_iters)
    return jax.vmap(_to_pixels)(rig.K, xy)


def camera_centres(rig: Rig) -> jax.Array:
    """Camera centres in the world, -R^T t: (C, 3) metres."""
    return -jnp.einsum("cji,cj->ci", rig.R, rig.t)


@compiled.jit(static_argnames="num_iters")
def pixel_rays(rig: Rig, px: jax.Array, *, num_iters: int = UNDISTORT_ITERS) -> jax.Array:
    """Unit directions, in the world, of the rays through (distorted) pixels.

    The ray of pixel ``px[c, ...]`` starts at ``camera_centres(rig)[c]``.

    Args:
      px: (C, ..., 2) pixels of each camera.
    Returns:
      (C, ..., 3) unit vectors, world frame.
    """
    xy = undistort_normalized(rig, px, num_iters=num_iters)
    d_cam = jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1)
    d_cam = d_cam / jnp.linalg.norm(d_cam, axis=-1, keepdims=True)  # norm >= 1: no guard needed
    return jnp.einsum("cji,c...j->c...i", rig.R, d_cam)  # world_from_cam = R^T


def projection_matrices(rig: Rig) -> jax.Array:
    """Pinhole projection matrices K [R | t] (no distortion): (C, 3, 4)."""
    return jnp.einsum("cij,cjk->cik", rig.K, jnp.concatenate([rig.R, rig.t[..., None]], axis=-1))


def normalise_pixels(rig: Rig, px: jax.Array) -> jax.Array:
    """Pixels to [-1, 1] by each camera's image size. px: (C, ..., 2) -> (C, ..., 2)."""
    size = rig.size.reshape(rig.size.shape[:1] + (1,) * (px.ndim - 2) + (2,))
    return 2.0 * px / size - 1.0


def rig_centre_and_radius(rig: Rig) -> tuple[jax.Array, jax.Array]:
    """Centre (mean camera centre, (3,)) and radius (largest centre distance, ()) of the rig.

    Networks see world coordinates as ``(x - centre) / radius``, so one trained model's inputs
    are of order one on any rig, whatever its units' origin.
    """
    centres = camera_centres(rig)
    centre = centres.mean(axis=0)
    radius = jnp.linalg.norm(centres - centre[None], axis=-1).max()
    return centre, jnp.maximum(radius, 1e-6)


def up_vector(rig: Rig) -> np.ndarray:
    """World up direction: the calibration's ``up`` or, without one, inferred from the cameras.

    Cameras that film people are mounted level (no roll) but pitch down, so their image x axes
    (``R[0]``) are all perpendicular to up while their image-up directions (``-R[1]``) lean
    towards the scene. Up is the direction most perpendicular to every x axis (the smallest
    eigenvector of sum x x^T), signed by the mean image-up; a weak pull towards the mean image-up
    decides when the x axes leave several directions free (one camera, or parallel cameras: then
    give ``up`` in the calibration). On the presets this is within 2.5 degrees of the calibrated
    up; the plain mean image-up is 6-10 degrees off.

    Returns:
      (3,) unit vector (numpy; host-side, for scene set-up).
    Raises:
      InputError when the cameras' image-up directions cancel out.
    """
    if rig.up is not None:
        return np.asarray(rig.up, dtype=np.float64)
    R = np.asarray(rig.R, dtype=np.float64)
    image_up = -R[:, 1, :].mean(axis=0)
    n = np.linalg.norm(image_up)
    if n < 1e-6:
        raise InputError("cannot infer the up direction: cameras disagree; give 'up'", field="up")
    image_up /= n
    x_axes = R[:, 0, :]  # (C, 3) image x axes in the world
    m = x_axes.T @ x_axes + 1e-3 * (np.eye(3) - np.outer(image_up, image_up))
    up = np.linalg.eigh(m)[1][:, 0]
    return up * np.sign(up @ image_up)
