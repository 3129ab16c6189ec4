"""Pinhole cameras: look-at, OpenGL-style perspective, and the paper's view sphere.

Conventions (glTF): right-handed world, y up; a camera looks down its local -z axis with +y up
and +x to the right. ``proj`` is the OpenGL perspective matrix (clip = proj @ cam, NDC in
[-1, 1]^3). Screen space: pixel ``(row i, col j)`` has its centre at ``x = j + 0.5``,
``y = i + 0.5``, row 0 at the top (NDC y = +1).

The paper's cameras sit on a sphere around a mesh *normalised to unit size*: centred on its
bounding-box centre and scaled so the largest bounding-box extent is 1
(:func:`normalize_transform`). Instead of moving the mesh, pass ``frame=(center, scale)`` to
the camera functions: the normalisation is folded into ``world_to_cam`` (a similarity), so
G-buffer positions stay in the asset's own world space and normals are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

NEAR = 0.05  # near plane in normalised (unit-size mesh) units
FAR = 100.0


@dataclass
class Camera:
    """One view. ``eye`` (3,) world position; ``world_to_cam`` (4, 4) (may include the uniform
    scale of the mesh normalisation); ``proj`` (4, 4) OpenGL perspective; ``resolution``
    (H, W); ``fov_deg`` vertical field of view. Matrices are float64 numpy arrays."""

    eye: np.ndarray
    world_to_cam: np.ndarray
    proj: np.ndarray
    resolution: tuple[int, int]
    fov_deg: float

    @property
    def full_proj(self) -> np.ndarray:
        """(4, 4) world -> clip."""
        return self.proj @ self.world_to_cam


def perspective(fov_deg: float, aspect: float, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """(4, 4) OpenGL perspective; ``fov_deg`` is vertical, ``aspect`` = W / H."""
    if not (0.0 < fov_deg < 180.0):
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    f = 1.0 / math.tan(math.radians(fov_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def look_at_matrix(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) world -> camera for a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    fwd = target - eye
    n = np.linalg.norm(fwd)
    if n == 0.0:
        raise ValueError("camera eye and target coincide")
    fwd /= n
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight up/down: pick another up
        right = np.cross(fwd, np.array([0.0, 0.0, -1.0 if fwd[1] > 0 else 1.0]))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = right, true_up, -fwd
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def _frame_matrix(frame: tuple[np.ndarray, float] | None) -> np.ndarray:
    """(4, 4) world -> normalised: p' = (p - center) * scale."""
    m = np.eye(4)
    if frame is not None:
        center, scale = frame
        center = np.asarray(center, dtype=np.float64).reshape(3)
        m[:3, :3] *= float(scale)
        m[:3, 3] = -float(scale) * center
    return m


def look_at(
    eye,
    target=(0.0, 0.0, 0.0),
    up=(0.0, 1.0, 0.0),
    fov_deg: float = 45.0,
    resolution: tuple[int, int] = (512, 512),
    frame: tuple[np.ndarray, float] | None = None,
) -> Camera:
    """A camera at ``eye`` looking at ``target``, both given in the normalised frame when
    ``frame=(center, scale)`` is set (world = normalised / scale + center)."""
    h, w = int(resolution[0]), int(resolution[1])
    if h <= 0 or w <= 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    view = look_at_matrix(eye, target, up) @ _frame_matrix(frame)
    eye_n = np.asarray(eye, dtype=np.float64)
    if frame is not None:
        eye_w = eye_n / float(frame[1]) + np.asarray(frame[0], dtype=np.float64).reshape(3)
    else:
        eye_w = eye_n.copy()
    return Camera(
        eye=eye_w,
        world_to_cam=view,
        proj=perspective(fov_deg, w / h),
        resolution=(h, w),
        fov_deg=float(fov_deg),
    )


def sphere_direction(elev_deg: float, azim_deg: float) -> np.ndarray:
    """(3,) unit vector at elevation (from the xz plane, +y up) and azimuth (from +z toward
    +x)."""
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def orbit_cameras(
    n_elev: int,
    n_azim: int,
    distance: float,
    fov_deg: float,
    resolution: int | tuple[int, int],
    elev_range_deg: tuple[float, float] = (-60.0, 60.0),
    azim_offset_deg: float = 0.0,
    frame: tuple[np.ndarray, float] | None = None,
) -> list[Camera]:
    """``n_elev * n_azim`` cameras looking at the origin from ``distance``: elevations evenly
    spaced over ``elev_range_deg`` (inclusive; the middle of it when ``n_elev == 1``),
    azimuths ``azim_offset_deg + 360 k / n_azim``. Ordered elevation-major."""
    if n_elev <= 0 or n_azim <= 0:
        raise ValueError("n_elev and n_azim must be positive")
    if distance <= 0:
        raise ValueError("distance must be positive")
    res = (
        (resolution, resolution) if isinstance(resolution, int) else (resolution[0], resolution[1])
    )
    lo, hi = elev_range_deg
    elevs = np.linspace(lo, hi, n_elev) if n_elev > 1 else np.array([(lo + hi) / 2.0])
    cams = []
    for e in elevs:
        for k in range(n_azim):
            a = azim_offset_deg + 360.0 * k / n_azim
            eye = distance * sphere_direction(float(e), a)
            cams.append(look_at(eye, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov_deg, res, frame))
    return cams


PAPER_DISTANCE = 3.25
PAPER_FOV_DEG = 10.0


def paper_train_cameras(
    resolution: int | tuple[int, int], frame: tuple[np.ndarray, float] | None = None
) -> list[Camera]:
    """The paper's 750 training views: 15 elevations in [-60, 60] x 50 azimuths, distance
    3.25, FoV 10 degrees, around the unit-size mesh."""
    return orbit_cameras(
        15, 50, PAPER_DISTANCE, PAPER_FOV_DEG, resolution, (-60.0, 60.0), 0.0, frame
    )


def paper_eval_cameras(
    resolution: int | tuple[int, int], frame: tuple[np.ndarray, float] | None = None
) -> list[Camera]:
    """The paper's 240 evaluation views: 6 elevations in [-50, 50] x 40 azimuths offset by
    4.5 degrees. Training elevations are multiples of 120/14 = 8.57 degrees from -60, these
    are multiples of 20 from -50, and training azimuths are multiples of 7.2, these 4.5 + 9k:
    no evaluation camera coincides with a training camera."""
    return orbit_cameras(
        6, 40, PAPER_DISTANCE, PAPER_FOV_DEG, resolution, (-50.0, 50.0), 4.5, frame
    )


def normalize_transform(v_pos: torch.Tensor | np.ndarray) -> tuple[np.ndarray, float]:
    """``(center (3,), scale)`` so that ``(v_pos - center) * scale`` is centred on its
    bounding-box centre with the largest bounding-box extent equal to 1. Non-finite
    positions are ignored; an empty or point-like mesh gets scale 1."""
    p = v_pos.detach().cpu().double().numpy() if isinstance(v_pos, torch.Tensor) else v_pos
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if p.shape[0] == 0:
        return np.zeros(3), 1.0
    lo, hi = p.min(axis=0), p.max(axis=0)
    extent = float((hi - lo).max())
    scale = 1.0 / extent if extent > 0.0 else 1.0
    return (lo + hi) / 2.0, scale
