"""The recording's structure (runs, holds, rates) and the linear twin around the nominal fit: the nominal
Jacobian and the generic "unexplained structure" regressors (each catalogue effect's regressors are in
registry.py, which builds on this module). Pure numpy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physics import errorsep as es
from physics.frames import SPECIFIC_FORCE_L
from physics.recording import Recording

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
# The linear twin: nominal Jacobian and generic regressors (N, 3, p)
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


def _stage_Q(ctx: Context, stage: str) -> np.ndarray:
    """Rotations (N, 3, 3) turning ``stage``'s frame into body axes (physics.effects.stage_to_body, per sample)."""
    theta, phi = ctx.ang[:, 1], ctx.ang[:, 2]
    from physics.frames import rot_x, rot_y
    if stage == "outer":
        return np.transpose(rot_y(theta) @ rot_x(phi), (0, 2, 1))
    return np.transpose(rot_x(phi), (0, 2, 1))


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

