"""A simulated station without hardware: the true world, poses of a procedure, and the recording
a unit would produce on it. Pure: randomness comes from the caller's generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from physics.frames import SPECIFIC_FORCE_L, field_direction, to_body
from physics.recording import Recording
from physics.sensor import LinearSensor, Unit
from physics.table import IDEAL_TABLE, Motion, TableGeometry, move_seconds, platform_attitude

#: Encoder resolution of the table (PHYSICS.md).
ENCODER_STEP_DEG = 0.001


@dataclass(frozen=True)
class World:
    """What the station really is: the lab field and the table's true geometry."""

    inclination_deg: float = 55.0
    declination_deg: float = 23.0
    geometry: TableGeometry = IDEAL_TABLE
    temperature_c: float = 23.0

    @property
    def field_L(self) -> np.ndarray:
        """Unit field vector in the lab frame."""
        return field_direction(self.inclination_deg, self.declination_deg)

    def body_vectors(self, psi_t: np.ndarray, theta_t: np.ndarray, phi_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True (h_b, f_b) seen by a unit on the platform at these encoder angles."""
        C = platform_attitude(psi_t, theta_t, phi_t, self.geometry)
        return to_body(C, self.field_L), to_body(C, SPECIFIC_FORCE_L)


@dataclass(frozen=True)
class Pose:
    """One hold of a procedure: move to the encoder angles, settle, take ``samples`` samples."""

    step: str
    psi_t: float
    theta_t: float
    phi_t: float
    samples: int = 20


@dataclass
class PlanCost:
    """Table time of a list of poses under a station's motion limits."""

    positions: int
    move_s: float
    settle_s: float
    sample_s: float
    moves: list[float] = field(default_factory=list)

    @property
    def total_s(self) -> float:
        """Total table time in seconds."""
        return self.move_s + self.settle_s + self.sample_s


def plan_cost(poses: list[Pose], motion: Motion = Motion(), start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> PlanCost:
    """Seconds of table time to run ``poses`` from ``start`` (moves, settles and sampling)."""
    here = np.asarray(start, dtype=float)
    moves = []
    for p in poses:
        there = np.array([p.psi_t, p.theta_t, p.phi_t])
        moves.append(move_seconds(there - here, motion))
        here = there
    return PlanCost(
        positions=len(poses),
        move_s=float(sum(moves)),
        settle_s=motion.settle_s * len(poses),
        sample_s=sum(p.samples for p in poses) / motion.sample_rate_hz,
        moves=moves,
    )


def true_readings(unit: Unit, world: World, psi_t: np.ndarray, theta_t: np.ndarray, phi_t: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Noise-free raw (mag, acc) of ``unit`` at these encoder angles."""
    h_b, f_b = world.body_vectors(psi_t, theta_t, phi_t)
    mag = unit.mag.measure(h_b)
    acc = unit.acc.measure(f_b) if unit.acc is not None else None
    return mag, acc


def simulate_recording(
    unit: Unit,
    poses: list[Pose],
    world: World = World(),
    motion: Motion = Motion(),
    rng: np.random.Generator | None = None,
    meta: dict[str, str] | None = None,
) -> Recording:
    """The recording ``unit`` produces when a station runs ``poses`` (noise from ``rng``).

    Times follow the motion profile: move, settle, then samples at the compass rate. Encoder angles
    are the commanded ones rounded to the encoder resolution, as a real table reports them.
    """
    rng = rng if rng is not None else np.random.default_rng()
    cost = plan_cost(poses, motion)
    t, steps, angles = [], [], []
    clock = 0.0
    for pose, move_s in zip(poses, cost.moves):
        clock += move_s + motion.settle_s
        n = pose.samples
        t.append(clock + np.arange(n) / motion.sample_rate_hz)
        clock += n / motion.sample_rate_hz
        steps += [pose.step] * n
        angles.append(np.tile([pose.psi_t, pose.theta_t, pose.phi_t], (n, 1)))
    ang = np.round(np.vstack(angles) / ENCODER_STEP_DEG) * ENCODER_STEP_DEG
    h_b, f_b = world.body_vectors(ang[:, 0], ang[:, 1], ang[:, 2])
    mag = unit.mag.measure(h_b, rng)
    acc = unit.acc.measure(f_b, rng) if unit.acc is not None else None
    header = {"serial": unit.serial, "station": "simulated", "model": unit.model,
              "sample_rate_hz": f"{motion.sample_rate_hz:g}"}
    header.update(meta or {})
    return Recording.from_arrays(
        t=np.concatenate(t), step=np.array(steps, dtype=object),
        psi_t=ang[:, 0], theta_t=ang[:, 1], phi_t=ang[:, 2],
        mag=mag, acc=acc, temp_c=np.full(len(ang), world.temperature_c), meta=header,
    )


def truth_json(unit: Unit, world: World) -> dict[str, object]:
    """The true parameters of a simulated unit and its world (the ``.truth.json`` format), to score a
    calibration against."""
    def sensor(s: LinearSensor | None) -> dict[str, object] | None:
        if s is None:
            return None
        return {"M_o": s.M_o.tolist(), "k": s.k.tolist(), "bias": s.bias.tolist(),
                "angles_deg": s.angles_deg.tolist(), "noise_lsb": s.noise_lsb}
    g = world.geometry
    return {"serial": unit.serial, "model": unit.model, "magnetometer": sensor(unit.mag),
            "accelerometer": sensor(unit.acc),
            "field": {"inclination_deg": world.inclination_deg, "declination_deg": world.declination_deg},
            "base_tilt_deg": list(g.base_tilt_deg), "nonperp_deg": list(g.nonperp_deg),
            "encoder_zero_deg": list(g.encoder_zero_deg)}


def truth_from_json(d: dict[str, Any]) -> tuple[Unit, World]:
    """Inverse of :func:`truth_json` (files written before the table terms existed read as ideal tables)."""
    def sensor(s: dict[str, Any] | None) -> LinearSensor | None:
        if s is None:
            return None
        return LinearSensor(np.array(s["M_o"]), np.array(s["k"]), np.array(s["bias"]), noise_lsb=float(s.get("noise_lsb", 0.0)))
    mag = sensor(d["magnetometer"])
    assert mag is not None, "truth without a magnetometer"
    geometry = TableGeometry(base_tilt_deg=tuple(d.get("base_tilt_deg", (0.0, 0.0))),  # type: ignore[arg-type]
                             nonperp_deg=tuple(d.get("nonperp_deg", (0.0, 0.0))),  # type: ignore[arg-type]
                             encoder_zero_deg=tuple(d.get("encoder_zero_deg", (0.0, 0.0, 0.0))))  # type: ignore[arg-type]
    world = World(d["field"]["inclination_deg"], d["field"]["declination_deg"], geometry)
    return Unit(str(d.get("serial")), mag, sensor(d.get("accelerometer")), model=str(d.get("model", "simulated"))), world
