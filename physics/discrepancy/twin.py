"""The recording's structure (runs, holds, rates) and the linear twin around the nominal fit: the nominal
Jacobian, every catalogue effect's regressors and the generic "unexplained structure" regressors.
Pure numpy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physics import effects as fx
from physics import errorsep as es
from physics.frames import SPECIFIC_FORCE_L
from physics.heading import wrap180
from physics.recording import Recording
from physics.table import TableGeometry, platform_attitude

#: Harmonic orders searched against each table angle in the "unexplained" tests.
HARMONICS = (2, 3, 4)
#: Recording metadata key naming where the table angles come from; anything but "turntable" (e.g. an
#: optical reference tracking a hand-held unit) makes the table's own effects untestable.
ATTITUDE_SOURCE_KEY = "attitude_source"


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

