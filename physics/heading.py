"""Tilt-compensated magnetic heading and heading error (PHYSICS.md, "Heading")."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from physics.frames import rot_x, rot_y, yaw_pitch_roll


def wrap180(angle_deg: ArrayLike) -> np.ndarray:
    """Wrap angles to [-180, 180)."""
    return (np.asarray(angle_deg, dtype=float) + 180.0) % 360.0 - 180.0


def pitch_roll(f_b: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll (deg) from specific force in body axes (g): theta = atan2(f_x, hypot(f_y, f_z)), phi = atan2(-f_y, -f_z)."""
    f = np.atleast_2d(np.asarray(f_b, dtype=float))
    pitch = np.degrees(np.arctan2(f[:, 0], np.hypot(f[:, 1], f[:, 2])))
    roll = np.degrees(np.arctan2(-f[:, 1], -f[:, 2]))
    return pitch, roll


def levelled_field(h_b: ArrayLike, f_b: ArrayLike) -> np.ndarray:
    """Field rotated into the local level frame: ``Ry(theta) Rx(phi) h_b`` (N, 3)."""
    pitch, roll = pitch_roll(f_b)
    h = np.atleast_2d(np.asarray(h_b, dtype=float))
    return np.einsum("nij,njk,nk->ni", rot_y(pitch), rot_x(roll), h)


def magnetic_heading(h_b: ArrayLike, f_b: ArrayLike) -> np.ndarray:
    """Tilt-compensated magnetic heading in [0, 360) deg: ``atan2(-h_y, h_x)`` of the levelled field."""
    h = levelled_field(h_b, f_b)
    return np.degrees(np.arctan2(-h[:, 1], h[:, 0])) % 360.0


def reference_heading(C_Lb: np.ndarray, declination_deg: float) -> np.ndarray:
    """True magnetic heading of the body: its ZYX yaw minus D (= psi_t - D for a level, ideal table)."""
    yaw, _, _ = yaw_pitch_roll(C_Lb)
    return (yaw - declination_deg) % 360.0


def heading_error(measured_deg: ArrayLike, reference_deg: ArrayLike) -> np.ndarray:
    """``wrap180(measured - reference)`` in degrees."""
    return wrap180(np.asarray(measured_deg) - np.asarray(reference_deg))


def error_summary(err_deg: ArrayLike) -> dict[str, float]:
    """Max absolute and RMS heading error, the two figures PHYSICS.md asks to report."""
    e = np.asarray(err_deg, dtype=float)
    return {"max": float(np.max(np.abs(e))), "rms": float(np.sqrt(np.mean(e * e)))}


def circular_mean_deg(angles_deg: ArrayLike) -> float:
    """Mean direction (deg, in [0, 360)) of a set of angles."""
    a = np.radians(np.asarray(angles_deg, dtype=float))
    return float(np.degrees(np.arctan2(np.sin(a).mean(), np.cos(a).mean())) % 360.0)
