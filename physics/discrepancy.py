"""Discrepancy analysis: where a recording departs from the nominal twin, which catalogued physics
explains it, the fit with it, and what is left unexplained (issue 6).

The method, in the order :func:`analyze` runs it:

1. **Compare.** Fit the nominal model ``raw = M R^T v + b`` (physics/errorsep.py's joint fit) to every
   sample; the residuals are what the twin does not predict.
2. **Noise.** Estimate each axis's noise as AR(1) plus white (quantisation) from first differences of
   the residual inside the static holds (else every contiguous run of samples): a difference cancels
   any pose's mean, so slow model errors and drifts do not inflate it. The data and every regressor are
   prewhitened with it (Kalman innovations).
3. **Linear twin.** Around the nominal fit the twin is linear in everything: the nominal Jacobian J0
   (M, b and two field-direction coordinates) plus, for each catalogue effect (physics/effects.py),
   regressor columns whose coefficients are the effect's parameters in its own units. The same
   machinery takes generic "unexplained structure" regressors (harmonics against each table angle,
   polynomials in time and temperature, the table rate, the accelerometer).
4. **Test.** Nested likelihood-ratio tests on the whitened data: the statistic of adding an effect's
   columns to the current model is chi-square with df = the rank they add. A parametric bootstrap
   (simulated AR(1) nulls at the recording's own time stamps, with the noise re-estimated each time,
   as the analysis does) measures how far the noise estimate inflates each statistic (a Bartlett
   factor). p-values are Bonferroni-corrected over every test of the round; no AIC. Mains pickup is a
   line search over frequency against the local spectrum (colour-robust), corrected for the number of
   independent frequencies.
5. **Name.** Forward selection: the catalogue effect with the smallest corrected p joins the model
   while it stays below alpha (at most :data:`MAX_EFFECTS`). Two effects are confusable when either
   one, once in the model, leaves the other insignificant; both are reported with the experiment that
   would separate them. Structure that no entry explains is reported as "unexplained structure against
   <input>". Effects the nominal model absorbs completely can only show as implausible or shifted
   nominal parameters ("parameter_shift").
6. **Model it.** Parameters with 1-sigma, residual RMS and heading error before and after, and the
   improvement on held-out data (4 interleaved folds of holds and 1-s chunks of motion).

Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy import signal, stats
from threadpoolctl import threadpool_limits

from physics import effects as fx
from physics import errorsep as es
from physics.calibration import Calibration, json_safe
from physics.frames import SPECIFIC_FORCE_L, field_angles
from physics.heading import magnetic_heading, wrap180
from physics.recording import Recording, RecordingError
from physics.sensor import split_matrix
from physics.table import TableGeometry, platform_attitude

#: At most this many catalogue effects are added to one recording's model.
MAX_EFFECTS = 3
#: Harmonic orders searched against each table angle in the "unexplained" tests.
HARMONICS = (2, 3, 4)
#: Plausibility limits on the nominal fit: beyond these a unit is not what it claims to be.
MAX_MISALIGNMENT_DEG = 10.0
MAX_K_MISMATCH = 0.25
MAX_BIAS_FIELDS = 3.0
#: Longer recordings are block-averaged to this many samples (a hand-held IMU at 285 Hz) to keep the
#: analysis within seconds; the note says so.
MAX_SAMPLES = 20_000
#: Fewer samples cannot estimate the noise, let alone test anything against it.
MIN_SAMPLES = 200
#: Recording metadata key naming where the table angles come from; anything but "turntable" (e.g. an
#: optical reference tracking a hand-held unit) makes the table's own effects untestable.
ATTITUDE_SOURCE_KEY = "attitude_source"

Progress = Callable[[str, float], None]


@dataclass
class Analysis:
    """The analyser's output: ``result`` is the JSON report, ``series`` per-sample arrays for plots."""

    result: dict[str, Any]
    series: dict[str, np.ndarray] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The JSON report (already JSON-safe)."""
        return self.result


# --------------------------------------------------------------------------------------------------
# The recording's structure: segments, holds, motion
# --------------------------------------------------------------------------------------------------

@dataclass
class Context:
    """Per-sample quantities every regressor needs (N samples)."""

    rec: Recording
    t: np.ndarray
    ang: np.ndarray  # (N, 3) encoder degrees
    R: np.ndarray  # (N, 3, 3) nominal platform attitude C_LP
    segment: np.ndarray  # (N,) contiguous sampling runs (a gap or a new step starts one)
    hold: np.ndarray  # (N,) hold index, -1 while moving
    rate: np.ndarray  # (N, 3) encoder rates, deg/s
    rate_hz: float

    @property
    def moving(self) -> np.ndarray:
        """Samples taken while the table turned."""
        return self.hold < 0


def sample_period(t: np.ndarray) -> float:
    """The median time between samples (1 when the time stamps do not advance)."""
    dt = np.diff(t)
    return float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0


def runs(t: np.ndarray, step: np.ndarray, gap: float = 1.5) -> np.ndarray:
    """Index of each sample's contiguous run: a new run starts at a change of step or after a pause of
    more than ``gap`` sample periods (a move between holds)."""
    new = np.r_[True, (np.diff(t) > gap * sample_period(t)) | (step[1:] != step[:-1])]
    return np.cumsum(new) - 1


def blocks(run: np.ndarray, k: int) -> np.ndarray:
    """Index of each sample's block: ``k`` consecutive samples of one run (the last block of a run may
    be shorter)."""
    start = np.r_[0, np.flatnonzero(np.diff(run)) + 1]
    within = np.arange(len(run)) - np.repeat(start, np.diff(np.r_[start, len(run)]))
    return np.cumsum(np.r_[True, (np.diff(run) != 0) | (np.diff(within // k) != 0)]) - 1


def decimate(rec: Recording, k: int) -> Recording:
    """Average every ``k`` consecutive samples of one contiguous run of a step (angles unwrapped)."""
    t = np.asarray(rec.t, float)
    seg = runs(t, rec.step)
    group = blocks(seg, k)
    n = np.bincount(group)

    def avg(x: np.ndarray | None) -> np.ndarray | None:
        if x is None:
            return None
        x = np.asarray(x, float)
        return (np.bincount(group, x) / n if x.ndim == 1
                else np.column_stack([np.bincount(group, x[:, j]) / n for j in range(x.shape[1])]))

    ang = np.column_stack([rec.psi_t, rec.theta_t, rec.phi_t])
    for s in np.unique(seg):
        i = np.flatnonzero(seg == s)
        ang[i] = np.degrees(np.unwrap(np.radians(ang[i]), axis=0))
    first = np.r_[0, np.flatnonzero(np.diff(group)) + 1]
    a = avg(ang)
    return Recording.from_arrays(avg(t), rec.step[first], a[:, 0], a[:, 1], a[:, 2], avg(rec.mag), avg(rec.acc),
                                 avg(rec.temp_c), rec.meta)


def _strict(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Time stamps of one segment made strictly increasing (lines read in a burst share a stamp)."""
    return t if np.all(np.diff(t) > 0) else t[0] + np.arange(len(t)) / rate_hz


def context(rec: Recording) -> Context:
    """Segments, holds and rates of a recording with table angles."""
    t = np.asarray(rec.t, float)
    ang = es.table_angles(rec)
    rate_hz = 1.0 / sample_period(t)
    segment = runs(t, rec.step)
    new = np.r_[True, segment[1:] != segment[:-1]]
    key = np.round(ang, 3)
    still = np.r_[False, np.all(key[1:] == key[:-1], axis=1) & ~new[1:]]
    # a hold: a run of samples at one set of encoder angles (at least 3), within one segment
    start = np.r_[True, ~still[1:]]
    run = np.cumsum(start) - 1
    size = np.bincount(run)
    hold_runs = np.flatnonzero(size >= 3)
    hold = np.full(len(t), -1)
    is_hold = np.isin(run, hold_runs)
    hold[is_hold] = np.searchsorted(hold_runs, run[is_hold])
    rate = np.zeros_like(ang)
    for s in np.unique(segment):
        i = np.flatnonzero(segment == s)
        if len(i) >= 2:  # unwrapped: a hand-held heading crosses +-180
            rate[i] = np.gradient(np.degrees(np.unwrap(np.radians(ang[i]), axis=0)), _strict(t[i], rate_hz), axis=0)
    return Context(rec, t, ang, es.rotations(rec), segment, hold, rate, rate_hz)


# --------------------------------------------------------------------------------------------------
# Noise: AR(1) per axis, whitening, simulation
# --------------------------------------------------------------------------------------------------

@dataclass
class NoiseModel:
    """Each axis's noise: an AR(1) process (marginal ``sigma``, lag-1 coefficient ``phi``) plus white
    noise (``white``: quantisation, the converter). Arrays of shape (3,) or (3, K) for K nulls.

    A quantised sensor with strongly coloured noise is not AR(1): the rounding adds white noise that an
    AR(1) model reads as a lower phi, and whitening with that phi leaves the slow noise correlated, which
    every slow effect's test would take for a signal."""

    sigma: np.ndarray
    phi: np.ndarray
    white: np.ndarray

    @property
    def floor(self) -> np.ndarray:
        """Per-sample sigma (AR and white parts together)."""
        return np.sqrt(self.sigma ** 2 + self.white ** 2)

    def kalman(self) -> tuple[np.ndarray, np.ndarray]:
        """Steady-state Kalman gain K and innovation sigma of the AR(1)-plus-white model."""
        s2, p, q = self.sigma ** 2, self.phi, self.white ** 2
        e2 = s2 * (1.0 - p * p)
        P = s2
        for _ in range(200):  # converges geometrically (phi^2 per step at worst)
            Pm = p * p * P + e2
            P = Pm * q / np.maximum(Pm + q, 1e-300)
        Pm = p * p * P + e2
        return Pm / np.maximum(Pm + q, 1e-300), np.sqrt(Pm + q)

    def spectrum(self, f: np.ndarray, rate_hz: float) -> np.ndarray:
        """Noise power (arbitrary scale) at frequencies ``f`` per axis: (len(f), 3)."""
        z = np.exp(-2j * np.pi * f / rate_hz)[:, None]
        return self.sigma ** 2 * (1 - self.phi ** 2) / np.abs(1.0 - self.phi * z) ** 2 + self.white ** 2


#: Lags of the differences' autocovariance that the noise model is fitted to.
NOISE_LAGS = 12


def noise_model(r: np.ndarray, segment: np.ndarray) -> NoiseModel:
    """AR(1)-plus-white noise per axis (and per trailing column) from first differences inside segments.

    A difference cancels any pose's mean and nearly any slow model error. For x = a + w (a: AR(1) of
    variance s^2, w: white of variance q), d = x_t - x_{t-1} has autocovariances
    g(0) = 2 u / (1 - phi) + 2 q, g(1) = -u - q, g(k) = -phi^(k-1) u for k >= 2, with
    u = s^2 (1 - phi)^2. (u, phi, q) are fitted to the first :data:`NOISE_LAGS` lags by least squares:
    many lags pin phi near 1 much better than two do, and phi near 1 sets the slow noise every slow
    effect's test is judged against."""
    same = segment[1:] == segment[:-1]
    d = np.diff(r, axis=0)
    g = []
    ok = same.copy()
    for k in range(NOISE_LAGS + 1):
        if k:
            ok = ok[1:] & same[:-k]
        prod = d[k:] * d[:len(d) - k] if k else d * d
        g.append(np.mean(prod[ok], axis=0) if ok.any() else np.zeros(d.shape[1:]))
    g = np.array(g)  # (lags, 3, ...)
    shape = g.shape[1:]
    G = g.reshape(len(g), -1)
    sig, phi, white = np.empty(G.shape[1]), np.empty(G.shape[1]), np.empty(G.shape[1])
    k = np.arange(len(g))
    for i in range(G.shape[1]):
        sig[i], phi[i], white[i] = _fit_difference_acov(G[:, i], k)
    return NoiseModel(sig.reshape(shape), phi.reshape(shape), white.reshape(shape))


def _fit_difference_acov(g: np.ndarray, k: np.ndarray) -> tuple[float, float, float]:
    """(s, phi, sqrt q) of AR(1)-plus-white noise from its differences' autocovariance g(k)."""
    from scipy.optimize import least_squares

    g0 = max(g[0], 1e-300)
    phi1 = float(np.clip(1.0 + 2.0 * g[1] / g0, -0.5, 0.98))  # AR(1) alone, the start

    def model(x: np.ndarray) -> np.ndarray:
        u, ph, q = x[0] ** 2, x[1], x[2] ** 2
        m = -u * ph ** np.maximum(k - 1, 0)
        m[0] = 2 * u / (1 - ph) + 2 * q
        m[1] -= q
        return m

    u0 = g0 * (1 - phi1) / 2 * (1 - phi1)
    sol = least_squares(lambda x: (model(x) - g) / g0, [np.sqrt(max(u0, 1e-300)), phi1, np.sqrt(0.1 * g0)],
                        bounds=([0.0, -0.5, 0.0], [np.inf, 0.985, np.inf]), x_scale=1.0)
    u, ph, q = sol.x[0] ** 2, float(sol.x[1]), sol.x[2] ** 2
    s = float(np.sqrt(max(u, 1e-12)) / (1 - ph))
    if s * s < 0.02 * q:  # no AR part to speak of: white noise, and its phi means nothing
        return s, 0.0, float(np.sqrt(q))
    return s, ph, float(np.sqrt(q))


def estimate_noise(r: np.ndarray, ctx: "Context") -> NoiseModel:
    """The noise floor: :func:`noise_model` on the static holds when they hold 200 samples or more (the
    table at rest: nothing but the sensor's noise), else on every contiguous run of samples."""
    hold = ctx.hold >= 0
    if hold.sum() - len(np.unique(ctx.hold[hold])) >= 200:
        return noise_model(r[hold], ctx.hold[hold])
    return noise_model(r, ctx.segment)


def whiten_all(X: np.ndarray, noise: NoiseModel, segment: np.ndarray) -> np.ndarray:
    """Whiten (N, 3, p) columns (or (N, 3) data) into stacked rows (3N, p) (axis-major): the Kalman
    innovations of the AR(1)-plus-white model, nu_t = x_t - phi x_{t-1} + phi (1 - K) nu_{t-1}, each over
    its innovation sigma, restarted (from the marginal sigma) at each segment."""
    flat = X.ndim == 2
    X3 = X[:, :, None] if flat else X
    K, S = noise.kalman()
    first = np.r_[True, segment[1:] != segment[:-1]]
    starts = np.flatnonzero(first)
    ends = np.r_[starts[1:], len(segment)]
    out = np.empty((3, X3.shape[0], X3.shape[2]))
    for j in range(3):
        b, a = [1.0, -noise.phi[j]], [1.0, -noise.phi[j] * (1.0 - K[j])]
        for lo, hi in zip(starts, ends):
            out[j, lo:hi] = signal.lfilter(b, a, X3[lo:hi, j, :], axis=0)
        out[j] /= S[j]
        out[j, first] *= S[j] / noise.floor[j]  # a segment's first sample: nothing to predict it from
    out = out.reshape(3 * X3.shape[0], X3.shape[2])
    return out[:, 0] if flat else out


def _whiten_each(e: np.ndarray, noise: NoiseModel, segment: np.ndarray) -> np.ndarray:
    """Whiten K realisations (N, 3, K), each with its own noise model ((3, K) arrays): a time loop over
    all realisations at once."""
    K, S = noise.kalman()
    c = noise.phi * (1.0 - K)
    first = np.r_[True, segment[1:] != segment[:-1]]
    out = np.empty_like(e)
    nu = np.zeros(e.shape[1:])
    for t in range(len(e)):
        nu = e[t] if first[t] else e[t] - noise.phi * e[t - 1] + c * nu
        out[t] = nu / (noise.floor if first[t] else S)
    return out


def simulate_noise(n: int, noise: NoiseModel, segment: np.ndarray, rng: np.random.Generator, k: int = 1) -> np.ndarray:
    """``k`` realisations (N, 3, k) of the noise model, the AR part restarted at each segment."""
    e = rng.normal(size=(n, 3, k))
    first = np.r_[True, segment[1:] != segment[:-1]]
    innov = e * (noise.sigma * np.sqrt(1 - noise.phi ** 2))[None, :, None]
    innov[first] = e[first] * noise.sigma[None, :, None]
    out = np.empty_like(e)
    starts = np.flatnonzero(first)
    for a, b in zip(starts, np.r_[starts[1:], n]):
        for j in range(3):
            out[a:b, j] = signal.lfilter([1.0], [1.0, -noise.phi[j]], innov[a:b, j], axis=0)
    return out + rng.normal(size=(n, 3, k)) * noise.white[None, :, None]


# --------------------------------------------------------------------------------------------------
# The linear twin: nominal Jacobian and effect regressors (N, 3, p)
# --------------------------------------------------------------------------------------------------

@dataclass
class Nominal:
    """The nominal fit the twin is linearised around."""

    M: np.ndarray
    b: np.ndarray
    v: np.ndarray  # unit field in the table's base frame
    basis: np.ndarray  # (2, 3) tangent directions of v

    def body_field(self, ctx: Context) -> np.ndarray:
        return np.einsum("nji,j->ni", ctx.R, self.v)

    def predict(self, ctx: Context) -> np.ndarray:
        return self.body_field(ctx) @ self.M.T + self.b


def fit_nominal(ctx: Context, mag: np.ndarray) -> Nominal:
    """The nominal joint fit; attitudes that cannot determine every parameter still give the best fit
    (the undetermined combinations stay in the nominal Jacobian's null space and are never tested)."""
    try:
        f = es.joint_magnetometer(ctx.R, mag)
    except es.InsufficientData:
        f = es._fix_sign(es.fit_vector_sensor(ctx.R, mag, es._sphere_starts()))
    return Nominal(f.M, f.b, f.v, f.basis)


def nominal_columns(ctx: Context, nom: Nominal) -> np.ndarray:
    """d(raw)/d[M (9, row-major), b (3), field direction (2)]: (N, 3, 14)."""
    n = len(ctx.t)
    h = nom.body_field(ctx)
    J = np.zeros((n, 3, 14))
    for i in range(3):
        J[:, i, 3 * i: 3 * i + 3] = h
        J[:, i, 9 + i] = 1.0
    dh = np.einsum("nji,kj->nki", ctx.R, nom.basis)  # (N, 2, 3)
    J[:, :, 12:14] = np.einsum("ij,nkj->nik", nom.M, dh)
    return J


def _through_M(nom: Nominal, dh: np.ndarray) -> np.ndarray:
    """Raw-count columns from body-field columns (N, 3, p): M dh."""
    return np.einsum("ij,njp->nip", nom.M, dh)


def _stage_Q(ctx: Context, stage: str) -> np.ndarray:
    theta, phi = ctx.ang[:, 1], ctx.ang[:, 2]
    from physics.frames import rot_x, rot_y
    if stage == "outer":
        return np.transpose(rot_y(theta) @ rot_x(phi), (0, 2, 1))
    return np.transpose(rot_x(phi), (0, 2, 1))


_SYM = [np.array(m, float) for m in (
    [[1, 0, 0], [0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 1, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 0], [0, 0, 1]],
    [[0, 1, 0], [1, 0, 0], [0, 0, 0]], [[0, 0, 1], [0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 0, 1], [0, 1, 0]])]
_GRAD = [fx.gradient_matrix(np.eye(5)[i]) for i in range(5)]


def hysteresis_signs(ang: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sign of the last change larger than HYSTERESIS_STEP of each body-field component (N, 3), as the
    concealed effect defines it. Between consecutive samples the table is followed along a straight
    line in encoder angles (that is how it moves), so a reversal during an unsampled move counts."""
    signs = np.zeros((len(ang), 3))
    h = np.einsum("nji,j->ni", platform_attitude(ang[:, 0], ang[:, 1], ang[:, 2]), v)
    anchor, sign = h[0].copy(), np.zeros(3)
    for i in range(len(h)):
        path = h[i:i + 1]
        step = ang[i] - ang[i - 1] if i > 0 else np.zeros(3)
        if np.max(np.abs(step)) > 1.0:
            steps = int(min(90, np.ceil(np.max(np.abs(step)))))
            a = ang[i - 1] + np.linspace(0, 1, steps + 1)[1:, None] * step
            path = np.einsum("nji,j->ni", platform_attitude(a[:, 0], a[:, 1], a[:, 2]), v)
        for p in path:
            d = p - anchor
            moved = np.abs(d) > fx.HYSTERESIS_STEP
            sign = np.where(moved, np.sign(d), sign)
            anchor = np.where(moved, p, anchor)
        signs[i] = sign
    return signs


def effect_columns(ctx: Context, nom: Nominal, temp: np.ndarray | None) -> dict[str, tuple[np.ndarray, list[str], str | None]]:
    """Regressors (N, 3, p) of every catalogue effect (and stage variants), with parameter labels, or the
    reason the effect cannot be tested on this recording."""
    h = nom.body_field(ctx)
    pred = nom.predict(ctx)
    k = np.linalg.norm(nom.M, axis=1)
    n = len(ctx.t)
    tilted = np.any(np.abs(wrap180(ctx.ang[:, 1:])) > 5.0)
    # angles from an attitude reference (a hand-held unit tracked optically) are not a turntable's
    source = ctx.rec.meta.get(ATTITUDE_SOURCE_KEY, "turntable")
    no_table = None if source == "turntable" else f"needs a turntable (the angles come from: {source})"
    out: dict[str, tuple[np.ndarray, list[str], str | None]] = {}
    none = np.zeros((n, 3, 0))
    for stage in fx.STAGES:
        Q = _stage_Q(ctx, stage)
        why = no_table or (None if tilted else "needs poses tilted about the inner axes")
        out[f"stage_hard_iron:{stage}"] = (_through_M(nom, Q), ["m[0]", "m[1]", "m[2]"], why)
        soft = np.stack([np.einsum("nij,jk,nlk,nl->ni", Q, E, Q, h) for E in _SYM], axis=2)
        out[f"stage_soft_iron:{stage}"] = (_through_M(nom, soft), ["Axx", "Ayy", "Azz", "Axy", "Axz", "Ayz"], why)
    u = (pred - nom.b) / k
    out["nonlinearity"] = (np.stack([np.eye(3)[j] * u[:, j:j + 1] ** 3 for j in range(3)], axis=2),
                           ["c3[0]", "c3[1]", "c3[2]"], None)
    if temp is not None and np.all(np.isfinite(temp)) and np.ptp(temp) > 0.05:
        tc = (temp - temp.mean())[:, None, None] * np.eye(3)[None]
        out["temperature_drift"] = (tc, ["bias_per_c[0]", "bias_per_c[1]", "bias_per_c[2]"], None)
    else:
        out["temperature_drift"] = (none, [], "needs temp_c that changes during the run")
    tt = ctx.t - ctx.t.mean()
    drift = np.einsum("nji,jk->nik", ctx.R, np.eye(3)) * tt[:, None, None]
    out["field_drift"] = (_through_M(nom, drift), ["rate_per_s[0]", "rate_per_s[1]", "rate_per_s[2]"], None)
    moving = ctx.moving.sum()
    if moving >= 20:
        dpred = np.zeros_like(pred)
        for s in np.unique(ctx.segment[ctx.moving]):
            i = np.flatnonzero(ctx.segment == s)
            if len(i) >= 2:
                dpred[i] = np.gradient(pred[i], _strict(ctx.t[i], ctx.rate_hz), axis=0)
        out["time_lag"] = (-dpred[:, :, None], ["lag_s"], None)
    else:
        out["time_lag"] = (none, [], "needs samples taken while the table turns (a characterize run)")
    s = hysteresis_signs(ctx.ang, nom.v)
    if np.any(s > 0) and np.any(s < 0):
        out["hysteresis"] = (_through_M(nom, np.stack([np.eye(3)[j] * s[:, j:j + 1] for j in range(3)], axis=2)),
                             ["offset[0]", "offset[1]", "offset[2]"], None)
    else:
        out["hysteresis"] = (none, [], "needs holds approached from both sides")
    cols = []
    for g in ((1e-3, 0, 0, 0), (0, 1e-3, 0, 0), (0, 0, 1e-3, 0), (0, 0, 0, 1e-3)):
        geo = TableGeometry(nonperp_deg=(g[0], g[1]), encoder_zero_deg=(0.0, g[2], g[3]))
        Rg = platform_attitude(ctx.ang[:, 0], ctx.ang[:, 1], ctx.ang[:, 2], geo)
        cols.append((np.einsum("nji,j->ni", Rg, nom.v) @ nom.M.T + nom.b - pred) / 1e-3)
    out["table_axis_error"] = (np.stack(cols, axis=2), ["nonperp_deg[0]", "nonperp_deg[1]", "encoder_zero_deg[0]",
                                                        "encoder_zero_deg[1]"],
                               no_table or (None if tilted else "needs poses tilted about the inner axes"))
    grad = [np.einsum("nji,jk,nkl,l->ni", ctx.R, G, ctx.R, e) for G in _GRAD for e in np.eye(3)]
    out["field_gradient"] = (_through_M(nom, np.stack(grad, axis=2)),
                             [f"G{g}*r{r}" for g in ("xx", "yy", "xy", "xz", "yz") for r in "xyz"], no_table)
    return out


def generic_columns(ctx: Context, nom: Nominal, temp: np.ndarray | None) -> dict[str, np.ndarray]:
    """Regressors of structure no catalogue entry has to explain: 'unexplained structure against <input>'."""
    n = len(ctx.t)
    out: dict[str, np.ndarray] = {}

    def per_axis(f: np.ndarray) -> np.ndarray:  # (N, q) -> (N, 3, 3q): each function on each axis
        return np.concatenate([f[:, None, :] * np.eye(3)[j][None, :, None] for j in range(3)], axis=2)

    for j, name in enumerate(("psi_t", "theta_t", "phi_t")):
        a = np.radians(ctx.ang[:, j])
        if np.ptp(ctx.ang[:, j]) < 30.0:
            continue
        f = np.column_stack([g(m * a) for m in HARMONICS for g in (np.cos, np.sin)])
        out[f"{name} harmonics {HARMONICS[0]}-{HARMONICS[-1]}"] = per_axis(f)
    tt = (ctx.t - ctx.t.mean()) / max(np.ptp(ctx.t), 1e-9)
    out["time (polynomial 1-3)"] = per_axis(np.column_stack([tt, tt ** 2, tt ** 3]))
    if temp is not None and np.all(np.isfinite(temp)) and np.ptp(temp) > 0.05:
        tc = (temp - temp.mean()) / np.ptp(temp)
        out["temperature (polynomial 1-2)"] = per_axis(np.column_stack([tc, tc ** 2]))
    if ctx.moving.sum() >= 20:
        w = ctx.rate / 30.0
        out["table rate"] = per_axis(np.column_stack([w, np.abs(w)]))
    acc = ctx.rec.acc
    if acc is not None and np.all(np.isfinite(acc)):
        f_nom = np.einsum("nji,j->ni", ctx.R, SPECIFIC_FORCE_L)
        a = (acc - acc.mean(axis=0)) / np.maximum(acc.std(axis=0), 1e-9)
        out["accelerometer"] = per_axis(np.column_stack([a, a * a, f_nom * f_nom]))
    return out


# --------------------------------------------------------------------------------------------------
# Tests on the whitened linear twin
# --------------------------------------------------------------------------------------------------

def _orth(A: np.ndarray, rcond: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the column space of A (rank-revealing)."""
    if A.shape[1] == 0:
        return A
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > rcond * max(s[0], 1e-300)] if s.size else U[:, :0]


def _complement(X: np.ndarray, Q: np.ndarray, rcond: float = 1e-6) -> np.ndarray:
    """Orthonormal basis of what X adds beyond span(Q) (Q orthonormal). Directions that are mostly in
    span(Q) (kept fraction below sqrt(rcond)) count as absorbed."""
    if X.shape[1] == 0:
        return X
    norm = np.linalg.norm(X, axis=0)
    Xn = X[:, norm > 0] / norm[norm > 0]
    Xp = Xn - Q @ (Q.T @ Xn)
    U, s, _ = np.linalg.svd(Xp, full_matrices=False)
    return U[:, s > 1e-3]


@dataclass
class Test:
    """One nested test: what the columns add to the current model."""

    name: str
    basis: np.ndarray  # (3N, df) orthonormal, orthogonal to the current model
    statistic: float = 0.0
    bartlett: float = 1.0
    p_value: float = 1.0
    p_adjusted: float = 1.0
    log_p: float = 0.0  # natural log of the corrected p: ranks tests whose p underflows to 0

    @property
    def df(self) -> int:
        return int(self.basis.shape[1])


def _score(tests: list[Test], y: np.ndarray, null: np.ndarray | None, extra: int = 0) -> None:
    """Statistic, null-calibrated chi-square p and Bonferroni p of every test on whitened residual y.

    ``null`` holds whitened null residuals (K, 3N) from simulations; the statistic's null distribution
    is taken as c chi2(nu) with the mean and variance of the simulated statistics (Satterthwaite): the
    scale c is the Bartlett factor, and a smaller nu carries the heavier tail that an uncertain noise
    estimate gives. ``extra`` counts other tests of the same round (the mains line search) in the
    correction."""
    m = sum(1 for t in tests if t.df > 0) + extra
    for t in tests:
        if t.df == 0:
            continue
        t.statistic = float(np.sum((t.basis.T @ y) ** 2))
        c, nu = 1.0, float(t.df)
        if null is not None and len(null) >= 20:
            sims = np.sum((null @ t.basis) ** 2, axis=1)
            mean = float(np.mean(sims))
            t.bartlett = mean / t.df
            c = max(t.bartlett, 0.5)
            if len(null) >= 100:  # enough nulls to measure the spread as well as the scale
                c = max(float(np.var(sims, ddof=1)) / (2.0 * mean), 0.5)
                nu = float(np.clip(mean / c, 0.5, 10.0 * t.df))
        t.p_value = float(stats.chi2.sf(t.statistic / c, nu))
        t.p_adjusted = float(min(1.0, t.p_value * m))
        t.log_p = float(min(0.0, chi2_logsf(t.statistic / c, nu) + np.log(m)))


def chi2_logsf(x: float, df: float) -> float:
    """log of the chi-square tail, finite far beyond where scipy's underflows (Wilson-Hilferty there)."""
    v = float(stats.chi2.logsf(x, df))
    if np.isfinite(v):
        return v
    z = ((x / df) ** (1 / 3) - (1 - 2 / (9 * df))) / np.sqrt(2 / (9 * df))
    return float(stats.norm.logsf(z))


def _null_residuals(ctx: Context, noise: NoiseModel, Q: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """K whitened null residuals (K, 3N): noise simulated from the model at the recording's time
    stamps, re-estimated as the analysis does, whitened with that estimate, the nominal model projected
    out."""
    n = len(ctx.t)
    e = simulate_noise(n, noise, ctx.segment, rng, k)  # (N, 3, K)
    z = _whiten_each(e, estimate_noise(e, ctx), ctx.segment)
    Z = z.transpose(1, 0, 2).reshape(3 * n, k)  # axis-major rows, as whiten_all stacks them
    Z -= Q @ (Q.T @ Z)
    return Z.T


# --- mains: a line in the spectrum -----------------------------------------------------------------

def line_search(r: np.ndarray, ctx: Context, noise: NoiseModel) -> dict[str, float]:
    """Strongest spectral line common to the three axes in residual ``r`` (N, 3).

    The Fourier sum over every sample, sum_n r_n exp(-2 pi i f t_n), is exact for any time stamps: each
    segment (uniformly sampled) is one FFT on a common frequency grid, shifted by its start time. Each
    axis's periodogram is divided by the local noise level: the AR(1) spectrum of the noise estimate
    times the running median of the ratio (so any smooth colour is allowed); 2 sum_j P_j / S_j is then
    chi-square(6) at one frequency, and p is corrected for the number of frequencies searched."""
    span = float(ctx.t[-1] - ctx.t[0])
    nfft = int(2 ** np.ceil(np.log2(max(2.0 * span * ctx.rate_hz, 64))))
    f = np.fft.rfftfreq(nfft, 1.0 / ctx.rate_hz)
    X = np.zeros((len(f), 3), complex)
    for s in np.unique(ctx.segment):
        i = np.flatnonzero(ctx.segment == s)
        if len(i) < 2:
            continue
        # each run's own mean removed: a line lives inside the holds, while every slow effect moves
        # whole holds and would otherwise pass for a low-frequency line
        x = r[i] - r[i].mean(axis=0)
        X += np.fft.rfft(x, nfft, axis=0) * np.exp(-2j * np.pi * f * (ctx.t[i[0]] - ctx.t[0]))[:, None]
    P = np.abs(X) ** 2
    lo = 3.0 / max(span, 1e-9)
    keep = (f >= lo) & (f < ctx.rate_hz / 2 - 2 * (f[1] - f[0]))
    if keep.sum() < 50:
        return {"statistic": 0.0, "p_value": 1.0, "log_p": 0.0, "alias_hz": float("nan"), "independent": 0}
    ar = noise.spectrum(f, ctx.rate_hz)
    S = ar * np.column_stack([_running_median(P[:, j] / ar[:, j], 101) for j in range(3)]) / np.log(2.0)
    stat = 2.0 * np.sum(P / np.maximum(S, 1e-300), axis=1)
    stat[~keep] = 0.0
    i = int(np.argmax(stat))
    # gapped sampling makes the periodogram vary on the grid's own scale: on simulated white nulls the
    # maximum behaves like twice as many independent frequencies as grid points searched
    n_ind = max(1, int(2 * keep.sum()))
    # refine the peak between grid points: the exact Fourier sum on a fine local grid (a frequency
    # off by a fraction of a bin loses the phase over a long run)
    fine = f[i] + np.linspace(-1.5, 1.5, 61) * (f[1] - f[0])
    tt = ctx.t - ctx.t[0]
    E = np.exp(-2j * np.pi * np.outer(fine, tt))
    power = np.sum(np.abs(E @ r) ** 2, axis=1)
    f_best = float(fine[int(np.argmax(power))])
    log_p1 = chi2_logsf(stat[i], 6)
    p = float(-np.expm1(n_ind * np.log1p(-min(np.exp(log_p1), 1 - 1e-16))))
    # log p for ranking; when p1 is tiny, p = n_ind p1
    log_p = float(np.log(p)) if p > 1e-300 else float(log_p1 + np.log(n_ind))
    return {"statistic": float(stat[i]), "p_value": p, "log_p": log_p, "alias_hz": f_best, "independent": n_ind}


def _running_median(x: np.ndarray, width: int) -> np.ndarray:
    from scipy.ndimage import median_filter
    return median_filter(x, size=width, mode="mirror")


def mains_columns(ctx: Context, f_hz: float) -> np.ndarray:
    """cos/sin at ``f_hz`` on each axis: (N, 3, 6)."""
    w = 2 * np.pi * f_hz * ctx.t  # phase referred to t = 0 of the recording
    f = np.column_stack([np.cos(w), np.sin(w)])
    return np.concatenate([f[:, None, :] * np.eye(3)[j][None, :, None] for j in range(3)], axis=2)


# --------------------------------------------------------------------------------------------------
# The analysis
# --------------------------------------------------------------------------------------------------

def analyze(rec: Recording, calibration: Calibration | None = None, *, alpha: float = 0.01, null_sims: int = 200,
            rng: np.random.Generator | None = None, progress: Progress | None = None) -> Analysis:
    """Locate, name and model where ``rec`` departs from the nominal twin (module docstring).

    ``calibration`` (optional) is the unit's calibration as the nominal model: its parameters are
    compared with this recording's fit ("parameter_shift"). ``null_sims`` simulated nulls calibrate
    the tests; ``alpha`` is the family-wise false-alarm rate of the verdict.
    """
    # many small matrix products: several BLAS threads fight over the cores and run 5-10x slower
    with threadpool_limits(1):
        if not rec.has_angles:
            from physics.handheld import analyze_attitude_free
            return analyze_attitude_free(rec, alpha=alpha, null_sims=null_sims, rng=rng, progress=progress)
        return _analyze_table(rec, calibration, alpha, null_sims, rng, progress)


def _analyze_table(rec: Recording, calibration: Calibration | None, alpha: float, null_sims: int,
                   rng: np.random.Generator | None, progress: Progress | None) -> Analysis:
    if len(rec) < MIN_SAMPLES:
        raise RecordingError(f"the analysis needs at least {MIN_SAMPLES} samples (10 s at 20 Hz), got {len(rec)}")
    rng = rng if rng is not None else np.random.default_rng(0)
    say = progress or (lambda stage, frac: None)
    notes: list[str] = []
    if len(rec) > MAX_SAMPLES:
        k = int(np.ceil(len(rec) / MAX_SAMPLES))
        rec = decimate(rec, k)
        notes.append(f"{k} consecutive samples averaged into one ({len(rec)} left) to keep the analysis fast")
    say("compare: nominal fit", 0.0)
    ctx = context(rec)
    y_raw = np.asarray(rec.mag, float)
    nom = fit_nominal(ctx, y_raw)
    r0 = y_raw - nom.predict(ctx)
    temp = rec.temp_c

    say("noise floor", 0.15)
    noise = estimate_noise(r0, ctx)
    J0 = nominal_columns(ctx, nom)
    eff = effect_columns(ctx, nom, temp)
    gen = generic_columns(ctx, nom, temp)
    untestable = [{"effect": name.split(":")[0], "reason": why} for name, (_, _, why) in eff.items() if why]
    untestable = [dict(t) for t in {(u["effect"], u["reason"]): u for u in untestable}.values()]
    n_round1 = len([1 for X, _, why in eff.values() if not why]) + len(gen) + 1

    # Mains first: a line hides under the smooth effects' tests but biases the noise estimate they rely
    # on, so once found it is fitted and the noise re-estimated without it.
    say("spectral lines", 0.25)
    all_tests: list[dict[str, Any]] = []
    selected: list[str] = []
    mains_hz: float | None = None
    line = line_search(r0, ctx, noise)
    chosen = line["log_p"] + np.log(n_round1) < np.log(alpha)
    all_tests.append({"effect": "mains_interference", "variant": f"line at {line['alias_hz']:.4f} Hz", "round": 1,
                      "statistic": line["statistic"], "df": 6, "bartlett": 1.0, "p_value": line["p_value"],
                      "p_adjusted": min(1.0, line["p_value"] * n_round1), "selected": bool(chosen), "generic": False})
    if chosen:
        mains_hz = line["alias_hz"]
        Xm = mains_columns(ctx, mains_hz)
        coef_m, *_ = np.linalg.lstsq(Xm.transpose(1, 0, 2).reshape(-1, 6), r0.T.ravel(), rcond=None)
        noise = estimate_noise(r0 - np.einsum("nip,p->ni", Xm, coef_m), ctx)
        selected.append("mains_interference")

    A0 = whiten_all(J0, noise, ctx.segment)
    Q0 = _orth(A0)
    zr = whiten_all(r0, noise, ctx.segment)
    z = zr - Q0 @ (Q0.T @ zr)
    candidates = {name: whiten_all(X, noise, ctx.segment) for name, (X, _, why) in eff.items() if not why}
    if mains_hz is not None:
        candidates["mains_interference"] = whiten_all(mains_columns(ctx, mains_hz), noise, ctx.segment)
    generic_w = {name: whiten_all(X, noise, ctx.segment) for name, X in gen.items()}

    say("null simulations", 0.35)
    null = _null_residuals(ctx, noise, Q0, null_sims, rng) if null_sims > 0 else None

    say("tests", 0.55)
    Q = _orth(np.column_stack([A0] + [candidates[s] for s in selected]))
    resid = z - Q @ (Q.T @ z)
    for round_no in range(MAX_EFFECTS):
        tests = {name: Test(name, _complement(Xw, Q)) for name, Xw in candidates.items() if name not in selected}
        gtests = {name: Test(name, _complement(Xw, Q)) for name, Xw in generic_w.items()} if round_no == 0 else {}
        # round 1's family also holds the line search
        _score(list(tests.values()) + list(gtests.values()), resid, null, extra=1 if round_no == 0 else 0)
        best_name, best_log = None, np.log(alpha)
        for name, t in tests.items():
            if t.df > 0 and t.log_p < best_log:
                best_name, best_log = name, t.log_p
        if best_name is not None:
            best_name = _simplest(best_name, tests, candidates, Q, resid, null, alpha, len(tests) + len(gtests) + 1)
        all_tests += [_row(t, round_no + 1, selected=name == best_name, generic=name in gtests)
                      for name, t in {**tests, **gtests}.items()]
        if best_name is None:
            break
        selected.append(best_name)
        Q = _orth(np.column_stack([A0] + [candidates[s] for s in selected]))
        resid = z - Q @ (Q.T @ z)
    generic_first = {row["variant"]: row for row in all_tests if row["generic"]}

    # Backward check: forward selection can take a many-parameter effect first that only stands in for
    # a simpler one chosen after it. Each effect must stay significant given all the others (same
    # correction as the first round); the weakest that does not is dropped, until all do.
    final: dict[str, Test] = {}
    while selected:
        final = {}
        for name in selected:
            others = [candidates[o] for o in selected if o != name]
            Qo = _orth(np.column_stack([A0, *others]))
            t = Test(name, _complement(candidates[name], Qo))
            _score([t], z - Qo @ (Qo.T @ z), null, extra=n_round1 - 1)
            final[name] = t
        weakest = max(selected, key=lambda nm: final[nm].log_p)
        if final[weakest].log_p < np.log(alpha):
            break
        selected.remove(weakest)
        all_tests.append(_row(final[weakest], "backward", dropped=True))

    say("model: refit with the effects", 0.7)
    # final linear fit (whitened) of nominal + selected effects, for parameters and sigmas
    parts = [A0] + [candidates[s] for s in selected]
    A = np.column_stack(parts)
    coef, cov = _lstsq_cov(A, zr)
    raw_cols = [J0] + [(mains_columns(ctx, mains_hz) if s == "mains_interference" else eff[s][0]) for s in selected]
    Xraw = np.concatenate(raw_cols, axis=2)
    fitted = np.einsum("nip,p->ni", Xraw, coef)
    r_after = r0 - fitted
    offsets = np.cumsum([0] + [b.shape[1] for b in parts])

    # generic tests again on the final residual: what no catalogue entry explains
    unexplained = [row for row in generic_first.values() if row["p_adjusted"] < alpha]
    if selected:
        Qf = _orth(A)
        zf = zr - Qf @ (Qf.T @ zr)
        gt = [Test(name, _complement(Xw, Qf)) for name, Xw in generic_w.items()]
        _score(gt, zf, null)
        unexplained = [_row(t, "final", generic=True) for t in gt if t.df > 0 and t.p_adjusted < alpha]

    say("held-out", 0.8)
    fold = _folds(ctx)
    pred_before = _heldout(ctx, y_raw, nom, [J0], fold, noise.floor)
    pred_after = _heldout(ctx, y_raw, nom, raw_cols, fold, noise.floor)
    rms = lambda r: np.sqrt(np.mean(r * r, axis=0))  # noqa: E731
    ho_before, ho_after = rms(y_raw - pred_before), rms(y_raw - pred_after)

    say("name and rank", 0.9)
    findings = []
    for i, name in enumerate(selected):
        c = coef[offsets[i + 1]:offsets[i + 2]]
        cv = cov[offsets[i + 1]:offsets[i + 2], offsets[i + 1]:offsets[i + 2]]
        contrib = np.einsum("nip,p->ni", raw_cols[i + 1], c)
        t = final[name]  # the effect's test given every other effect kept
        row = {"statistic": t.statistic, "df": t.df, "p_value": t.p_value, "p_adjusted": t.p_adjusted}
        confusable = _confusable(name, selected, candidates, A0, z, alpha) if name != "mains_interference" else []
        findings.append(_finding(name, c, cv, eff, row, contrib, nom, ctx, y_raw, confusable, mains_hz))
    for row in unexplained:
        findings.append({"effect": fx.UNEXPLAINED, **{k: row[k] for k in ("statistic", "df", "p_value", "p_adjusted")},
                         "parameters": {}, "sigma": {}, "heading_impact_deg": None, "where": {"against": row["variant"]},
                         "explanation": f"unexplained structure against {row['variant']}: no catalogue entry accounts for it",
                         "confusable_with": [], "separating_experiment": ""})
    findings.extend(_parameter_findings(nom, calibration, A0, ctx))
    findings.sort(key=lambda f: (f["effect"] in (fx.UNEXPLAINED, fx.PARAMETER_SHIFT), -(f["heading_impact_deg"] or 0.0)))

    heading_before = _heading_error(ctx, y_raw, nom)
    # after: the nominal parameters as refitted together with the effects, on readings with the
    # fitted effects taken out (what a compass that also corrected them would report)
    v_after = nom.v + coef[12:14] @ nom.basis
    nom_after = Nominal(nom.M + coef[:9].reshape(3, 3), nom.b + coef[9:12], v_after / np.linalg.norm(v_after), nom.basis)
    heading_after = _heading_error(ctx, y_raw - (fitted - np.einsum("nip,p->ni", J0, coef[:14])), nom_after)
    result: dict[str, Any] = {
        "verdict": "discrepancy" if findings else "consistent",
        "model": "table",
        "samples": int(len(rec)),
        "duration_s": float(np.ptp(ctx.t)),
        "alpha": alpha,
        "noise_floor_lsb": noise.floor.tolist(),
        "noise_ar1": noise.phi.tolist(),
        "noise_white_lsb": noise.white.tolist(),
        "residual_rms_before_lsb": rms(r0).tolist(),
        "residual_rms_after_lsb": rms(r_after).tolist(),
        "heldout": {"scheme": "4 folds: whole holds (or 1-s chunks with fewer than 8 holds) and 1-s chunks of motion, "
                           "interleaved in time",
                    "rms_before_lsb": ho_before.tolist(), "rms_after_lsb": ho_after.tolist(),
                    "improvement_pct": float(100.0 * (1.0 - ho_after.mean() / max(ho_before.mean(), 1e-300)))},
        "heading_error_deg": {"before": heading_before, "after": heading_after},
        "nominal": _nominal_json(nom),
        "findings": findings,
        "tests": all_tests,
        "untestable": untestable,
        "locate": locate(ctx, r0, noise.floor, candidates, Q0, z, null, generic_first),
        "notes": notes,
    }
    say("done", 1.0)
    # the rows analysed (the recording's, or their block averages when it was decimated)
    series = {"t": ctx.t, "step": rec.step, "psi_t": rec.psi_t, "theta_t": rec.theta_t, "phi_t": rec.phi_t, "mag": y_raw,
              "residual_before": r0, "residual_after": r_after, "heldout_pred_before": pred_before,
              "heldout_pred_after": pred_after, "fold": fold}
    return Analysis(json_safe(result), series)


def _row(t: Test, round_: int | str, selected: bool = False, generic: bool = False, **extra: Any) -> dict[str, Any]:
    """One test as the report lists it."""
    return {"effect": t.name.split(":")[0], "variant": t.name, "round": round_, "statistic": t.statistic, "df": t.df,
            "bartlett": t.bartlett, "p_value": t.p_value, "p_adjusted": t.p_adjusted, "selected": selected,
            "generic": generic, **extra}


def _simplest(best: str, tests: dict[str, "Test"], candidates: dict[str, np.ndarray], Q: np.ndarray, resid: np.ndarray,
              null: np.ndarray | None, alpha: float, m: int) -> str:
    """The effect to add: ``best`` (smallest corrected p), unless an effect with fewer parameters is
    significant too and, once in the model, leaves nothing significant for ``best`` to add; then the
    simplest such one. Smallest p alone favours the effect with more parameters whenever it contains a
    simpler one (soft iron on a stage spans a magnet on it at one azimuth)."""
    simpler = sorted((t.df, t.log_p, name) for name, t in tests.items()
                     if 0 < t.df < tests[best].df and t.log_p < np.log(alpha))
    for _, _, name in simpler:
        Qs = _orth(np.column_stack([Q, candidates[name]]))
        given = Test(best, _complement(candidates[best], Qs))
        _score([given], resid - Qs @ (Qs.T @ resid), null, extra=m - 1)
        if given.df == 0 or given.log_p >= np.log(alpha):
            return name
    return best


def _lstsq_cov(A: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares on whitened data with the coefficients' covariance. A combination the design
    cannot determine (e.g. an effect's component the nominal model absorbs) gets the minimum-norm
    estimate and infinite variance on every coefficient it involves."""
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    An = A / scale
    U, s, Vt = np.linalg.svd(An, full_matrices=False)
    keep = s > 1e-9 * s[0]
    inv = np.zeros_like(s)
    inv[keep] = 1.0 / s[keep]
    coef = (Vt.T * inv) @ (U.T @ y) / scale
    cov = (Vt.T * inv ** 2) @ Vt / np.outer(scale, scale)
    if not keep.all():
        lost = np.max(np.abs(Vt[~keep]), axis=0) > 0.05
        cov[lost, :] = cov[:, lost] = 0.0
        cov[lost, lost] = np.inf
    return coef, cov


def _confusable(name: str, selected: list[str], candidates: dict[str, np.ndarray], A0: np.ndarray, z: np.ndarray,
                alpha: float) -> list[str]:
    """Other effects that, put in the model instead, leave ``name`` insignificant while being
    significant themselves: this recording cannot tell them apart."""
    out = []
    others = [s for s in selected if s != name]
    base = np.column_stack([A0] + [candidates[s] for s in others]) if others else A0
    Qb = _orth(base)
    zb = z - Qb @ (Qb.T @ z)
    own = Test(name, _complement(candidates[name], Qb))
    _score([own], zb, None)
    for other, Xw in candidates.items():
        if other in selected or other.split(":")[0] == name.split(":")[0] or other == "mains_interference":
            continue
        alone = Test(other, _complement(Xw, Qb))
        if alone.df == 0:
            continue
        _score([alone], zb, None)
        if alone.p_value > alpha / 10:
            continue
        Qo = _orth(np.column_stack([base, Xw]))
        given = Test(name, _complement(candidates[name], Qo))
        _score([given], z - Qo @ (Qo.T @ z), None)
        if given.df == 0 or given.p_value > alpha:
            out.append(other.split(":")[0])
    return sorted(set(out))


def _finding(name: str, c: np.ndarray, cv: np.ndarray, eff: dict, row: dict, contrib: np.ndarray, nom: Nominal,
             ctx: Context, y: np.ndarray, confusable: list[str], mains_hz: float | None) -> dict[str, Any]:
    effect, _, stage = name.partition(":")
    entry = fx.CATALOGUE[effect]
    sd = np.sqrt(np.maximum(np.diag(cv), 0.0))  # inf: not determined by this recording (absorbed)
    params: dict[str, Any] = {}
    sigma: dict[str, Any] = {}
    if effect == "mains_interference":
        # a cos(w t + phase) = a cos(phase) cos(w t) - a sin(phase) sin(w t); one phase for the pickup
        # direction, signed amplitudes per axis
        a = np.hypot(c[0::2], c[1::2])
        ph = np.arctan2(-c[1::2], c[0::2])
        ref = float(ph[np.argmax(a)])
        signed = a * np.sign(np.cos(ph - ref))
        params = {"amplitude_lsb": signed.tolist(), "alias_hz": mains_hz, "phase_rad": ref}
        sigma = {"amplitude_lsb": np.sqrt((sd[0::2] ** 2 + sd[1::2] ** 2) / 2).tolist()}
    else:
        labels = eff[name][1]
        groups: dict[str, list[int]] = {}
        for i, lab in enumerate(labels):
            groups.setdefault(lab.split("[")[0], []).append(i)
        for key, idx in groups.items():
            params[key] = c[idx].tolist() if len(idx) > 1 or "[" in labels[idx[0]] else float(c[idx[0]])
            sigma[key] = sd[idx].tolist() if len(idx) > 1 or "[" in labels[idx[0]] else float(sd[idx[0]])
        if effect == "stage_soft_iron":
            params = {"A": _sym(c).tolist()}
            sigma = {"A": _sym(sd).tolist()}
        if effect == "field_gradient":
            params = {"gradient_times_offset": c.tolist(), "labels": labels}
            sigma = {"gradient_times_offset": sd.tolist()}
        if stage:
            params["stage"] = stage
    impact = _heading_impact(ctx, y, nom, contrib)
    plausible = {k: v for k, v in entry.plausible.items() if k in params}
    implausible = [k for k, lim in plausible.items() if np.max(np.abs(np.asarray(params[k], float))) > lim]
    where = _where(effect, stage, ctx, contrib)
    explanation = f"{entry.title}: {entry.description} Signature: {entry.signature}."
    if np.isinf(sd).any():
        labels = eff[name][1] if name in eff else []
        lost = [labels[i] for i in np.flatnonzero(np.isinf(sd))] if labels else []
        explanation += (f" This recording cannot determine {', '.join(lost)} (the nominal model absorbs that part; "
                        f"sigma null): {entry.needs}.")
    if implausible:
        explanation += f" The fitted {', '.join(implausible)} exceed what is plausible for this effect."
    return {"effect": effect, "statistic": row["statistic"], "df": row["df"], "p_value": row["p_value"],
            "p_adjusted": row["p_adjusted"], "parameters": params, "sigma": sigma, "heading_impact_deg": impact,
            "where": where, "explanation": explanation, "confusable_with": confusable,
            "separating_experiment": "; ".join(fx.separating_experiment(effect, o) for o in confusable)}


def _sym(a6: np.ndarray) -> np.ndarray:
    """3x3 symmetric from (xx, yy, zz, xy, xz, yz), infinities allowed (undetermined sigmas)."""
    return sum(x * E for x, E in zip(a6, _SYM)) if np.all(np.isfinite(a6)) else np.array(
        [[a6[0], a6[3], a6[4]], [a6[3], a6[1], a6[5]], [a6[4], a6[5], a6[2]]])


def _where(effect: str, stage: str, ctx: Context, contrib: np.ndarray) -> dict[str, Any]:
    """Where the fitted effect acts: axis, steps, frame, and for motion effects the direction of travel."""
    rms_axis = np.sqrt(np.mean(contrib ** 2, axis=0))
    steps = {}
    for s in np.unique(ctx.rec.step):
        m = ctx.rec.step == s
        steps[str(s)] = float(np.sqrt(np.mean(contrib[m] ** 2)))
    frame = {"stage_hard_iron": f"{stage} stage", "stage_soft_iron": f"{stage} stage", "nonlinearity": "sensor",
             "temperature_drift": "sensor", "field_drift": "lab", "time_lag": "sensor (timing)",
             "hysteresis": "body", "table_axis_error": "table geometry", "field_gradient": "lab (position)",
             "mains_interference": "sensor"}[effect]
    out: dict[str, Any] = {"axis": "xyz"[int(np.argmax(rms_axis))], "rms_lsb": rms_axis.tolist(),
                           "steps": dict(sorted(steps.items(), key=lambda kv: -kv[1])[:5]), "frame": frame}
    if effect == "time_lag" and ctx.moving.any():
        w = ctx.rate[:, 0] if np.ptp(ctx.rate[:, 0]) > 0 else ctx.rate.sum(axis=1)
        out["direction"] = {"positive_rate_rms_lsb": float(np.sqrt(np.mean(contrib[w > 1] ** 2))) if np.any(w > 1) else None,
                            "negative_rate_rms_lsb": float(np.sqrt(np.mean(contrib[w < -1] ** 2))) if np.any(w < -1) else None}
    return out


def _level(ctx: Context) -> np.ndarray:
    return (np.abs(wrap180(ctx.ang[:, 1])) < 0.01) & (np.abs(wrap180(ctx.ang[:, 2])) < 0.01)


def _corrected_heading(raw: np.ndarray, nom: Nominal, R: np.ndarray) -> np.ndarray:
    """Heading with the nominal calibration, levelled with the table's attitude R."""
    if np.linalg.cond(nom.M) > 1e8:  # attitudes that cannot determine M (e.g. one pose): no heading
        return np.full(len(raw), np.nan)
    h = np.linalg.solve(nom.M, (raw - nom.b).T).T
    return magnetic_heading(h, np.einsum("nji,j->ni", R, SPECIFIC_FORCE_L))


def _heading_impact(ctx: Context, y: np.ndarray, nom: Nominal, contrib: np.ndarray) -> float | None:
    """Largest heading change the fitted effect makes, over the recording's attitudes within 60 deg of level."""
    ok = np.all(np.abs(wrap180(ctx.ang[:, 1:])) <= 60.0, axis=1)
    if not ok.any():
        return 0.0
    d = wrap180(_corrected_heading(y[ok], nom, ctx.R[ok]) - _corrected_heading(y[ok] - contrib[ok], nom, ctx.R[ok]))
    return float(np.max(np.abs(d))) if np.isfinite(d).all() else None


def _heading_error(ctx: Context, y: np.ndarray, nom: Nominal) -> float | None:
    """Max level heading error of hold means, with the nominal calibration, against the table."""
    lev = _level(ctx) & (ctx.hold >= 0)
    if not lev.any():
        return None
    g = ctx.hold[lev]
    n = np.bincount(g)
    keep = n > 0
    mean = np.column_stack([np.bincount(g, y[lev][:, j])[keep] / n[keep] for j in range(3)])
    first = np.flatnonzero(lev)[[np.flatnonzero(g == i)[0] for i in np.flatnonzero(keep)]]
    _, dec = field_angles(nom.v)
    err = wrap180(_corrected_heading(mean, nom, ctx.R[first]) - (ctx.ang[first, 0] - dec))
    return float(np.max(np.abs(err))) if np.isfinite(err).all() else None


def _folds(ctx: Context) -> np.ndarray:
    """Fold of each sample: whole holds interleaved (a hold is predicted from the others), motion in
    1-s chunks; a recording of fewer than 8 holds is cut into 1-s chunks throughout."""
    chunk = np.floor((ctx.t - ctx.t[0]) / 1.0).astype(int)
    if ctx.hold.max() < 7:
        return chunk % 4
    fold = np.empty(len(ctx.t), int)
    h = ctx.hold >= 0
    fold[h] = ctx.hold[h] % 4
    fold[~h] = (chunk[~h] + 1) % 4
    return fold


def _heldout(ctx: Context, y: np.ndarray, nom: Nominal, cols: list[np.ndarray], fold: np.ndarray,
             sigma: np.ndarray) -> np.ndarray:
    """Each sample predicted by the linear twin fitted to the other folds (axis-weighted least squares)."""
    X = np.concatenate(cols, axis=2)
    base = nom.predict(ctx)
    r0 = y - base
    pred = np.empty_like(y)
    for f in np.unique(fold):
        train = fold != f
        A = np.concatenate([X[train, j, :] / sigma[j] for j in range(3)], axis=0)
        b = np.concatenate([r0[train, j] / sigma[j] for j in range(3)])
        coef, _ = _lstsq_cov(A, b)
        test = ~train
        pred[test] = base[test] + np.einsum("nip,p->ni", X[test], coef)
    return pred


def _nominal_json(nom: Nominal) -> dict[str, Any]:
    M_o, k = split_matrix(nom.M)
    inc, dec = field_angles(nom.v)
    return {"M_o": M_o.tolist(), "k": k.tolist(), "bias": nom.b.tolist(), "inclination_deg": inc,
            "declination_deg": dec}


def _parameter_findings(nom: Nominal, cal: Calibration | None, A0: np.ndarray, ctx: Context) -> list[dict[str, Any]]:
    """Absorbed effects show as implausible nominal parameters, or as shifts from the unit's calibration."""
    if np.linalg.matrix_rank(A0 / np.maximum(np.linalg.norm(A0, axis=0), 1e-300), tol=1e-6) < A0.shape[1]:
        return []  # the attitudes cannot determine M, b and the field: nothing to judge them by
    M_o, k = split_matrix(nom.M)
    problems: dict[str, Any] = {}
    mis = np.degrees(np.arccos(np.clip(np.abs(np.diag(M_o)), -1, 1)))
    if mis.max() > MAX_MISALIGNMENT_DEG:
        problems["misalignment_deg"] = mis.tolist()
    if np.ptp(k) / np.median(k) > MAX_K_MISMATCH:
        problems["k_mismatch"] = float(np.ptp(k) / np.median(k))
    if np.max(np.abs(nom.b) / k) > MAX_BIAS_FIELDS:
        problems["bias_in_fields"] = (np.abs(nom.b) / k).tolist()
    shifts: dict[str, Any] = {}
    if cal is not None:
        _, cov0 = _lstsq_cov(A0, np.zeros(A0.shape[0]))
        sd_b = np.sqrt(np.maximum(np.diag(cov0)[9:12], 0.0))
        cal_sd_b = np.asarray(cal.sigma.get("bias", np.zeros(3)) if cal.sigma.get("bias") is not None else np.zeros(3), float)
        db = nom.b - cal.mag.bias
        z_b = db / np.sqrt(sd_b ** 2 + cal_sd_b ** 2 + 1.0)  # +1 LSB^2: quantisation of the stored numbers
        dk = k / cal.mag.k - 1.0
        dang = M_o_angle_change(M_o, cal.mag.M_o)
        if np.any(np.abs(z_b) > 5) and np.max(np.abs(db)) > 5:
            shifts["bias_lsb"] = db.tolist()
        if np.max(np.abs(dk)) > 0.005:
            shifts["k_relative"] = dk.tolist()
        if np.max(dang) > 0.2:
            shifts["axis_change_deg"] = dang.tolist()
    if not problems and not shifts:
        return []
    what = []
    if "bias_lsb" in shifts or "bias_in_fields" in problems:
        what.append("a magnet on the platform or near the unit, or a temperature offset, moves the bias")
    if {"k_relative", "axis_change_deg", "k_mismatch", "misalignment_deg"} & (shifts.keys() | problems.keys()):
        what.append("soft iron on the platform, or a changed mounting, moves the matrix M")
    return [{"effect": fx.PARAMETER_SHIFT, "statistic": None, "df": None, "p_value": None, "p_adjusted": None,
             "parameters": {**problems, **shifts}, "sigma": {}, "heading_impact_deg": None,
             "where": {"frame": "platform (absorbed by the nominal model)"},
             "explanation": "The nominal model absorbs this completely, so it shows as parameters, not residuals: "
                            + "; ".join(what) + ".",
             "confusable_with": [], "separating_experiment":
                 "calibrate again with the suspected part removed, or compare with the unit's calibration on another station"}]


def M_o_angle_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (deg) between corresponding sensor axes of two M_o."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def locate(ctx: Context, r0: np.ndarray, sigma: np.ndarray, candidates: dict, Q0: np.ndarray, z: np.ndarray,
           null: np.ndarray | None, generic: dict[str, dict]) -> dict[str, Any]:
    """Where the nominal residual lives: axis, step, harmonics against each angle, time, direction, frame,
    whiteness, witness channels."""
    rms = np.sqrt(np.mean(r0 ** 2, axis=0))
    by_step = []
    for s in dict.fromkeys(ctx.rec.step.tolist()):
        m = ctx.rec.step == s
        by_step.append({"step": str(s), "samples": int(m.sum()), "rms_lsb": np.sqrt(np.mean(r0[m] ** 2, axis=0)).tolist(),
                        "mean_lsb": r0[m].mean(axis=0).tolist()})
    harmonics: dict[str, Any] = {}
    for j, name in enumerate(("psi_t", "theta_t", "phi_t")):
        if np.ptp(ctx.ang[:, j]) < 30.0:
            continue
        a = np.radians(ctx.ang[:, j])
        amp = []
        for m in (1, 2, 3, 4):
            F = np.column_stack([np.cos(m * a), np.sin(m * a), np.ones_like(a)])
            coef, *_ = np.linalg.lstsq(F, r0, rcond=None)
            amp.append(np.hypot(coef[0], coef[1]).tolist())
        harmonics[name] = {"orders": [1, 2, 3, 4], "amplitude_lsb": amp}
    time: dict[str, Any] = {}
    tt = ctx.t - ctx.t.mean()
    slope = (tt @ r0) / max(tt @ tt, 1e-300)
    time["trend_lsb_per_min"] = (60.0 * slope).tolist()
    hold_keys = {}
    for h in np.unique(ctx.hold[ctx.hold >= 0]):
        i = np.flatnonzero(ctx.hold == h)
        hold_keys.setdefault(tuple(np.round(ctx.ang[i[0]], 2)), []).append(i)
    repeats = [v for v in hold_keys.values() if len(v) >= 2]
    if repeats:
        first, last = repeats[0][0], repeats[0][-1]
        time["repeated_pose"] = {"angles": list(np.round(ctx.ang[first[0]], 2)), "dt_s": float(ctx.t[last[0]] - ctx.t[first[0]]),
                                 "difference_lsb": (r0[last].mean(axis=0) - r0[first].mean(axis=0)).tolist()}
    hm = ctx.hold >= 0
    if hm.sum() > 10:
        g = ctx.hold[hm]
        n = np.bincount(g)
        ok = n > 0
        means = np.column_stack([np.bincount(g, r0[hm][:, j])[ok] / n[ok] for j in range(3)])
        c = np.cumsum(means - means.mean(axis=0), axis=0)
        k = int(np.argmax(np.sum(c ** 2, axis=1)))
        t_hold = np.bincount(g, ctx.t[hm])[ok] / n[ok]
        time["change_point_t_s"] = float(t_hold[k])
    direction: dict[str, Any] = {}
    if ctx.moving.sum() >= 20:
        w = ctx.rate
        for j, name in enumerate(("psi", "theta", "phi")):
            pos, neg = ctx.moving & (w[:, j] > 1), ctx.moving & (w[:, j] < -1)
            if pos.any() and neg.any():
                direction[name] = {"positive_mean_lsb": r0[pos].mean(axis=0).tolist(),
                                   "negative_mean_lsb": r0[neg].mean(axis=0).tolist(),
                                   "speeds_dps": sorted({float(np.round(abs(x), 0)) for x in w[ctx.moving, j] if abs(x) > 1})[:6]}
    frame = {}
    for name in ("stage_hard_iron:outer", "stage_hard_iron:middle", "field_drift", "temperature_drift"):
        if name in candidates:
            t = Test(name, _complement(candidates[name], Q0))
            _score([t], z, null)
            frame[{"stage_hard_iron:outer": "fixed in the outer stage", "stage_hard_iron:middle": "fixed in the middle stage",
                   "field_drift": "drifting in the lab frame", "temperature_drift": "drifting in the sensor frame"}[name]] = {
                "statistic": t.statistic, "df": t.df, "p_value": t.p_value}
    zz = z.reshape(3, -1)
    lb = []
    for j in range(3):
        x = zz[j] - zz[j].mean()
        ac = np.array([x[k:] @ x[:-k] for k in range(1, 11)]) / max(x @ x, 1e-300)
        n = len(x)
        q = n * (n + 2) * np.sum(ac ** 2 / (n - np.arange(1, 11)))
        lb.append({"ljung_box_q": float(q), "lags": 10, "p_value": float(stats.chi2.sf(q, 10))})
    witness = {name: {"statistic": row["statistic"], "df": row["df"], "p_value": row["p_value"]}
               for name, row in generic.items()}
    return {"by_axis": {"rms_lsb": rms.tolist(), "dominant": "xyz"[int(np.argmax(rms / sigma))]},
            "by_step": by_step, "harmonics": harmonics, "time": time, "direction": direction, "frame": frame,
            "whiteness": {"per_axis": lb}, "witness": witness}
