"""Rotations, the Earth field and gravity in the lab frame (PHYSICS.md, "Frames").

Lab frame L: z down along gravity, x at the turntable's azimuth zero mark, y = z x x.
Rotations are active and right-handed; angles at the public API are in degrees.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

#: Specific force measured by an accelerometer at rest, in the lab frame, in g (f = -g, z is down).
SPECIFIC_FORCE_L = np.array([0.0, 0.0, -1.0])


def _rot(axis: int, angle_deg: ArrayLike) -> np.ndarray:
    a = np.radians(np.asarray(angle_deg, dtype=float))
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def rot_x(angle_deg: ArrayLike) -> np.ndarray:
    """Active right-handed rotation about x; shape (..., 3, 3) for an array of angles."""
    return _rot(0, angle_deg)


def rot_y(angle_deg: ArrayLike) -> np.ndarray:
    """Active right-handed rotation about y; shape (..., 3, 3) for an array of angles."""
    return _rot(1, angle_deg)


def rot_z(angle_deg: ArrayLike) -> np.ndarray:
    """Active right-handed rotation about z; shape (..., 3, 3) for an array of angles."""
    return _rot(2, angle_deg)


def field_direction(inclination_deg: float, declination_deg: float) -> np.ndarray:
    """Unit Earth-field vector in the lab frame: [cos I cos D, cos I sin D, sin I]."""
    i, d = np.radians(inclination_deg), np.radians(declination_deg)
    return np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])


def field_angles(v: ArrayLike) -> tuple[float, float]:
    """Inverse of :func:`field_direction`: (inclination, declination) in degrees of any vector."""
    x, y, z = np.asarray(v, dtype=float)
    inc = np.degrees(np.arctan2(z, np.hypot(x, y)))
    dec = np.degrees(np.arctan2(y, x)) % 360.0
    return float(inc), float(dec)


def to_body(C_Lb: np.ndarray, v_L: ArrayLike) -> np.ndarray:
    """Express a lab vector in body coordinates for every attitude: C_Lb^T v_L, shape (N, 3)."""
    return np.einsum("nji,j->ni", np.atleast_3d(C_Lb).reshape(-1, 3, 3), np.asarray(v_L, float))


def yaw_pitch_roll(C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZYX Euler angles (deg) of C = Rz(yaw) Ry(pitch) Rx(roll); yaw in [0, 360)."""
    C = np.asarray(C).reshape(-1, 3, 3)
    yaw = np.degrees(np.arctan2(C[:, 1, 0], C[:, 0, 0])) % 360.0
    pitch = np.degrees(np.arcsin(np.clip(-C[:, 2, 0], -1.0, 1.0)))
    roll = np.degrees(np.arctan2(C[:, 2, 1], C[:, 2, 2]))
    return yaw, pitch, roll
