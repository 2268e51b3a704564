"""Pinhole cameras on a sphere looking at the origin, and the per-pixel primary rays.

Conventions (those of TANGO's and Text2Mesh's code): y is up; a camera at azimuth ``a`` and
elevation ``e`` on a sphere of radius ``r`` sits at ``r * (cos e cos a, sin e, cos e sin a)`` and
looks at the origin. Camera-to-world matrices follow OpenGL: the camera looks along its -z axis,
+x is right and +y is up in the image. Pixel ``(row, col)`` of a ``W x W`` image has index
``row * W + col``, row 0 at the top; rays pass through pixel centres.
"""

from __future__ import annotations

import numpy as np

#: elevations are clamped this far from the poles, where look-at with a +y up vector is singular
POLE_MARGIN = 1e-2


def camera_positions(azimuth: np.ndarray, elevation: np.ndarray, radius: np.ndarray | float) -> np.ndarray:
    """Eye positions ``(V, 3)`` float64 for ``azimuth, elevation (V,)`` radians and ``radius``."""
    az = np.asarray(azimuth, np.float64)
    el = np.asarray(elevation, np.float64)
    r = np.asarray(radius, np.float64)
    return np.stack([r * np.cos(el) * np.cos(az), r * np.sin(el), r * np.cos(el) * np.sin(az)], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world matrices ``(V, 4, 4)`` float64 for eyes ``(V, 3)`` looking at ``target``.

    Valid for eyes not on the vertical line through the target (elevation within
    ``POLE_MARGIN`` of +-pi/2 is excluded by :func:`sample_views`).
    """
    eye = np.atleast_2d(np.asarray(eye, np.float64))
    target = np.zeros(3) if target is None else np.asarray(target, np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward, axis=-1, keepdims=True)
    right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    up = np.cross(right, forward)
    c2w = np.zeros((len(eye), 4, 4))
    c2w[:, :3, 0] = right
    c2w[:, :3, 1] = up
    c2w[:, :3, 2] = -forward
    c2w[:, :3, 3] = eye
    c2w[:, 3, 3] = 1.0
    return c2w


def sample_views(
    n: int,
    *,
    anchor_azimuth: float,
    anchor_elevation: float,
    std: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """TANGO's view pool: view 0 is the anchor; the others are Gaussian around it.

    Elevation ~ N(anchor_elevation, (pi/std)^2) and azimuth ~ N(anchor_azimuth, (2 pi/std)^2),
    as in TANGO's and Text2Mesh's samplers. Elevations are clamped to
    ``[-pi/2 + POLE_MARGIN, pi/2 - POLE_MARGIN]`` (a pole has no defined image "up").

    Returns ``azimuth (n,)``, ``elevation (n,)`` float64 radians.
    """
    az = anchor_azimuth + rng.normal(size=n) * (2.0 * np.pi / std)
    el = anchor_elevation + rng.normal(size=n) * (np.pi / std)
    az[0], el[0] = anchor_azimuth, anchor_elevation
    lim = np.pi / 2 - POLE_MARGIN
    return az, np.clip(el, -lim, lim)


def grid_views(azimuths: int, elevations_deg: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Fixed evaluation views: ``azimuths`` equally spaced azimuths times the given elevations.

    Returns ``azimuth (A*E,)``, ``elevation (A*E,)`` float64 radians, elevation-major order.
    """
    az = np.linspace(0.0, 2.0 * np.pi, azimuths, endpoint=False)
    el = np.deg2rad(np.asarray(elevations_deg, np.float64))
    ee, aa = np.meshgrid(el, az, indexing="ij")
    return aa.ravel(), ee.ravel()


def camera_space_directions(width: int, fov_deg: float) -> np.ndarray:
    """Unit ray directions in camera space through the ``width x width`` pixel centres.

    ``fov_deg`` is the full field of view (horizontal = vertical). Returns ``(W*W, 3)`` float64,
    row-major from the top-left pixel; every direction has negative z.
    """
    t = np.tan(np.deg2rad(fov_deg) / 2.0)
    c = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    x = np.broadcast_to(c[None, :] * t, (width, width))
    y = np.broadcast_to(-c[:, None] * t, (width, width))
    d = np.stack([x, y, -np.ones((width, width))], axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def world_rays(c2w: np.ndarray, cam_dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins ``(N, 3)`` (broadcast eye) and world directions ``(N, 3)`` for one camera ``(4, 4)``."""
    dirs = cam_dirs @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape)
    return origins, dirs
