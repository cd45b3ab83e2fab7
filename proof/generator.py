"""The blind proof's generator: recordings with concealed effects, each sized by its non-centrality.

Two kinds of case share everything but the effect drawn:

- **catalogue** cases (:func:`make_case`, issue 6): one effect of ``physics.effects.CATALOGUE`` (or a
  pair) concealed with the catalogue's own concealment classes, or none (a null), on the characterize
  plan with the full spread of units, fields, warm-ups and noise (:func:`draw_null`);
- **open-world** cases (:func:`make_open_case`, issue 12): physics no catalogue entry names
  (proof.concealments: offsets present in time windows in each frame, gain following temperature,
  slowly drifting misalignment, intermittent interference), on the ordinary calibration plan
  (:func:`ordinary_plan`) with 3 LSB noise, each with the truth of its frame, form, input and windows,
  and the frames the recording cannot tell from the true one (:func:`equivalent_frames`).

The generator is a separate code path from the analyser on purpose: it uses only the forward side
(physics.simulate.simulate_timeline with the concealment classes, random units from physics.sensor)
and its own nominal fit to set effect sizes. It never imports physics.discrepancy; only the runner
does, to analyse.

Effect size is the **non-centrality** ``lambda`` of the effect in the recording::

    lambda = min over (M, b, v) of  || W ( c_E - (M R(alpha)^T v + b) ) ||^2

where ``c_E`` (N x 3) is the noise-free, unquantised magnetometer output with the effect concealed,
``R(alpha)`` the nominal (ideal-table, level-base) attitudes at the true mechanism angles of each
row, ``M, b, v`` the nominal model's matrix, bias and base-frame field direction (unit vector), and
``W`` the whitening of the true noise: per axis, ``(e_k - rho e_{k-1}) / (sigma sqrt(1 - rho^2))``
along the recording's rows with ``rho = phi ** gap`` (gap in sample periods since the previous row:
``phi`` within a hold or scan, nearly 0 after a move, the first row ``e / sigma``).

Because the effect-free clean recording is exactly nominal at the true angles, this is
``|| W (d - P d) ||^2`` with ``d`` the effect's contribution and ``P`` the (generalised least-squares)
projection onto what the nominal model absorbs, to first order: the expected increase of the
whitened residual sum of squares that the effect causes, i.e. the non-centrality of the likelihood
ratio test of the nominal model against the truth. It uses the whitened fit rather than
errorsep.joint_magnetometer's, which weights each axis by its own residual (meaningless on
noise-free data) and ignores the noise colour; the whitened fit gives the smallest, i.e. the most
demanding, lambda. Table angles are recorded rounded to the encoder step (0.001 deg); that
rounding alone makes a small misfit of the nominal model, reported per case as ``nc_floor`` (not
counted in lambda).

Each effect's magnitude is scaled (parameters times ``sqrt(target / lambda)``, re-measured, repeated
until within 10 %) so that lambda hits a target drawn log-uniformly in [3, 300]; the achieved value is
recorded. In a pair, each effect is set to its own target alone (log-uniform in [25, 300], see
:data:`PAIR_NC_RANGE`). Catalogue and open-world effects go through the same sizing
(:func:`_conceal`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import least_squares

from physics import errorsep as es
from physics.effects import CONCEAL, Effect, make_effect
from physics.recording import Recording
from physics.sensor import Unit, random_unit
from physics.simulate import Noise, Pose, Scan, World, ar1_whiten, plan_timeline, simulate_timeline, truth_json
from physics.table import Motion, TableGeometry, base_rotation
from proof.concealments import OPEN_KINDS, make_open

#: Every concealable catalogue effect, in catalogue order.
EFFECTS: tuple[str, ...] = tuple(CONCEAL)

#: Non-centrality range of the proof (catalogue and open-world cases alike).
NC_RANGE = (3.0, 300.0)
#: Non-centrality range of each effect of a pair: from the size at which one effect alone should be
#: detected (the 90 % target at 25), so that "both named" measures separation, not detection power
#: (with both effects spread over 3-300 only a third of the pairs would have both above 25).
PAIR_NC_RANGE = (25.0, 300.0)
#: Non-centrality range of the open world's large departures (``open_large``): what users meet when a
#: magnet or a steel tool sits near the unit (the issue's own examples moved the level heading by
#: 0.8-2.5 deg, lambda 1e4-1e6 on the ordinary plan). Above the main range a departure is found
#: easily; what these cases test is that its model is right to the sample: one sample on the wrong side
#: of a 400-LSB step leaves the residual at several times the floor.
LARGE_NC_RANGE = (300.0, 1e6)

#: Parameters scaled to set an effect's size (the others give its direction, shape or windows).
SCALED = {
    "stage_hard_iron": ("m",), "stage_soft_iron": ("A",), "nonlinearity": ("c3",),
    "temperature_drift": ("bias_per_c",), "field_drift": ("rate_per_s",), "time_lag": ("lag_s",),
    "hysteresis": ("offset",), "table_axis_error": ("nonperp_deg", "encoder_zero_deg"),
    "field_gradient": ("gradient",), "mains_interference": ("amplitude_lsb",),
    # open world (proof.concealments)
    "segment_offset_sensor": ("offset",), "segment_offset_lab": ("offset",), "segment_offset_outer": ("offset",),
    "segment_offset_middle": ("offset",), "intermittent_interference": ("offset",),
    "gain_vs_temp": ("gain_per_c",), "misalignment_drift": ("rate_rad_per_s",),
}

#: Noise of the open-world cases: 3 LSB per axis, quantised; white in this share of the cases, else
#: AR(1) with phi in 0.3-0.9 as in the catalogue cases (a real unit's noise is often coloured).
OPEN_SIGMA_LSB = 3.0
OPEN_WHITE = 0.7
#: A single window covers this share of the recording's duration (at least 15 %, never all of it: an
#: offset present throughout is the unit's bias or the field and the nominal model absorbs it).
WINDOW_FRAC = (0.15, 0.6)
#: Intermittent interference: 2-3 windows of this share each, separated by at least INTERMITTENT_GAP
#: (more than the scorer's 5 % edge tolerance, so that neighbouring windows stay distinguishable).
INTERMITTENT_FRAC = (0.08, 0.15)
INTERMITTENT_GAP = 0.08
#: Probability that a window starts with the recording, and (separately) that one ends with it.
TOUCH = 0.15
#: gain_vs_temp needs a temperature that changes: a warm-up of this many degrees with a time constant
#: of this share of the run (so that temp_c bends within the run instead of being a line in time).
GAIN_WARMUP_C = (2.0, 5.0)
GAIN_TAU_FRAC = (0.3, 1.0)


# --------------------------------------------------------------------------------------------------
# Cases
# --------------------------------------------------------------------------------------------------

@dataclass
class Case:
    """One recording of the proof and its truth."""

    kind: str  # "null", a catalogue effect id, "a+b", or an open-world kind (proof.concealments.OPEN_KINDS)
    effects: list[str]
    params: dict[str, dict[str, Any]]  # effect id -> Effect.params() (the truth)
    target_nc: dict[str, float]
    nc: dict[str, float]  # achieved non-centrality of each effect alone
    nc_total: float  # of all the case's effects together (0 for a null)
    nc_floor: float  # of the encoder rounding alone (not an effect; see the module docstring)
    unit: Unit
    world: World
    noise: Noise
    rec: Recording | None = None  # what the analyser gets
    clean: Recording | None = None  # the truth: with the effects, without noise and quantisation
    seed: int | None = None
    generator: str = "catalogue"  # "catalogue" or "open" (which draw made the world and noise)
    model: dict[str, Any] | None = None  # open-world truth in the analyser's finding["model"] schema
    span_s: tuple[float, float] | None = None  # the recording's [first sample, one period after the last)
    #: frames the recording cannot tell from the true one where the effect is present (equivalent_frames)
    frames: list[str] | None = None
    #: the same recording without the effects, with the same noise: what a perfect model of them leaves
    free: Recording | None = None

    def truth(self) -> dict[str, Any]:
        """The true unit, world and noise, JSON-safe."""
        t = truth_json(self.unit, self.world)
        t.update({"temperature_c": self.world.temperature_c, "warmup_c": self.world.warmup_c,
                  "warmup_tau_s": self.world.warmup_tau_s,
                  "noise": {"sigma_lsb": self.noise.sigma.tolist(), "phi": self.noise.phi,
                            "quantized": self.noise.quantized}})
        return t

    def summary(self) -> dict[str, Any]:
        """The case without its recordings, JSON-safe."""
        d = {"kind": self.kind, "effects": list(self.effects), "params": self.params,
             "target_nc": self.target_nc, "nc": self.nc, "nc_total": self.nc_total, "nc_floor": self.nc_floor,
             "noise": {"sigma_lsb": self.noise.sigma.tolist(), "phi": self.noise.phi}, "seed": self.seed}
        if self.generator != "catalogue":
            d.update({"generator": self.generator, "model": self.model, "frames": self.frames,
                      "span_s": None if self.span_s is None else list(self.span_s)})
        return d


def field_base(world: World) -> np.ndarray:
    """The true field direction in the table's base frame (what the nominal model calls v)."""
    return base_rotation(world.geometry.base_tilt_deg).T @ world.field_L


def _tangent(v: np.ndarray) -> np.ndarray:
    a = np.eye(3)[np.argmin(np.abs(v))]
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(v, e1)])


def nominal_misfit(rec: Recording, mag: np.ndarray, noise: Noise, rate_hz: float, v0: np.ndarray) -> float:
    """Whitened residual sum of squares of the best nominal fit ``mag ~ M R^T v + b`` (the module's lambda).

    ``rec`` gives the rows' times and table angles, ``mag`` (N, 3) the output fitted, ``v0`` the field
    direction to start from (the truth). Variable projection: M, b by whitened least squares for each
    v, v by Levenberg-Marquardt on its tangent plane.
    """
    R = es.rotations(rec)
    n = len(rec)
    W = lambda x: ar1_whiten(x, rec.t, rate_hz, noise.phi)  # noqa: E731  (sigma per axis below)
    RW = W(R.reshape(n, 9)).reshape(n, 3, 3)
    one = W(np.ones(n))
    y = W(np.asarray(mag, dtype=float))
    sigma = noise.sigma

    def residual(p: np.ndarray, ref: np.ndarray, basis: np.ndarray) -> np.ndarray:
        v = ref + p @ basis
        v = v / np.linalg.norm(v)
        X = np.column_stack([np.einsum("nji,j->ni", RW, v), one])
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        return ((y - X @ coef) / sigma).ravel()

    v = np.asarray(v0, dtype=float) / np.linalg.norm(v0)
    best = np.inf
    for _ in range(2):  # the tangent plane moves with the solution: restart once from it
        basis = _tangent(v)
        sol = least_squares(residual, np.zeros(2), args=(v, basis), method="lm", xtol=1e-12, ftol=1e-12)
        best = min(best, float(np.sum(sol.fun ** 2)))
        v = v + sol.x @ basis
        v /= np.linalg.norm(v)
    return best


def _unit_vector(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.standard_normal(n)
    return v / np.linalg.norm(v)


def draw_null(rng: np.random.Generator, warmup_c: tuple[float, float] = (0.0, 4.0),
              warmup_tau_s: tuple[float, float] = (100.0, 600.0), sigma_lsb: tuple[float, float] = (1.0, 5.0),
              axis_spread: float = 0.15, white: float = 0.5) -> tuple[Unit, World, Noise]:
    """A random unit, world and noise with the full parameter spread of the proof.

    Unit: physics.sensor.random_unit. World: I in 40-70 deg, D anywhere, base tilt up to 0.1 deg in a
    random direction, room 18-28 C, warm-up ``warmup_c`` C with time constant ``warmup_tau_s``. Noise:
    sigma uniform in ``sigma_lsb`` (each axis within ``axis_spread`` of it), white in a share ``white``
    of the cases, else AR(1) with phi in 0.3-0.9, quantised. The defaults are the catalogue cases'.
    """
    unit = random_unit(rng)
    tilt, az = rng.uniform(0.0, 0.1), rng.uniform(0.0, 2 * np.pi)
    world = World(inclination_deg=float(rng.uniform(40.0, 70.0)), declination_deg=float(rng.uniform(0.0, 360.0)),
                  geometry=TableGeometry(base_tilt_deg=(float(tilt * np.cos(az)), float(tilt * np.sin(az)))),
                  temperature_c=float(rng.uniform(18.0, 28.0)), warmup_c=float(rng.uniform(*warmup_c)),
                  warmup_tau_s=float(rng.uniform(*warmup_tau_s)))
    sigma = float(rng.uniform(*sigma_lsb))
    phi = 0.0 if rng.random() < white else float(rng.uniform(0.3, 0.9))
    spread = rng.uniform(1.0 - axis_spread, 1.0 + axis_spread, 3)
    noise = Noise(tuple(float(s) for s in sigma * spread), phi, True)  # type: ignore[arg-type]
    return unit.with_noise(mag_noise_lsb=sigma), world, noise


def draw_effect(effect_id: str, rng: np.random.Generator, unit: Unit, motion: Motion) -> dict[str, Any]:
    """Constructor arguments of catalogue effect ``effect_id`` with a random direction at a small reference size."""
    if effect_id == "stage_hard_iron":
        return {"stage": str(rng.choice(["outer", "middle"])), "m": 0.005 * _unit_vector(rng, 3)}
    if effect_id == "stage_soft_iron":
        a = _unit_vector(rng, 6) * 0.005
        A = np.array([[a[0], a[3], a[4]], [a[3], a[1], a[5]], [a[4], a[5], a[2]]])
        return {"stage": str(rng.choice(["outer", "middle"])), "A": A}
    if effect_id == "nonlinearity":
        return {"c3": 5.0 * _unit_vector(rng, 3), "k": unit.mag.k, "bias": unit.mag.bias}
    if effect_id == "temperature_drift":
        return {"bias_per_c": 2.0 * _unit_vector(rng, 3)}
    if effect_id == "field_drift":
        return {"rate_per_s": 1e-5 * _unit_vector(rng, 3)}
    if effect_id == "time_lag":
        return {"lag_s": 0.01}
    if effect_id == "hysteresis":
        return {"offset": 0.001 * _unit_vector(rng, 3)}
    if effect_id == "table_axis_error":
        a = 0.02 * _unit_vector(rng, 4)
        return {"nonperp_deg": a[:2], "encoder_zero_deg": a[2:]}
    if effect_id == "field_gradient":
        return {"gradient": 0.05 * _unit_vector(rng, 5), "offset_m": rng.uniform(0.01, 0.05) * _unit_vector(rng, 3)}
    if effect_id == "mains_interference":
        return {"amplitude_lsb": 2.0 * _unit_vector(rng, 3),
                "freq_hz": float(rng.choice([50.0, 60.0]) + rng.uniform(-0.3, 0.3)),
                "phase_rad": float(rng.uniform(0.0, 2 * np.pi)), "sample_rate_hz": motion.sample_rate_hz}
    raise ValueError(f"effect: expected one of {', '.join(EFFECTS)}, got {effect_id!r}")


def scale_effect(effect_id: str, kw: dict[str, Any], s: float) -> dict[str, Any]:
    """``kw`` with the effect's size parameters (:data:`SCALED`) multiplied by ``s``."""
    out = dict(kw)
    for name in SCALED[effect_id]:
        out[name] = float(kw[name]) * s if np.isscalar(kw[name]) else np.asarray(kw[name], dtype=float) * s
    return out


def conceal(effect_id: str, kw: dict[str, Any]) -> Effect:
    """The concealment of a catalogue effect or an open-world kind from its keyword parameters."""
    return make_open(effect_id, kw) if effect_id in OPEN_KINDS else make_effect(effect_id, kw)


def log_uniform(rng: np.random.Generator, lo: float = NC_RANGE[0], hi: float = NC_RANGE[1]) -> float:
    """A draw log-uniform in [lo, hi]."""
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


@dataclass
class _Concealed:
    """What :func:`_conceal` made: the sized effects' parameters, their lambdas and the recordings."""

    kws: dict[str, dict[str, Any]]
    nc: dict[str, float]
    nc_total: float
    nc_floor: float
    rec: Recording
    clean: Recording
    effects: list[Effect]
    free: Recording  # the same recording without the effects (the same noise)


def _conceal(draws: dict[str, Callable[[], dict[str, Any]]], targets: dict[str, float], unit: Unit, world: World,
             noise: Noise, noise_seed: int, plan: Sequence[Pose | Scan], motion: Motion, tolerance: float) -> _Concealed:
    """Size each effect of ``draws`` (id -> a draw of its parameters at a reference size) to its target
    lambda alone, then simulate them all together (the sizing of the module docstring).

    Each effect is scaled until its lambda alone is within ``tolerance`` of the target (at most 5
    rounds; the achieved value is recorded either way); a direction the nominal model absorbs
    completely is drawn again. The same noise (``noise_seed``) throughout, so the recording differs
    only by the effect.
    """
    rate = motion.sample_rate_hz
    v0 = field_base(world)

    def simulate(kws: dict[str, dict[str, Any]]) -> tuple[Recording, Recording]:
        effects = [conceal(e, kw) for e, kw in kws.items()]
        return simulate_timeline(unit, plan, world, motion, effects, noise, np.random.default_rng(noise_seed))

    def misfit(clean: Recording) -> float:
        return nominal_misfit(clean, clean.mag, noise, rate, v0)

    kws: dict[str, dict[str, Any]] = {}
    achieved: dict[str, float] = {}
    last: tuple[Recording, Recording] | None = None
    for e, draw in draws.items():
        kw = draw()
        lam = 0.0
        for attempt in range(5):
            last = simulate({e: kw})
            lam = misfit(last[1])
            if abs(lam / targets[e] - 1.0) <= tolerance or attempt == 4:
                break  # (kw is what was simulated and measured)
            if not lam > 1e-12:  # a direction the nominal model absorbs completely: draw another
                kw = draw()
                continue
            kw = scale_effect(e, kw, math.sqrt(targets[e] / lam))
        kws[e], achieved[e] = kw, lam

    if len(draws) == 1 and last is not None:
        rec, clean = last
        nc_total = next(iter(achieved.values()))
    else:
        rec, clean = simulate(kws)
        nc_total = misfit(clean) if draws else 0.0
    effects = [conceal(e, kw) for e, kw in kws.items()]
    # the encoder rounding alone: the effect-free output fitted at the recorded (rounded) angles
    free, clean0 = simulate_timeline(unit, plan, world, motion, (), noise, np.random.default_rng(noise_seed))
    floor = nominal_misfit(rec, clean0.mag, noise, rate, v0)
    return _Concealed(kws, achieved, float(nc_total), float(floor), rec, clean, effects, free)


def make_case(kind: str, rng: np.random.Generator, plan: Sequence[Pose | Scan], target_nc: float | dict[str, float] | None = None,
              motion: Motion = Motion(), tolerance: float = 0.1, seed: int | None = None) -> Case:
    """One catalogue case: ``kind`` is "null", an effect id, or two ids joined by "+".

    ``target_nc``: the non-centrality of each effect (one number for all, a dict per effect, or None
    to draw each log-uniformly in [3, 300]). Each effect is scaled until its lambda alone is within
    ``tolerance`` of the target (at most 5 rounds; the achieved value is recorded either way).
    """
    ids = [] if kind == "null" else kind.split("+")
    for e in ids:
        if e not in CONCEAL:
            raise ValueError(f"kind: unknown effect {e!r} (expected null, one of {', '.join(EFFECTS)} or a+b)")
    if len(set(ids)) != len(ids):
        raise ValueError(f"kind: a pair needs two different effects, got {kind!r}")
    unit, world, noise = draw_null(rng, (0.5, 4.0) if "temperature_drift" in ids else (0.0, 4.0))
    noise_seed = int(rng.integers(2 ** 63))

    targets: dict[str, float] = {}
    for e in ids:
        t = target_nc.get(e) if isinstance(target_nc, dict) else target_nc
        targets[e] = float(t) if t is not None else log_uniform(rng)

    draws = {e: (lambda e=e: draw_effect(e, rng, unit, motion)) for e in ids}
    c = _conceal(draws, targets, unit, world, noise, noise_seed, plan, motion, tolerance)
    return Case(kind=kind, effects=ids, params={e.id: e.params() for e in c.effects}, target_nc=targets,
                nc=c.nc, nc_total=c.nc_total, nc_floor=c.nc_floor, unit=unit, world=world, noise=noise,
                rec=c.rec, clean=c.clean, seed=seed)


# --------------------------------------------------------------------------------------------------
# Open world (issue 12): physics no catalogue entry names
# --------------------------------------------------------------------------------------------------

def ordinary_plan() -> list[Pose | Scan]:
    """The plan a user calibrates with, not one designed for the analysis: a level turn (the ``level``
    step, 4 holds), the calibration (procedures.calibrate.calibration_poses: a level turn about z, full
    sweeps about y and about x) and the six accelerometer poses; 60 samples per hold, 28 holds,
    about 200 s at the default Motion."""
    # imported here: procedures pulls in the engine, which the catalogue cases never need
    from procedures.calibrate import ACCEL6_POSES, calibration_poses

    plan: list[Pose | Scan] = [Pose("level", a, 0.0, 0.0, 60) for a in (0.0, 90.0, 180.0, 270.0)]
    plan += calibration_poses()
    plan += [Pose("accel6", *a, samples=60) for a in ACCEL6_POSES]
    return plan


#: The speed of :func:`sweeping_plan`'s turns (deg/s): a full turn in 36 s, 20 samples per 10 deg.
SWEEP_DPS = 10.0


def sweeping_plan() -> list[Pose | Scan]:
    """The ordinary plan as a station that turns without stopping would record it: the level turn's four
    holds, then a turn about z, sweeps about y and x and a turn back about z, each continuous at
    :data:`SWEEP_DPS` (every sample on the move, with its encoder angles), and the six accelerometer
    poses; about 260 s. The analyser is not told the plan: its holds are what it finds still."""
    from procedures.calibrate import ACCEL6_POSES

    plan: list[Pose | Scan] = [Pose("level", a, 0.0, 0.0, 60) for a in (0.0, 90.0, 180.0, 270.0)]
    plan += [Scan("rotate_z", "psi", 0.0, 360.0, SWEEP_DPS), Scan("sweep_y", "theta", -180.0, 180.0, SWEEP_DPS),
             Scan("sweep_x", "phi", -180.0, 180.0, SWEEP_DPS), Scan("rotate_z_back", "psi", 180.0, -180.0, SWEEP_DPS)]
    plan += [Pose("accel6", *a, samples=60) for a in ACCEL6_POSES]
    return plan


def _characterize_plan() -> list[Pose | Scan]:
    from procedures.calibrate import characterize_plan

    return characterize_plan()


#: The plans the open-world cases can be drawn on (`compasscal prove --open-plan`).
OPEN_PLANS: dict[str, Callable[[], list[Pose | Scan]]] = {
    "calibrate": ordinary_plan, "sweeps": sweeping_plan, "characterize": _characterize_plan}


def recording_span(plan: Sequence[Pose | Scan], motion: Motion = Motion()) -> tuple[float, float]:
    """``[t_first, t_end)`` of the recording ``plan`` makes: the first kept sample's time and one sample
    period after the last (half-open, so that a window ending there holds the last sample)."""
    tl = plan_timeline(plan, motion)
    if not len(tl.keep):
        raise ValueError("plan: records no samples")
    return float(tl.keep[0] / tl.rate_hz), float((tl.keep[-1] + 1) / tl.rate_hz)


def recording_rows(plan: Sequence[Pose | Scan], motion: Motion = Motion()) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) and true encoder angles (N, 3) of the samples ``plan`` records."""
    tl = plan_timeline(plan, motion)
    t = tl.keep / tl.rate_hz
    return t, tl.angles(t)


#: The gimbal chain from the lab to the unit; the encoder angle psi turns the outer stage against the
#: lab, theta the middle stage against the outer, phi the platform (and the sensor on it) against the middle.
FRAME_CHAIN = ("lab", "outer", "middle", "sensor")


def equivalent_frames(frame: str, angles: np.ndarray, still_deg: float = 1.0) -> list[str]:
    """The frames of :data:`FRAME_CHAIN` that ``angles`` (N, 3: the rows where an effect fixed in
    ``frame`` is present) cannot tell from ``frame``: those joined to it only by gimbal angles that
    stay within ``still_deg`` over all these rows (the relative rotation is then constant, so a vector
    fixed in one is fixed in the other). E.g. an offset on the outer stage while theta and phi hold
    still is an offset in the sensor frame."""
    i = FRAME_CHAIN.index(frame)
    still = np.ptp(np.asarray(angles, dtype=float).reshape(-1, 3), axis=0) <= still_deg if len(angles) else np.ones(3, bool)
    lo, hi = i, i
    while lo > 0 and still[lo - 1]:  # angle lo-1 joins FRAME_CHAIN[lo-1] and FRAME_CHAIN[lo]
        lo -= 1
    while hi < len(FRAME_CHAIN) - 1 and still[hi]:
        hi += 1
    return list(FRAME_CHAIN[lo:hi + 1])


def draw_windows(rng: np.random.Generator, span: tuple[float, float], count: int, frac: tuple[float, float],
                 min_gap_frac: float = 0.0, touch: float = TOUCH) -> list[list[float]]:
    """``count`` disjoint windows ``[t0, t1)`` in ``span``, each ``frac`` (uniform) of its duration long,
    at least ``min_gap_frac`` of it apart; the free time is shared at random before, between and after
    them, except that with probability ``touch`` the first starts with the span and (separately) the
    last ends with it."""
    lo, hi = span
    dur = hi - lo
    lengths = rng.uniform(*frac, count) * dur
    free = dur - lengths.sum() - (count - 1) * min_gap_frac * dur
    if free < 0:
        raise ValueError(f"draw_windows: {count} windows of {frac} with gaps of {min_gap_frac} do not fit")
    share = rng.dirichlet(np.ones(count + 1))
    if rng.random() < touch:
        share[-1] += share[0]
        share[0] = 0.0
    if rng.random() < touch and share[0] > 0.0:  # (not both: the windows would then fill everything)
        share[0] += share[-1]
        share[-1] = 0.0
    gaps = share * free
    gaps[1:-1] += min_gap_frac * dur
    out, t = [], lo + gaps[0]
    for L, g in zip(lengths, gaps[1:]):
        out.append([float(t), float(min(t + L, hi))])
        t += L + g
    if share[-1] == 0.0:
        out[-1][1] = float(hi)  # exactly the end, not a rounding short of it
    return out


def _inside(t: np.ndarray, segments: Sequence[Sequence[float]]) -> np.ndarray:
    return np.any([(t >= a) & (t < b) for a, b in segments], axis=0)


def draw_open(kind: str, rng: np.random.Generator, unit: Unit, world: World, span: tuple[float, float],
              rows: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, Any]:
    """Constructor arguments of open-world ``kind`` (proof.concealments) with a random direction, windows
    or rates at a small reference size (the generator scales it to the target lambda).

    ``rows`` (the recording's times and angles, :func:`recording_rows`): a window of an offset fixed in
    the lab or a stage is drawn again until the table turns that frame against the sensor within it
    (else it would be a sensor-frame offset, and no analysis could say otherwise).
    """
    if kind in ("segment_offset_sensor", "segment_offset_lab", "segment_offset_outer", "segment_offset_middle"):
        size = 20.0 if kind == "segment_offset_sensor" else 0.01  # LSB; lab-field units
        frame = kind.rsplit("_", 1)[1]
        for _ in range(100):
            segments = draw_windows(rng, span, 1, WINDOW_FRAC)
            if frame == "sensor" or rows is None or "sensor" not in equivalent_frames(frame, rows[1][_inside(rows[0], segments)]):
                break
        return {"offset": size * _unit_vector(rng, 3), "segments": segments}
    if kind == "intermittent_interference":
        return {"offset": 20.0 * _unit_vector(rng, 3),
                "segments": draw_windows(rng, span, int(rng.integers(2, 4)), INTERMITTENT_FRAC, INTERMITTENT_GAP)}
    if kind == "gain_vs_temp":
        # the room temperature is where the unit starts (its calibration's reference)
        return {"gain_per_c": 1e-4 * _unit_vector(rng, 3), "bias": unit.mag.bias, "t_ref_c": world.temperature_c}
    if kind == "misalignment_drift":
        return {"rate_rad_per_s": 1e-5 * _unit_vector(rng, 3), "bias": unit.mag.bias, "t_mid": 0.5 * (span[0] + span[1])}
    raise ValueError(f"open kind: expected one of {', '.join(OPEN_KINDS)}, got {kind!r}")


def make_open_case(kind: str, rng: np.random.Generator, plan: Sequence[Pose | Scan] | None = None,
                   target_nc: float | None = None, motion: Motion = Motion(), tolerance: float = 0.1,
                   seed: int | None = None) -> Case:
    """One open-world case: ``kind`` is one of proof.concealments.OPEN_KINDS, or "null" (none, with the
    open world's unit, warm-up and noise).

    ``plan`` defaults to :func:`ordinary_plan`. Noise: :data:`OPEN_SIGMA_LSB` per axis, white in a
    share :data:`OPEN_WHITE` of the cases, else AR(1). ``target_nc`` (None: log-uniform in [3, 300]) and
    ``tolerance`` size the effect as in :func:`make_case`. The case's ``model`` is the truth the scorer
    compares with the analyser's findings, ``span_s`` the recording's time span.
    """
    if kind != "null" and kind not in OPEN_KINDS:
        raise ValueError(f"kind: expected null or one of {', '.join(OPEN_KINDS)}, got {kind!r}")
    plan = list(plan) if plan is not None else ordinary_plan()
    span = recording_span(plan, motion)
    rows = recording_rows(plan, motion)
    if kind == "gain_vs_temp":
        run = span[1]
        warm = dict(warmup_c=GAIN_WARMUP_C, warmup_tau_s=(GAIN_TAU_FRAC[0] * run, GAIN_TAU_FRAC[1] * run))
    else:
        warm = {}
    unit, world, noise = draw_null(rng, sigma_lsb=(OPEN_SIGMA_LSB, OPEN_SIGMA_LSB), axis_spread=0.0, white=OPEN_WHITE,
                                   **warm)  # type: ignore[arg-type]
    noise_seed = int(rng.integers(2 ** 63))
    ids = [] if kind == "null" else [kind]
    targets = {e: float(target_nc) if target_nc is not None else log_uniform(rng) for e in ids}
    draws = {e: (lambda: draw_open(kind, rng, unit, world, span, rows)) for e in ids}
    c = _conceal(draws, targets, unit, world, noise, noise_seed, plan, motion, tolerance)
    model = c.effects[0].model() if c.effects else None  # type: ignore[attr-defined]
    frames = None
    if model is not None:
        present = _inside(rows[0], model["segments"]) if model["segments"] else np.ones(len(rows[0]), bool)
        frames = equivalent_frames(model["frame"], rows[1][present])
    return Case(kind=kind, effects=ids, params={kind: c.effects[0].params()} if ids else {}, target_nc=targets,
                nc=c.nc, nc_total=c.nc_total, nc_floor=c.nc_floor, unit=unit, world=world, noise=noise,
                rec=c.rec, clean=c.clean, seed=seed, generator="open", model=model, span_s=span, frames=frames,
                free=c.free)
