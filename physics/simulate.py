"""A simulated station without hardware: the true world, poses of a procedure, and the recording
a unit would produce on it. Pure: randomness comes from the caller's generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import copy
import math
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import lfilter

from physics.effects import Effect
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
    #: the unit warms up after power-on: ``warmup_c`` degrees more, reached with time constant ``warmup_tau_s``
    warmup_c: float = 0.0
    warmup_tau_s: float = 300.0

    def temperature_at(self, t: ArrayLike) -> np.ndarray | float:
        """Temperature inside the unit (deg C) at run time ``t`` (s, from power-on); vectorised."""
        if isinstance(t, (float, int)):  # one live sample (the simulated station): no arrays
            return self.temperature_c + self.warmup_c * (1.0 - math.exp(-max(t, 0.0) / self.warmup_tau_s))
        t_arr = np.asarray(t, dtype=float)
        temp = self.temperature_c + self.warmup_c * (1.0 - np.exp(-np.maximum(t_arr, 0.0) / self.warmup_tau_s))
        return float(temp) if temp.ndim == 0 else temp

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
    #: approach the hold from this side: first go to psi_t - approach_deg, then to the pose (0: directly)
    approach_deg: float = 0.0


#: The encoder angle each Scan axis turns (psi about z, theta about y, phi about x).
SCAN_AXES = ("psi", "theta", "phi")


@dataclass(frozen=True)
class Scan:
    """Turn one axis from ``start_deg`` to ``stop_deg`` at ``speed_dps`` while sampling at the compass
    rate (the other axes hold the given angles). The move to the start is not sampled; each sample
    carries the encoder angle it was taken at."""

    step: str
    axis: str  # "psi" | "theta" | "phi"
    start_deg: float
    stop_deg: float
    speed_dps: float
    psi_t: float = 0.0
    theta_t: float = 0.0
    phi_t: float = 0.0

    def __post_init__(self) -> None:
        if self.axis not in SCAN_AXES:
            raise ValueError(f"axis: expected one of {', '.join(SCAN_AXES)}, got {self.axis!r}")
        if not self.speed_dps > 0:
            raise ValueError(f"speed_dps: must be > 0, got {self.speed_dps}")

    @property
    def index(self) -> int:
        """0, 1, 2 for psi, theta, phi."""
        return SCAN_AXES.index(self.axis)

    def at(self, angle: float) -> tuple[float, float, float]:
        """The three encoder angles with the scanned axis at ``angle``."""
        a = [self.psi_t, self.theta_t, self.phi_t]
        a[self.index] = angle
        return (a[0], a[1], a[2])

    @property
    def start_angles(self) -> tuple[float, float, float]:
        """Where the scan starts."""
        return self.at(self.start_deg)

    @property
    def stop_angles(self) -> tuple[float, float, float]:
        """Where the scan ends."""
        return self.at(self.stop_deg)


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
    t_all = np.round(np.concatenate(t), 6)  # to the microsecond: a written t reads 0.3, not 0.30000000000000004
    return Recording.from_arrays(
        t=t_all, step=np.array(steps, dtype=object),
        psi_t=ang[:, 0], theta_t=ang[:, 1], phi_t=ang[:, 2],
        mag=mag, acc=acc, temp_c=np.broadcast_to(world.temperature_at(t_all), t_all.shape), meta=header,
    )


# --------------------------------------------------------------------------------------------------
# Time-stepped simulation of a whole plan, with concealed effects (issue 6)
# --------------------------------------------------------------------------------------------------

#: Column of (psi_t, theta_t, phi_t) turned by each Scan axis.
AXIS_COLUMN = {"psi": 0, "theta": 1, "phi": 2}


def ar1_whiten(x: ArrayLike, t: ArrayLike, rate_hz: float, phi: float) -> np.ndarray:
    """Innovations of a unit-variance AR(1) process (coefficient ``phi`` per sample period at ``rate_hz``)
    observed at times ``t`` (rows of ``x``): ``(x_k - rho x_{k-1}) / sqrt(1 - rho^2)`` with
    ``rho = phi ** gap`` and ``gap`` the time since the previous row in sample periods.

    That is the exact whitening of a Markov process seen at a subset of its instants: consecutive
    samples use ``phi``, the first row after a long gap (a move between holds) is nearly a fresh start,
    and the first row of all is one.
    """
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    if phi == 0.0 or len(x) == 0:
        return x.copy()
    gap = np.maximum(np.diff(t) * rate_hz, 0.5)  # duplicate time stamps would make rho 1
    rho = np.r_[0.0, phi ** gap].reshape((-1,) + (1,) * (x.ndim - 1))
    prev = np.concatenate([np.zeros_like(x[:1]), x[:-1]])
    return (x - rho * prev) / np.sqrt(1.0 - rho * rho)


@dataclass(frozen=True)
class Noise:
    """Magnetometer noise of a simulated run: per-axis marginal sigma (LSB), AR(1) coefficient ``phi``
    per sample (0: white), and whether the output is quantised to 1 LSB."""

    sigma_lsb: float | tuple[float, float, float] = 3.0
    phi: float = 0.0
    quantized: bool = True

    def __post_init__(self) -> None:
        if not -1.0 < self.phi < 1.0:
            raise ValueError(f"phi: must be in (-1, 1), got {self.phi}")
        if np.any(self.sigma < 0):
            raise ValueError(f"sigma_lsb: must not be negative, got {self.sigma_lsb}")

    @property
    def sigma(self) -> np.ndarray:
        """Marginal sigma per axis (3,)."""
        return np.broadcast_to(np.asarray(self.sigma_lsb, dtype=float), (3,)).copy()

    def sample(self, n: int, rng: np.random.Generator, segments: ArrayLike | None = None) -> np.ndarray:
        """(n, 3) noise, stationary from its first row: marginal sd ``sigma``, lag-1 correlation ``phi``.

        ``segments``: row indices where the process restarts from its stationary distribution; None
        runs one continuous process (a compass sampling all the time).
        """
        z = rng.standard_normal((n, 3))
        if self.phi == 0.0 or n == 0:
            return z * self.sigma
        cuts = [] if segments is None else [int(i) for i in np.ravel(segments) if 0 < int(i) < n]
        bounds = sorted(set([0, *cuts])) + [n]
        out = np.empty_like(z)
        for a, b in zip(bounds[:-1], bounds[1:]):
            u = z[a:b] * math.sqrt(1.0 - self.phi ** 2)
            u[0] = z[a]  # start in the stationary distribution
            out[a:b] = lfilter([1.0], [1.0, -self.phi], u, axis=0)
        return out * self.sigma

    def whiten(self, e: ArrayLike, t: ArrayLike, rate_hz: float) -> np.ndarray:
        """Rows of ``e`` (N, 3) made independent with unit variance under this noise (see :func:`ar1_whiten`)."""
        return ar1_whiten(e, t, rate_hz, self.phi) / self.sigma


class _Profile:
    """The table's motion as segments: segment k starts at ``t0[k]`` and moves from ``a0[k]`` to
    ``a1[k]`` in ``T[k]`` seconds, the longest axis along a trapezoid (acceleration ``acc``, peak speed
    ``vp`` reached after ``ta``) and the others scaled to it, so all axes arrive together. Between
    segments the table stands still at the last segment's end."""

    def __init__(self, start: np.ndarray) -> None:
        self.rows: list[tuple[float, float, float, float, float, float, np.ndarray, np.ndarray]] = []
        self.add(0.0, start, start, 1.0, 1.0)  # the start position, also before t = 0

    def add(self, t0: float, a0: np.ndarray, a1: np.ndarray, speed: float, accel: float) -> float:
        """Append a move starting at ``t0``; returns its duration (that of physics.table.move_seconds)."""
        D = float(np.max(np.abs(a1 - a0)))
        if D == 0.0:
            if not self.rows:
                self.rows.append((t0, 0.0, 0.0, accel, 0.0, 0.0, a0.copy(), a1.copy()))
            return 0.0
        ta = min(speed / accel, math.sqrt(D / accel))
        vp = accel * ta
        T = D / vp + ta
        self.rows.append((t0, T, D, accel, ta, vp, a0.copy(), a1.copy()))
        return T

    def angles(self, times: ArrayLike) -> np.ndarray:
        """True encoder angles (N, 3) (psi, theta, phi) at ``times``."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        t0, T, D, a, ta, vp = (np.array([r[i] for r in self.rows]) for i in range(6))
        a0 = np.array([r[6] for r in self.rows])
        a1 = np.array([r[7] for r in self.rows])
        k = np.clip(np.searchsorted(t0, times, side="right") - 1, 0, len(t0) - 1)
        T, D, a, ta, vp = T[k], D[k], a[k], ta[k], vp[k]
        tau = np.clip(times - t0[k], 0.0, T)
        p = np.where(tau < ta, 0.5 * a * tau ** 2,
                     np.where(tau <= T - ta, 0.5 * vp * ta + vp * (tau - ta), D - 0.5 * a * (T - tau) ** 2))
        frac = np.where(D > 0, p / np.where(D > 0, D, 1.0), 0.0)
        return a0[k] + frac[:, None] * (a1[k] - a0[k])


@dataclass
class Timeline:
    """A plan laid out in time: the table's motion and which compass samples are kept.

    The compass samples at ``rate_hz`` all the time (sample i at ``i / rate_hz``); the recording keeps
    those of the holds and the scans.
    """

    profile: _Profile
    n: int  # compass samples over the whole run
    keep: np.ndarray  # kept sample indices, increasing
    step: np.ndarray  # their step labels
    rate_hz: float
    duration_s: float

    def angles(self, times: ArrayLike) -> np.ndarray:
        """True mechanism angles (N, 3) at ``times`` (s)."""
        return self.profile.angles(times)


def plan_timeline(plan: Sequence[Pose | Scan], motion: Motion = Motion(),
                  start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Timeline:
    """Lay out ``plan`` in time under ``motion``.

    A Pose: (via ``psi_t - approach_deg`` when ``approach_deg`` is set) move to the pose, settle
    ``settle_s``, then keep the next ``samples`` compass samples. A Scan: move to its start, settle,
    then turn its axis to the stop at ``speed_dps`` (accelerating at ``max_accel_dps2``) keeping every
    sample taken from the start of the turn to its end, ramps included. Moves are simultaneous on
    all axes (the longest axis's trapezoid, the others scaled to it).
    """
    rate = motion.sample_rate_hz
    here = np.asarray(start, dtype=float)
    prof = _Profile(here)
    t = 0.0
    keep: list[np.ndarray] = []
    steps: list[str] = []

    def go(to: np.ndarray, speed: float = motion.max_speed_dps) -> None:
        nonlocal t, here
        t += prof.add(t, here, to, speed, motion.max_accel_dps2)
        here = to

    for item in plan:
        if isinstance(item, Scan):
            base = np.array([item.psi_t, item.theta_t, item.phi_t], dtype=float)
            a_start, a_stop = base.copy(), base.copy()
            a_start[AXIS_COLUMN[item.axis]] = item.start_deg
            a_stop[AXIS_COLUMN[item.axis]] = item.stop_deg
            go(a_start)
            t += motion.settle_s
            t_begin = t
            go(a_stop, item.speed_dps)
            idx = np.arange(math.ceil(t_begin * rate - 1e-9), math.floor(t * rate + 1e-9) + 1)
        elif isinstance(item, Pose):
            target = np.array([item.psi_t, item.theta_t, item.phi_t], dtype=float)
            if item.approach_deg:
                go(target - np.array([item.approach_deg, 0.0, 0.0]))
            go(target)
            t += motion.settle_s
            i0 = math.ceil(t * rate - 1e-9)  # the compass's next sample after settling
            idx = np.arange(i0, i0 + item.samples)
            t = (i0 + item.samples) / rate
        else:
            raise TypeError(f"plan: expected Pose or Scan items, got {type(item).__name__}")
        keep.append(idx)
        steps += [item.step] * len(idx)
    kept = np.concatenate(keep).astype(int) if keep else np.zeros(0, dtype=int)
    n = max(math.floor(t * rate + 1e-9) + 1, int(kept.max()) + 1 if kept.size else 0)
    return Timeline(prof, n, kept, np.array(steps, dtype=object), rate, t)


def _overrides(e: Effect, stage: str) -> bool:
    """Whether effect ``e`` acts at ``stage`` (the base class's stages do nothing)."""
    return getattr(type(e), stage, None) is not getattr(Effect, stage)


def simulate_timeline(
    unit: Unit,
    plan: Sequence[Pose | Scan],
    world: World = World(),
    motion: Motion = Motion(),
    effects: Sequence[Effect] = (),
    noise: Noise | None = None,
    rng: np.random.Generator | None = None,
    meta: dict[str, str] | None = None,
) -> tuple[Recording, Recording]:
    """Run ``plan`` in simulated time with ``effects`` concealed; returns (recording, clean recording).

    The compass samples at ``motion.sample_rate_hz`` all the time, moving or not, and every sample goes
    through the effects in time order as drivers/sim/world.SimWorld.read does: the table geometry once
    (``geometry``), then per sample ``sample_time`` -> true angles at that instant -> C_LP ->
    ``h_b``, ``f_b`` -> ``body_field`` -> linear magnetometer -> ``mag_raw`` (temperature
    ``world.temperature_at(t)``). Only hold and scan samples are recorded, with the true mechanism
    angles at the sample instant (rounded to the encoder step in the recording).

    The clean recording has the effects but no noise and no quantisation, and its angles are the true
    mechanism angles unrounded (the nominal model with them fits an effect-free clean recording
    exactly). ``noise`` defaults to the unit's own white noise; the accelerometer gets its white noise.
    """
    rng = rng if rng is not None else np.random.default_rng()
    noise = noise if noise is not None else Noise(unit.mag.noise_lsb, 0.0, unit.mag.quantized)
    tl = plan_timeline(plan, motion)
    effects = copy.deepcopy(list(effects))  # fresh state (hysteresis), and the caller's objects untouched
    geometry = world.geometry
    for e in effects:
        geometry = e.geometry(geometry)
    tg = np.arange(tl.n) / tl.rate_hz
    t_list = tg.tolist()

    ts = tg
    lagging = [e for e in effects if _overrides(e, "sample_time")]
    if lagging:
        ts_list = []
        for t in t_list:
            for e in lagging:
                t = e.sample_time(t, 0)
            ts_list.append(t)
        ts = np.array(ts_list)
    ang = tl.angles(ts)
    C = platform_attitude(ang[:, 0], ang[:, 1], ang[:, 2], geometry)
    h = np.einsum("nji,j->ni", C, world.field_L)
    f = np.einsum("nji,j->ni", C, SPECIFIC_FORCE_L)

    # Python loops only for the stages some effect acts on (they may keep state sample to sample)
    body = [e for e in effects if _overrides(e, "body_field")]
    if body:
        for i, t in enumerate(t_list):
            hb = h[i].copy()
            for e in body:
                hb = e.body_field(t, 0, ang[i], C[i], hb)
            h[i] = hb
    temp = np.asarray(world.temperature_at(tg), dtype=float) * np.ones(tl.n)
    mag = h @ unit.mag.M.T + unit.mag.bias
    raw = [e for e in effects if _overrides(e, "mag_raw")]
    if raw:
        temp_list = temp.tolist()
        for i, t in enumerate(t_list):
            m = mag[i].copy()
            for e in raw:
                m = e.mag_raw(t, 0, m, temp_list[i])
            mag[i] = m
    acc = f @ unit.acc.M.T + unit.acc.bias if unit.acc is not None else None

    k = tl.keep
    true_ang = tl.angles(tg[k])
    enc = np.round(true_ang / ENCODER_STEP_DEG) * ENCODER_STEP_DEG
    noisy_mag = mag[k] + noise.sample(tl.n, rng)[k]
    if noise.quantized:
        noisy_mag = np.round(noisy_mag)
    noisy_acc = None
    if acc is not None and unit.acc is not None:
        noisy_acc = acc[k] + (rng.normal(0.0, unit.acc.noise_lsb, (len(k), 3)) if unit.acc.noise_lsb > 0 else 0.0)
        if unit.acc.quantized:
            noisy_acc = np.round(noisy_acc)
    header = {"serial": unit.serial, "station": "simulated", "model": unit.model,
              "sample_rate_hz": f"{motion.sample_rate_hz:g}"}
    header.update(meta or {})
    rec = Recording.from_arrays(tg[k], tl.step, enc[:, 0], enc[:, 1], enc[:, 2], noisy_mag, noisy_acc, temp[k], header)
    clean = Recording.from_arrays(tg[k], tl.step, true_ang[:, 0], true_ang[:, 1], true_ang[:, 2], mag[k],
                                  None if acc is None else acc[k], temp[k], header)
    return rec, clean


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


#: Kinds of bad readings :func:`garble` makes: random int16 triples, a brown-out's zeros, one bit flipped.
GARBLE_KINDS = ("int16", "zeros", "bitflip")
#: The bits a ``bitflip`` flips: one axis off by 64 LSB (20 sigma of 3-LSB noise, under 5 % of most units'
#: k) to 16384 (a reading of the wrong sign); lower bits are lost in the noise.
BITFLIP_BITS = (6, 15)


def flip_bit(counts: ArrayLike, bit: ArrayLike) -> np.ndarray:
    """int16 ``counts`` with bit ``bit`` flipped in their two's complement (each count its own bit)."""
    flipped = (np.asarray(counts, dtype=np.int64) & 0xFFFF) ^ (1 << np.asarray(bit, dtype=np.int64))
    return np.where(flipped >= 0x8000, flipped - 0x10000, flipped)


def garble(x: np.ndarray, fraction: float, kind: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A copy of readings ``x`` (N, 3, counts) with ``fraction`` of its rows (at least one) garbled as a
    compass that passes its checksum can garble them, and the garbled rows' indices: replaced by random
    int16 triples (``int16``) or zeros (``zeros``), or one axis with one bit of its int16 count flipped
    (``bitflip``, :data:`BITFLIP_BITS`)."""
    if kind not in GARBLE_KINDS:
        raise ValueError(f"kind: expected one of {', '.join(GARBLE_KINDS)}, got {kind!r}")
    bad = rng.choice(len(x), max(1, round(fraction * len(x))), replace=False)
    out = np.array(x, dtype=float)
    if kind == "bitflip":
        axis = rng.integers(0, 3, bad.size)
        out[bad, axis] = flip_bit(np.round(out[bad, axis]), rng.integers(*BITFLIP_BITS, bad.size))
    else:
        out[bad] = rng.integers(-32768, 32768, (bad.size, 3)) if kind == "int16" else 0.0
    return out, bad
