"""A fixed pinhole camera that frames a bounding box: the primary rays used
by the benchmarks (the same rays for every method)."""
from __future__ import annotations

import numpy as np

VIEW = np.array([0.55, -0.45, 0.70])     # direction from the box centre to the eye


def primary_rays(bbox, width: int, height: int | None = None, fov_deg: float = 38.0):
    """(origins, directions) as float32 (N, 3) arrays, row-major pixels,
    unit directions; the eye sits 2.2 half-diagonals from the box centre."""
    lo, hi = np.asarray(bbox[0], np.float64), np.asarray(bbox[1], np.float64)
    c, half = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    view = VIEW / np.linalg.norm(VIEW)
    return look_rays(c + 2.2 * half * view, -view, width, height, fov_deg)


def look_rays(eye, forward, width: int, height: int | None = None, fov_deg: float = 38.0):
    """Pinhole rays from ``eye`` looking along ``forward`` (z up), one
    through each pixel centre: float32 (N, 3) origins and unit directions,
    row-major pixels."""
    height = width if height is None else height
    fwd = np.asarray(forward, np.float64) / np.linalg.norm(forward)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    s = np.tan(np.radians(fov_deg) / 2)
    u = ((np.arange(width) + 0.5) / width * 2 - 1) * s * width / height
    v = (1 - (np.arange(height) + 0.5) / height * 2) * s
    U, V = np.meshgrid(u, v)
    d = fwd + U.reshape(-1, 1) * right + V.reshape(-1, 1) * up
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(np.asarray(eye, np.float64), d.shape)
    return np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32)
