"""The three-axis turntable: geometry, platform attitude from encoder angles, and motion timing.

Nested gimbals (PHYSICS.md): outer axis z (psi_t), middle axis y (theta_t), inner axis x (phi_t):
``C_LP = C_LB Rz(psi_t) Ry(theta_t) Rx(phi_t)`` for an ideal table. A real table adds a base tilt
``C_LB``, small axis non-perpendicularities and encoder zero offsets; all are parameters here and all
are zero for the ideal table the nominal model assumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from physics.frames import rot_x, rot_y, rot_z


@dataclass(frozen=True)
class TableGeometry:
    """Small imperfections of a real table; the default is the ideal table.

    base_tilt_deg: (about x, about y); the base frame is ``C_LB = Ry(about_y) Rx(about_x)``.
    nonperp_deg: (middle axis y tilted about the outer frame's x, inner axis x tilted about the
        middle frame's z), i.e. the departures of the z-y and y-x axis pairs from 90 deg.
    encoder_zero_deg: (z, y, x) true gimbal angle when the encoder reads zero; the true angle is
        ``reading + encoder_zero``.
    """

    base_tilt_deg: tuple[float, float] = (0.0, 0.0)
    nonperp_deg: tuple[float, float] = (0.0, 0.0)
    encoder_zero_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def is_ideal(self) -> bool:
        """True when every imperfection is zero."""
        return not any(self.base_tilt_deg) and not any(self.nonperp_deg) and not any(self.encoder_zero_deg)


IDEAL_TABLE = TableGeometry()


def base_rotation(base_tilt_deg: ArrayLike) -> np.ndarray:
    """C_LB for a base tilted by (about x, about y) degrees."""
    tx, ty = np.asarray(base_tilt_deg, dtype=float)
    return rot_y(ty) @ rot_x(tx)


def platform_attitude(
    psi_t: ArrayLike, theta_t: ArrayLike, phi_t: ArrayLike, geometry: TableGeometry = IDEAL_TABLE
) -> np.ndarray:
    """C_LP (N, 3, 3) for encoder angles in degrees. The body frame is the platform's: C_Lb = C_LP."""
    psi, theta, phi = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (psi_t, theta_t, phi_t))
    z0, y0, x0 = geometry.encoder_zero_deg
    C = rot_z(psi + z0) @ rot_x(geometry.nonperp_deg[0]) @ rot_y(theta + y0)
    C = C @ rot_z(geometry.nonperp_deg[1]) @ rot_x(phi + x0)
    return base_rotation(geometry.base_tilt_deg) @ C


#: A drive's settling into position after a move (the simulated servo's; a station's own is its
#: ``Station.settle_s``): nominal seconds for plans and progress, never for control.
DRIVE_SETTLE_S = 0.2
#: The calibration's own wait after each move is in position (``CalibrateParams.settle_s``).
PROCEDURE_SETTLE_S = 0.1


@dataclass(frozen=True)
class Motion:
    """Axis motion limits and timing of a station (defaults: the issue's realistic station).

    ``settle_s`` is the whole wait at each pose before its samples: offline plans (physics.simulate)
    have no separate settle steps, so by default the drive's settling plus the calibration's own
    wait; the engine, which runs those waits as steps, passes the drive's alone."""

    max_speed_dps: float = 30.0
    max_accel_dps2: float = 60.0
    settle_s: float = DRIVE_SETTLE_S + PROCEDURE_SETTLE_S
    sample_rate_hz: float = 20.0


def move_seconds(delta_deg: ArrayLike, motion: Motion = Motion()) -> float:
    """Time of a simultaneous move of all axes by ``delta_deg`` with trapezoidal profiles.

    Each axis accelerates at the limit up to the speed limit (or a triangle when the move is short);
    the axes move together, so the move lasts as long as its longest axis. Settling is not included.
    """
    d = np.abs(np.atleast_1d(np.asarray(delta_deg, dtype=float)))
    v, a = motion.max_speed_dps, motion.max_accel_dps2
    ramp = v * v / a  # distance covered by accelerating to v and braking from it
    t = np.where(d >= ramp, d / v + v / a, 2.0 * np.sqrt(d / a))
    return float(t.max()) if t.size else 0.0
