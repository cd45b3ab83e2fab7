"""The error-separation calibration procedure (PHYSICS.md, "The error-separation procedure").

For now this module says *which poses* the procedure visits; the engine that drives a station
through them arrives with the procedures issue. ``compasscal simulate`` runs the same poses on an
ideal simulated table, so a simulated recording and a station's recording have the same steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physics.simulate import Pose

NAME = "calibrate"
VERSION = "1"


@dataclass(frozen=True)
class CalibrateParams:
    """Choices of the procedure, with defaults chosen for accuracy per second of table time.

    z_step_deg: azimuth step of the level rotation about z (a full turn).
    tilt_step_deg: step of the sweeps about y and x (full turns of the middle and inner axes).
    sweep_psi_deg: azimuth at which the y and x sweeps are made.
    samples: samples averaged at each pose.
    """

    z_step_deg: float = 45.0
    tilt_step_deg: float = 60.0
    sweep_psi_deg: float = 315.0
    samples: int = 70

    def __post_init__(self) -> None:
        for name in ("z_step_deg", "tilt_step_deg"):
            step = getattr(self, name)
            if not 0 < step <= 120:
                raise ValueError(f"{name}: must be in (0, 120] deg so a turn has at least three poses, got {step}")
        if self.samples < 1:
            raise ValueError(f"samples: must be at least 1, got {self.samples}")


def _turn(step_deg: float) -> np.ndarray:
    return np.arange(0.0, 360.0 - 1e-9, step_deg)


def calibration_poses(p: CalibrateParams = CalibrateParams()) -> list[Pose]:
    """Poses of the calibration: a level turn about z, then full turns about y and about x.

    The level turn (step ``rotate_z``) gives each horizontal axis its sinusoid and line and the
    accelerometer its reversal; the y and x sweeps let every axis see the field from -1 to +1 and
    the gravity vector turn through the body, which separates all of M, b, I, D and the base tilt.
    """
    poses = [Pose("rotate_z", float(psi), 0.0, 0.0, p.samples) for psi in _turn(p.z_step_deg)]
    poses += [Pose("sweep_y", p.sweep_psi_deg, float(th), 0.0, p.samples) for th in _turn(p.tilt_step_deg)[1:]]
    poses += [Pose("sweep_x", p.sweep_psi_deg, 0.0, float(ph), p.samples) for ph in _turn(p.tilt_step_deg)[1:]]
    return poses
