"""The blind proof of the discrepancy engine (issue 6): a generator of recordings with concealed
effects, a runner that hands each recording (and nothing else) to the analyser, and a scorer.

The generator is a separate code path from the analyser on purpose: it uses only the forward side
(physics.simulate.simulate_timeline with the concealment classes of physics.effects, random units
from physics.sensor) and its own nominal fit to set effect sizes. It never imports
physics.discrepancy; only the runner does, to analyse.

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
:data:`PAIR_NC_RANGE`).
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from itertools import combinations
from multiprocessing import get_context
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import least_squares, minimize
from scipy.stats import beta, chi2, ncx2

from physics import errorsep as es
from physics.calibration import json_safe
from physics.effects import CONCEAL, make_effect
from physics.recording import Recording
from physics.sensor import Unit, random_unit
from physics.simulate import Noise, Pose, Scan, World, ar1_whiten, simulate_timeline, truth_json
from physics.table import Motion, TableGeometry, base_rotation

#: Every concealable effect, in catalogue order.
EFFECTS: tuple[str, ...] = tuple(CONCEAL)

#: Non-centrality range of the proof and the bins of the detection table (lower edges inclusive; the
#: first bin also takes values a little under 3, the last a little over 300).
NC_RANGE = (3.0, 300.0)
NC_BINS = ((3.0, 6.0), (6.0, 14.0), (14.0, 35.0), (35.0, 100.0), (100.0, 300.0))
#: Non-centrality range of each effect of a pair: from the size at which one effect alone should be
#: detected (the 90 % target at 25), so that "both named" measures separation, not detection power
#: (with both effects spread over 3-300 only a third of the pairs would have both above 25).
PAIR_NC_RANGE = (25.0, 300.0)

#: Parameters scaled to set an effect's size (the others give its direction or shape).
SCALED = {
    "stage_hard_iron": ("m",), "stage_soft_iron": ("A",), "nonlinearity": ("c3",),
    "temperature_drift": ("bias_per_c",), "field_drift": ("rate_per_s",), "time_lag": ("lag_s",),
    "hysteresis": ("offset",), "table_axis_error": ("nonperp_deg", "encoder_zero_deg"),
    "field_gradient": ("gradient",), "mains_interference": ("amplitude_lsb",),
}

#: Parameters whose recovery is scored (vectors compared as a whole; the others have ambiguities:
#: soft iron's isotropic part is the unit's k, a gradient trades against its offset, mains against its phase).
RECOVERED = {
    "stage_hard_iron": ("m",), "field_drift": ("rate_per_s",), "temperature_drift": ("bias_per_c",),
    "nonlinearity": ("c3",), "hysteresis": ("offset",), "time_lag": ("lag_s",),
    "table_axis_error": ("nonperp_deg", "encoder_zero_deg"),
}

#: The issue's targets, printed next to each figure.
TARGETS = {"detect_at_10": 0.50, "detect_at_25": 0.90, "false_alarm": 0.01, "min_nulls": 300,
           "right_first": 0.90, "right_set": 0.98, "pairs_both": 0.80, "heldout": 1.05, "seconds": 30.0,
           "coverage": 0.95}

NOT_DETECTED = "(none)"


# --------------------------------------------------------------------------------------------------
# Generator
# --------------------------------------------------------------------------------------------------

@dataclass
class Case:
    """One recording of the proof and its truth."""

    kind: str  # "null", an effect id, or "a+b"
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
        return {"kind": self.kind, "effects": list(self.effects), "params": self.params,
                "target_nc": self.target_nc, "nc": self.nc, "nc_total": self.nc_total, "nc_floor": self.nc_floor,
                "noise": {"sigma_lsb": self.noise.sigma.tolist(), "phi": self.noise.phi}, "seed": self.seed}


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


def draw_null(rng: np.random.Generator, warmup_c: tuple[float, float] = (0.0, 4.0)) -> tuple[Unit, World, Noise]:
    """A random unit, world and noise with the full parameter spread of the proof.

    Unit: physics.sensor.random_unit. World: I in 40-70 deg, D anywhere, base tilt up to 0.1 deg in a
    random direction, room 18-28 C, warm-up ``warmup_c`` C with time constant 100-600 s. Noise: sigma
    1-5 LSB (each axis within 15 % of it), white in half the cases, else AR(1) with phi in 0.3-0.9,
    quantised.
    """
    unit = random_unit(rng)
    tilt, az = rng.uniform(0.0, 0.1), rng.uniform(0.0, 2 * np.pi)
    world = World(inclination_deg=float(rng.uniform(40.0, 70.0)), declination_deg=float(rng.uniform(0.0, 360.0)),
                  geometry=TableGeometry(base_tilt_deg=(float(tilt * np.cos(az)), float(tilt * np.sin(az)))),
                  temperature_c=float(rng.uniform(18.0, 28.0)), warmup_c=float(rng.uniform(*warmup_c)),
                  warmup_tau_s=float(rng.uniform(100.0, 600.0)))
    sigma = float(rng.uniform(1.0, 5.0))
    phi = 0.0 if rng.random() < 0.5 else float(rng.uniform(0.3, 0.9))
    noise = Noise(tuple(float(s) for s in sigma * rng.uniform(0.85, 1.15, 3)), phi, True)  # type: ignore[arg-type]
    return unit.with_noise(mag_noise_lsb=sigma), world, noise


def draw_effect(effect_id: str, rng: np.random.Generator, unit: Unit, motion: Motion) -> dict[str, Any]:
    """Constructor arguments of ``effect_id`` with a random direction at a small reference size."""
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


def log_uniform(rng: np.random.Generator, lo: float = NC_RANGE[0], hi: float = NC_RANGE[1]) -> float:
    """A draw log-uniform in [lo, hi]."""
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def make_case(kind: str, rng: np.random.Generator, plan: Sequence[Pose | Scan], target_nc: float | dict[str, float] | None = None,
              motion: Motion = Motion(), tolerance: float = 0.1, seed: int | None = None) -> Case:
    """One proof case: ``kind`` is "null", an effect id, or two ids joined by "+".

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
    rate = motion.sample_rate_hz
    v0 = field_base(world)

    def simulate(kws: dict[str, dict[str, Any]]) -> tuple[Recording, Recording]:
        effects = [make_effect(e, kw) for e, kw in kws.items()]
        return simulate_timeline(unit, plan, world, motion, effects, noise, np.random.default_rng(noise_seed))

    def misfit(clean: Recording) -> float:
        return nominal_misfit(clean, clean.mag, noise, rate, v0)

    targets: dict[str, float] = {}
    for e in ids:
        t = target_nc.get(e) if isinstance(target_nc, dict) else target_nc
        targets[e] = float(t) if t is not None else log_uniform(rng)

    kws: dict[str, dict[str, Any]] = {}
    achieved: dict[str, float] = {}
    last: tuple[Recording, Recording] | None = None
    for e in ids:
        kw = draw_effect(e, rng, unit, motion)
        lam = 0.0
        for attempt in range(5):
            last = simulate({e: kw})
            lam = misfit(last[1])
            if abs(lam / targets[e] - 1.0) <= tolerance or attempt == 4:
                break  # (kw is what was simulated and measured)
            if not lam > 1e-12:  # a direction the nominal model absorbs completely: draw another
                kw = draw_effect(e, rng, unit, motion)
                continue
            kw = scale_effect(e, kw, math.sqrt(targets[e] / lam))
        kws[e], achieved[e] = kw, lam

    if len(ids) == 1 and last is not None:
        rec, clean = last
        nc_total = achieved[ids[0]]
    else:
        rec, clean = simulate(kws)
        nc_total = misfit(clean) if ids else 0.0
    effects = [make_effect(e, kw) for e, kw in kws.items()]
    # the encoder rounding alone: the effect-free output fitted at the recorded (rounded) angles
    _, clean0 = simulate_timeline(unit, plan, world, motion, (), noise, np.random.default_rng(noise_seed))
    floor = nominal_misfit(rec, clean0.mag, noise, rate, v0)
    return Case(kind=kind, effects=ids, params={e.id: e.params() for e in effects}, target_nc=targets,
                nc=achieved, nc_total=float(nc_total), nc_floor=float(floor), unit=unit, world=world, noise=noise,
                rec=rec, clean=clean, seed=seed)


# --------------------------------------------------------------------------------------------------
# Runner
# --------------------------------------------------------------------------------------------------

@dataclass
class Outcome:
    """What the scorer needs of one analysis."""

    result: dict[str, Any] | None  # Analysis.result (None when the analyser raised)
    heldout_ratio: float | None = None  # RMS(rec.mag - heldout_pred_after) / RMS(rec.mag - clean.mag)
    seconds: float | None = None
    error: str | None = None
    heldout_before: float | None = None  # the same with heldout_pred_before (the nominal model)


def heldout_ratio(case: Case, series: dict[str, np.ndarray], key: str = "heldout_pred_after") -> float | None:
    """Held-out residual RMS of the analyser's final model (``key``: or of its nominal model) over
    that of the true model (1: as good as the truth), over all rows and axes."""
    if case.rec is None or case.clean is None or key not in series:
        return None
    pred = np.asarray(series[key], dtype=float)
    if pred.shape != case.rec.mag.shape:
        return None
    ok = np.all(np.isfinite(pred), axis=1)
    if not ok.any():
        return None
    ours = np.sqrt(np.mean((case.rec.mag[ok] - pred[ok]) ** 2))
    true = np.sqrt(np.mean((case.rec.mag[ok] - case.clean.mag[ok]) ** 2))
    return float(ours / true) if true > 0 else None


@dataclass(frozen=True)
class Task:
    """One case to generate and analyse (everything a worker process needs; picklable)."""

    index: int
    kind: str
    seed: int
    target_nc: dict[str, float] | None
    plan: tuple[Pose | Scan, ...]
    motion: Motion
    analyze_kwargs: dict[str, Any] = field(default_factory=dict)


def run_task(task: Task) -> tuple[int, Case, Outcome]:
    """Generate one case, hand its noisy recording (only) to the analyser, time it. Top level for spawn."""
    from physics.discrepancy import analyze  # the analyser is imported here only, never by the generator

    gen, ana = np.random.SeedSequence(task.seed).spawn(2)
    case = make_case(task.kind, np.random.default_rng(gen), task.plan, task.target_nc, task.motion, seed=task.seed)
    assert case.rec is not None
    rec = case.rec.select(slice(None))  # a copy: nothing the analyser does can touch the truth
    t0 = time.perf_counter()
    try:
        a = analyze(rec, rng=np.random.default_rng(ana), **task.analyze_kwargs)
    except Exception as e:  # noqa: BLE001 - a crash is a result of the proof, scored and reported
        out = Outcome(None, None, time.perf_counter() - t0, f"{type(e).__name__}: {e}")
    else:
        secs = time.perf_counter() - t0
        out = Outcome(a.result, heldout_ratio(case, a.series), secs, None,
                      heldout_ratio(case, a.series, "heldout_pred_before"))
    return task.index, replace(case, rec=None, clean=None), out


def proof_tasks(n: int, seed: int, plan: Sequence[Pose | Scan], nulls: int | None = None, pairs: int | None = None,
                motion: Motion = Motion(), analyze_kwargs: dict[str, Any] | None = None,
                pair_nc: tuple[float, float] = PAIR_NC_RANGE) -> list[Task]:
    """The proof's cases: ``n`` per effect at non-centralities spread log-uniformly over [3, 300]
    (stratified: one draw in each of n equal log-intervals), ``nulls`` nulls (default max(3 n, 20)),
    ``pairs`` pairs (default n // 2) of different effects drawn from all pairs, each effect at its own
    target log-uniform in ``pair_nc`` (see :data:`PAIR_NC_RANGE`)."""
    nulls = max(3 * n, 20) if nulls is None else nulls
    pairs = n // 2 if pairs is None else pairs
    rng = np.random.default_rng(np.random.SeedSequence([seed, 6]))
    lo, hi = np.log(NC_RANGE[0]), np.log(NC_RANGE[1])
    specs: list[tuple[str, dict[str, float] | None]] = []
    for e in EFFECTS:
        u = (np.arange(n) + rng.uniform(0.0, 1.0, n)) / max(n, 1)
        specs += [(e, {e: float(np.exp(lo + x * (hi - lo)))}) for x in rng.permutation(u)]
    specs += [("null", None)] * nulls
    all_pairs = list(combinations(EFFECTS, 2))
    order = np.concatenate([rng.permutation(len(all_pairs)) for _ in range(pairs // len(all_pairs) + 1)])[:pairs]
    for i in order:
        a, b = all_pairs[int(i)]
        specs.append((f"{a}+{b}", {a: log_uniform(rng, *pair_nc), b: log_uniform(rng, *pair_nc)}))
    seeds = np.random.SeedSequence(seed).generate_state(len(specs), dtype=np.uint64)
    return [Task(i, kind, int(s), target, tuple(plan), motion, dict(analyze_kwargs or {}))
            for i, ((kind, target), s) in enumerate(zip(specs, seeds))]


class _SingleThreadedBLAS:
    """Each worker on one BLAS thread (set in the environment the spawned workers inherit)."""

    VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

    def __enter__(self) -> None:
        self.saved = {k: os.environ.get(k) for k in self.VARS}
        for k in self.VARS:
            os.environ[k] = "1"

    def __exit__(self, *exc: object) -> None:
        for k, v in self.saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run_tasks(tasks: Sequence[Task], workers: int = 2,
              progress: Callable[[int, int, str], None] | None = None) -> tuple[list[Case], list[Outcome]]:
    """Run tasks (in a spawn pool of ``workers`` processes; in this process when ``workers`` <= 1),
    calling ``progress(done, total, kind)`` after each; results in task order."""
    results: dict[int, tuple[Case, Outcome]] = {}
    total = len(tasks)
    if workers <= 1:
        for task in tasks:
            i, case, out = run_task(task)
            results[i] = (case, out)
            if progress:
                progress(len(results), total, case.kind)
    else:
        with _SingleThreadedBLAS(), ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(run_task, t) for t in tasks]
            for f in as_completed(futures):
                i, case, out = f.result()
                results[i] = (case, out)
                if progress:
                    progress(len(results), total, case.kind)
    ordered = [results[t.index] for t in tasks]
    return [c for c, _ in ordered], [o for _, o in ordered]


def run_proof(n: int, seed: int, workers: int = 2, progress: Callable[[int, int, str], None] | None = None, *,
              plan: Sequence[Pose | Scan], nulls: int | None = None, pairs: int | None = None,
              motion: Motion = Motion(), analyze_kwargs: dict[str, Any] | None = None,
              pair_nc: tuple[float, float] = PAIR_NC_RANGE) -> dict[str, Any]:
    """The blind proof: generate the cases of :func:`proof_tasks`, analyse each noisy recording with
    ``physics.discrepancy.analyze`` (default arguments unless ``analyze_kwargs``; never anything of the
    truth), score. Returns ``{"score", "cases", "config"}``, JSON-safe."""
    tasks = proof_tasks(n, seed, plan, nulls, pairs, motion, analyze_kwargs, pair_nc)
    t0 = time.perf_counter()
    cases, outcomes = run_tasks(tasks, workers, progress)
    sc = score(cases, outcomes)
    per_case = []
    for c, o in zip(cases, outcomes):
        d = c.summary()
        r = o.result or {}
        d.update({"verdict": r.get("verdict"),
                  "findings": [{k: f.get(k) for k in ("effect", "p_value", "p_adjusted", "parameters", "sigma",
                                                      "confusable_with")} for f in r.get("findings", [])],
                  "heldout_ratio": o.heldout_ratio, "heldout_before": o.heldout_before, "seconds": o.seconds,
                  "error": o.error})
        per_case.append(d)
    config = {"n": n, "seed": seed, "nulls": sum(c.kind == "null" for c in cases),
              "pairs": sum("+" in c.kind for c in cases), "pair_nc": list(pair_nc), "workers": workers, "plan_items": len(plan),
              "analyze_kwargs": dict(analyze_kwargs or {}), "wall_s": time.perf_counter() - t0}
    return json_safe({"score": sc, "cases": per_case, "config": config})


# --------------------------------------------------------------------------------------------------
# Scorer
# --------------------------------------------------------------------------------------------------

def clopper_pearson_upper(k: int, n: int, confidence: float = 0.95) -> float:
    """One-sided upper confidence bound of a binomial rate with k successes in n trials."""
    if n == 0:
        return 1.0
    return 1.0 if k >= n else float(beta.ppf(confidence, k + 1, n - k))


def logistic_fit(nc: Sequence[float], detected: Sequence[bool], at: Sequence[float] = (10.0, 25.0),
                 ridge: float = 0.01) -> dict[str, float] | None:
    """Detection probability at non-centralities ``at`` from a logistic fit against log(lambda).

    A weak ridge keeps the fit finite when the classes separate (all detected above some size).
    None with fewer than 3 cases.
    """
    x = np.log(np.asarray(nc, dtype=float) / 20.0)
    y = np.asarray(detected, dtype=float)
    if len(x) < 3:
        return None

    def nll(b: np.ndarray) -> tuple[float, np.ndarray]:
        z = b[0] + b[1] * x
        p = 1.0 / (1.0 + np.exp(-z))
        f = float(np.sum(np.logaddexp(0.0, z) - y * z) + 0.5 * ridge * (b @ b))
        g = np.array([np.sum(p - y), np.sum((p - y) * x)]) + ridge * b
        return f, g

    b = minimize(nll, np.zeros(2), jac=True, method="BFGS").x
    return {f"{a:g}": float(1.0 / (1.0 + np.exp(-(b[0] + b[1] * np.log(a / 20.0))))) for a in at}


def _outcome(a: Outcome | dict[str, Any]) -> Outcome:
    return a if isinstance(a, Outcome) else Outcome(a)  # a bare Analysis.result (hand-made analyses in tests)


def _named(finding: dict[str, Any]) -> set[str]:
    return {finding.get("effect", "")} | set(finding.get("confusable_with", []) or [])


def _bin(nc: float) -> int:
    for i, (lo, hi) in enumerate(NC_BINS):
        if nc < hi:
            return i
    return len(NC_BINS) - 1


def _flat(params: dict[str, Any], names: Sequence[str]) -> np.ndarray | None:
    try:
        return np.concatenate([np.ravel(np.asarray(params[k], dtype=float)) for k in names])
    except (KeyError, TypeError, ValueError):
        return None


def _pct(xs: Sequence[float], q: float) -> float | None:
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return float(np.percentile(xs, q)) if xs else None


def score(cases: Sequence[Case], analyses: Sequence[Outcome | dict[str, Any]]) -> dict[str, Any]:
    """Score analyses against the truth of their cases (same order).

    An analysis is an :class:`Outcome` or a bare ``Analysis.result`` dict. Detected means verdict
    "discrepancy". Figures (all JSON-safe):

    - ``detection[effect]``: per non-centrality bin [detected, cases] of the single-effect cases, and
      the logistic-fit rate at lambda 10 and 25;
    - ``false_alarms``: nulls, false alarms, rate, one-sided 95 % Clopper-Pearson upper bound;
    - ``confusion[true][first finding]`` over single-effect cases and nulls (``(none)`` when not detected);
    - ``naming``: among detected single-effect cases, "right" when the true effect is the first
      finding or in its confusable_with; split into identifiable (first finding has no
      confusable_with: right name first) and confusable (the true effect is in the named set);
    - ``pairs``: both effects named (each is some finding's effect or in its confusable_with);
    - ``recovery[effect]``: for the finding naming the true effect (same stage for stage effects),
      median |est - true| / |true| of the :data:`RECOVERED` vector and the coverage of its 1.96-sigma
      intervals (fraction of components);
    - ``heldout``: RMS(rec - held-out prediction after) / RMS(rec - clean truth), median and 90th
      percentile, for effect cases, detected effect cases and nulls;
    - ``seconds``: per analysis, median and max; ``errors``: analyses that raised.
    """
    if len(cases) != len(analyses):
        raise ValueError(f"score: {len(cases)} cases but {len(analyses)} analyses")
    det: dict[str, list[tuple[float, bool]]] = {e: [] for e in EFFECTS}
    confusion: dict[str, dict[str, int]] = {}
    naming: dict[str, dict[str, int]] = {e: {"detected": 0, "right": 0, "identifiable": 0, "identifiable_right": 0,
                                             "confusable": 0, "confusable_right": 0} for e in EFFECTS}
    pairs = {"cases": 0, "both_named": 0, "detected": 0}
    pair_nc: list[float] = []
    recovery: dict[str, dict[str, Any]] = {e: {"cases": 0, "rel_err": [], "covered": 0, "components": 0,
                                               "wrong_stage": 0} for e in RECOVERED}
    nulls = {"cases": 0, "false_alarms": 0}
    held: dict[str, list[float]] = {"effects": [], "detected": [], "nulls": []}
    held_before: dict[str, list[float]] = {"effects": [], "detected": [], "nulls": []}
    removed: list[float] = []  # share of the held-out excess over the truth that the fitted effects remove
    held_by_effect: dict[str, list[float]] = {e: [] for e in EFFECTS}
    seconds: list[float] = []
    errors: list[dict[str, Any]] = []
    nc_floor: list[float] = []
    design: dict[str, Any] = {"df": {}, "tests": [], "alpha": None}  # round-1 tests, for the ideal power

    for case, a in zip(cases, analyses):
        o = _outcome(a)
        result, ratio, secs, error, before = o.result, o.heldout_ratio, o.seconds, o.error, o.heldout_before
        round1 = [t for t in (result or {}).get("tests", []) or [] if t.get("round") == 1 and (t.get("df") or 0) > 0]
        if round1:
            design["tests"].append(len(round1))
            design["alpha"] = (result or {}).get("alpha", design["alpha"])
            for t in round1:
                if not t.get("generic") and t.get("effect") in EFFECTS:
                    design["df"][t["effect"]] = max(design["df"].get(t["effect"], 0), int(t["df"]))
        if secs is not None:
            seconds.append(secs)
        if error is not None or result is None:
            errors.append({"kind": case.kind, "seed": case.seed, "error": error})
        result = result or {}
        detected = result.get("verdict") == "discrepancy"
        findings = list(result.get("findings", []) or [])
        first = findings[0].get("effect", NOT_DETECTED) if detected and findings else NOT_DETECTED
        nc_floor.append(case.nc_floor)
        if case.kind == "null":
            nulls["cases"] += 1
            nulls["false_alarms"] += int(detected)
            confusion.setdefault("null", {}).setdefault(first, 0)
            confusion["null"][first] += 1
            for store, x in ((held, ratio), (held_before, before)):
                if x is not None:
                    store["nulls"].append(x)
            continue
        for store, x in ((held, ratio), (held_before, before)):
            if x is not None:
                store["effects"].append(x)
                if detected:
                    store["detected"].append(x)
        if detected and ratio is not None and before is not None and before > 1.0:
            removed.append(1.0 - (ratio ** 2 - 1.0) / (before ** 2 - 1.0))
        if len(case.effects) == 2:
            pairs["cases"] += 1
            pairs["detected"] += int(detected)
            pair_nc += list(case.nc.values())
            named = set().union(*(_named(f) for f in findings)) if findings else set()
            pairs["both_named"] += int(detected and set(case.effects) <= named)
            continue
        (true,) = case.effects
        det[true].append((case.nc[true], detected))
        confusion.setdefault(true, {}).setdefault(first, 0)
        confusion[true][first] += 1
        if ratio is not None:
            held_by_effect[true].append(ratio)
        if detected and findings:
            nm = naming[true]
            f0 = findings[0]
            right = true in _named(f0)
            nm["detected"] += 1
            nm["right"] += int(right)
            if f0.get("confusable_with"):
                nm["confusable"] += 1
                nm["confusable_right"] += int(right)
            else:
                nm["identifiable"] += 1
                nm["identifiable_right"] += int(f0.get("effect") == true)
        if true in RECOVERED:
            match = [f for f in findings if f.get("effect") == true]
            if not match:
                continue
            f, truth = match[0], case.params[true]
            est_p, sig_p = f.get("parameters", {}) or {}, f.get("sigma", {}) or {}
            rec = recovery[true]
            if "stage" in truth and est_p.get("stage") not in (None, truth["stage"]):
                rec["wrong_stage"] += 1
                continue
            names = RECOVERED[true]
            est, tru, sig = _flat(est_p, names), _flat(truth, names), _flat(sig_p, names)
            if est is None or tru is None or est.shape != tru.shape:
                continue
            # a component the recording cannot determine (the nominal model absorbs it) comes with a
            # null sigma: it is neither recovered nor covered, and is counted apart
            ok = np.isfinite(sig) if sig is not None and sig.shape == est.shape else np.ones(est.shape, bool)
            rec["cases"] += 1
            rec["undetermined"] = rec.get("undetermined", 0) + int((~ok).sum())
            rec["rel_err"].append(float(np.linalg.norm((est - tru)[ok]) / max(np.linalg.norm(tru[ok]), 1e-300)))
            if sig is not None and sig.shape == est.shape:
                rec["components"] += int(ok.sum())
                rec["covered"] += int(np.sum(np.abs(est - tru)[ok] <= 1.96 * sig[ok]))

    # the best any single test could do: one chi-square test of the effect's own df at the family's
    # corrected level (what the detection targets ask of a test that also has to tell effects apart)
    m = float(np.median(design["tests"])) if design["tests"] else None
    ideal: dict[str, dict[str, float]] = {}
    if m and design["alpha"]:
        for e, df in design["df"].items():
            c = chi2.isf(design["alpha"] / m, df)
            ideal[e] = {"df": df, "10": float(ncx2.sf(c, df, 10.0)), "25": float(ncx2.sf(c, df, 25.0))}
    detection = {}
    for e, rows in det.items():
        bins = [[0, 0] for _ in NC_BINS]
        for nc, d in rows:
            b = bins[_bin(nc)]
            b[0] += int(d)
            b[1] += 1
        fitted = logistic_fit([r[0] for r in rows], [r[1] for r in rows]) if rows else None
        detection[e] = {"bins": bins, "cases": len(rows), "detected": sum(d for _, d in rows),
                        "rate_at_10": fitted["10"] if fitted else None, "rate_at_25": fitted["25"] if fitted else None,
                        "heldout_median": _pct(held_by_effect[e], 50), "ideal": ideal.get(e)}
    k, n = nulls["false_alarms"], nulls["cases"]
    false_alarms = {"nulls": n, "false_alarms": k, "rate": k / n if n else None,
                    "upper95": clopper_pearson_upper(k, n) if n else None,
                    "nc_floor_median": _pct([c.nc_floor for c in cases if c.kind == "null"], 50),
                    "nc_floor_max": _pct([c.nc_floor for c in cases if c.kind == "null"], 100)}

    def rate(a: int, b: int) -> float | None:
        return a / b if b else None

    tot = {k2: sum(v[k2] for v in naming.values()) for k2 in next(iter(naming.values()))}
    naming_out = {"by_effect": naming, "detected": tot["detected"], "right": tot["right"],
                  "right_rate": rate(tot["right"], tot["detected"]),
                  "identifiable": tot["identifiable"], "right_first_rate": rate(tot["identifiable_right"], tot["identifiable"]),
                  "confusable": tot["confusable"], "right_set_rate": rate(tot["confusable_right"], tot["confusable"])}
    recovery_out = {e: {"cases": r["cases"], "rel_err_median": _pct(r["rel_err"], 50),
                        "coverage": rate(r["covered"], r["components"]), "components": r["components"],
                        "wrong_stage": r["wrong_stage"]} for e, r in recovery.items()}
    return {
        "detection": detection,
        "false_alarms": false_alarms,
        "confusion": confusion,
        "naming": naming_out,
        "pairs": {**pairs, "both_named_rate": rate(pairs["both_named"], pairs["cases"]),
                  "nc_min": min(pair_nc, default=None), "nc_max": max(pair_nc, default=None)},
        "recovery": recovery_out,
        "heldout": {k2: {"cases": len(v), "median": _pct(v, 50), "p90": _pct(v, 90),
                         "before_median": _pct(held_before[k2], 50), "before_p90": _pct(held_before[k2], 90)}
                    for k2, v in held.items()},
        "heldout_excess_removed": {"cases": len(removed), "median": _pct(removed, 50), "p10": _pct(removed, 10)},
        "seconds": {"analyses": len(seconds), "median": _pct(seconds, 50), "max": _pct(seconds, 100)},
        "errors": errors,
    }


# --------------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------------

def _f(x: float | None, fmt: str = "{:.0%}") -> str:
    return "-" if x is None else fmt.format(x)


def _mark(ok: bool | None) -> str:
    return "" if ok is None else (" ok" if ok else " MISSED")


def format_report(sc: dict[str, Any]) -> str:
    """The score as plain-text tables, each figure next to the issue's target."""
    T = TARGETS
    out: list[str] = []
    bins = ["[{:g},{:g})".format(*b) if i < len(NC_BINS) - 1 else "[{:g},{:g}]".format(*b) for i, b in enumerate(NC_BINS)]
    head = (f"{'effect':<20}{'n':>4}" + "".join(f"{b:>10}" for b in bins) + f"{'@10':>7}{'@25':>7}{'held-out':>10}"
            + f"{'ideal@10':>10}{'ideal@25':>10}")
    out += ["Detection rate by non-centrality (detected/cases; logistic fit at lambda 10 and 25; "
            f"targets >= {T['detect_at_10']:.0%} at 10, >= {T['detect_at_25']:.0%} at 25). ideal: one chi-square "
            "test of the effect's df at the family's corrected level, the best a test could do", head, "-" * len(head)]
    missed, fitted = [], []
    for e, d in sc["detection"].items():
        cells = "".join(f"{f'{k}/{n}' if n else '-':>10}" for k, n in d["bins"])
        r10, r25 = d["rate_at_10"], d["rate_at_25"]
        if r10 is not None:
            fitted.append(e)
            if r10 < T["detect_at_10"] or r25 < T["detect_at_25"]:
                missed.append(e)
        idl = d.get("ideal") or {}
        out.append(f"{e:<20}{d['cases']:>4}{cells}{_f(r10):>7}{_f(r25):>7}{_f(d['heldout_median'], '{:.3f}'):>10}"
                   f"{_f(idl.get('10')):>10}{_f(idl.get('25')):>10}")
    out.append(f"effects meeting both detection targets: {len(fitted) - len(missed)}/{len(fitted)} with a fit "
               f"(3 cases or more)" + (f"; missed: {', '.join(missed)}" if missed else ""))
    out.append("")

    fa = sc["false_alarms"]
    ok = None if fa["upper95"] is None else (fa["upper95"] <= T["false_alarm"] and fa["nulls"] >= T["min_nulls"])
    out.append(f"False alarms on nulls: {fa['false_alarms']}/{fa['nulls']} = {_f(fa['rate'], '{:.2%}')}, one-sided 95 % "
               f"upper bound {_f(fa['upper95'], '{:.2%}')} (target <= {T['false_alarm']:.0%} on >= {T['min_nulls']} nulls)"
               + _mark(ok))
    out.append(f"  encoder rounding alone (nc_floor, not an effect): median {_f(fa['nc_floor_median'], '{:.2f}')}, "
               f"max {_f(fa['nc_floor_max'], '{:.2f}')}")
    out.append("")

    nm = sc["naming"]
    out.append("Naming, among detected single-effect cases:")
    out.append(f"  right name first (first finding has no confusable): {nm['identifiable']} cases, "
               f"{_f(nm['right_first_rate'])} (target >= {T['right_first']:.0%})"
               + _mark(None if nm["right_first_rate"] is None else nm["right_first_rate"] >= T["right_first"]))
    out.append(f"  right set when reported confusable: {nm['confusable']} cases, {_f(nm['right_set_rate'])} "
               f"(target >= {T['right_set']:.0%})"
               + _mark(None if nm["right_set_rate"] is None else nm["right_set_rate"] >= T["right_set"]))
    out.append(f"  overall (first finding or its confusable_with): {nm['right']}/{nm['detected']} = {_f(nm['right_rate'])}")
    head = f"  {'effect':<20}{'detected':>9}{'right':>7}{'ident.':>8}{'right':>7}{'confus.':>9}{'right':>7}"
    out += [head]
    for e, r in nm["by_effect"].items():
        out.append(f"  {e:<20}{r['detected']:>9}{r['right']:>7}{r['identifiable']:>8}{r['identifiable_right']:>7}"
                   f"{r['confusable']:>9}{r['confusable_right']:>7}")
    out.append("")

    p = sc["pairs"]
    span = f" (each effect at lambda {p['nc_min']:.0f}-{p['nc_max']:.0f})" if p.get("nc_min") is not None else ""
    out.append(f"Pairs{span}: both effects named in {p['both_named']}/{p['cases']} = {_f(p['both_named_rate'])} "
               f"(target >= {T['pairs_both']:.0%}){_mark(None if p['both_named_rate'] is None else p['both_named_rate'] >= T['pairs_both'])}; "
               f"detected {p['detected']}/{p['cases']}")
    out.append("")

    conf = sc["confusion"]
    cols = [c for c in [*EFFECTS, "unexplained", "parameter_shift", NOT_DETECTED]
            if any(c in row for row in conf.values())]
    cols += sorted({c for row in conf.values() for c in row} - set(cols))
    short = {c: c[:7] for c in cols}
    out.append("Confusion matrix (rows: true effect; columns: first finding; (none): not detected)")
    out.append(f"{'':<20}" + "".join(f"{short[c]:>8}" for c in cols))
    for true in [*EFFECTS, "null"]:
        if true in conf:
            out.append(f"{true:<20}" + "".join(f"{conf[true].get(c, 0) or '.':>8}" for c in cols))
    out.append("")

    out.append(f"Parameter recovery (finding naming the true effect; coverage of 1.96-sigma intervals, "
               f"target ~{T['coverage']:.0%})")
    out.append(f"  {'effect':<20}{'cases':>6}{'median rel. err':>17}{'coverage':>10}{'wrong stage':>13}")
    for e, r in sc["recovery"].items():
        out.append(f"  {e:<20}{r['cases']:>6}{_f(r['rel_err_median'], '{:.3f}'):>17}{_f(r['coverage']):>10}"
                   f"{r['wrong_stage']:>13}")
    out.append("")

    h = sc["heldout"]
    out.append(f"Held-out residual RMS over the true model's (target <= {T['heldout']:.2f}), after the fitted effects "
               f"(before: the nominal model):")
    for k, v in h.items():
        ok = None if v["median"] is None else v["median"] <= T["heldout"]
        out.append(f"  {k:<9} {v['cases']:>4} cases: median {_f(v['median'], '{:.3f}')}, 90th percentile "
                   f"{_f(v['p90'], '{:.3f}')}{_mark(ok)}   (before: {_f(v['before_median'], '{:.3f}')}, "
                   f"{_f(v['before_p90'], '{:.3f}')})")
    x = sc.get("heldout_excess_removed", {})
    if x.get("cases"):
        out.append(f"  share of the held-out excess over the truth removed by the fitted effects (detected cases, "
                   f"(before^2 - after^2) / (before^2 - 1)): median {_f(x['median'])}, 10th percentile {_f(x['p10'])}")
    s = sc["seconds"]
    ok = None if s["max"] is None else s["max"] <= T["seconds"]
    out.append(f"Seconds per analysis: median {_f(s['median'], '{:.1f}')}, max {_f(s['max'], '{:.1f}')} "
               f"(target < {T['seconds']:.0f}){_mark(ok)}")
    if sc["errors"]:
        out.append(f"Analyses that raised: {len(sc['errors'])}")
        for e in sc["errors"][:10]:
            out.append(f"  {e['kind']} (seed {e['seed']}): {e['error']}")
    return "\n".join(out)
