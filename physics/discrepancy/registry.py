"""How the analyser fits each catalogue effect: one registry keyed by effect id (issue 12).

physics/effects.py's :data:`~physics.effects.CATALOGUE` says what an effect *is*: its frame, form and
what it depends on (``Entry.model``), its plausible ranges and what a recording needs to show it. This
module says how the analyser *fits* it, one :class:`Fit` per catalogue id in :data:`REGISTRY`:

- ``table``: its regressors in the table model (analysis.py), linearised around the nominal fit, or the
  reason this recording cannot test it; an effect whose catalogue frame is ``"stage"`` is built once per
  stage of :data:`physics.effects.STAGES` (variants ``"<id>:<stage>"``);
- ``line``: instead of ``table``, for the effect the table model finds by a search over frequency
  (lrt.line_search): its columns at the frequency found;
- ``free``: its blocks in the attitude-free model (attitude_free.py), or why it needs table angles;
- ``params``: how its coefficients become parameters by name, when not grouped by label;
- ``where``: what a table-model finding adds to where the effect acts.

Adding an effect to the analyser: an ``Entry`` (and its concealment class) in physics/effects.py, and one
``Fit`` here. The concealment classes are not used here on purpose: the blind proof would not catch a
mistake the fitting and the concealing side shared (effects.py's docstring).

Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from physics import effects as fx
from physics.discrepancy.lrt import mains_columns
from physics.discrepancy.twin import ATTITUDE_SOURCE_KEY, Context, Nominal, _stage_Q, _strict
from physics.heading import wrap180
from physics.table import TableGeometry, platform_attitude

#: A table-model builder's answer: columns (N, 3, p), their parameter labels, and the reason the
#: recording cannot test the effect (None when it can; the columns may then be empty).
Columns = tuple[np.ndarray, list[str], str | None]


# --------------------------------------------------------------------------------------------------
# The table model: regressors around the nominal fit (N, 3, p), raw counts per unit of each parameter
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TableInputs:
    """What every table-model builder reads, computed once per recording and nominal fit."""

    ctx: Context
    nom: Nominal
    temp: np.ndarray | None  # temp_c, when logged
    h: np.ndarray  # (N, 3) the nominal field in body axes
    pred: np.ndarray  # (N, 3) the nominal prediction, raw counts
    k: np.ndarray  # (3,) sensitivities: row norms of M
    tilted: bool  # poses tilted about the inner axes (what tells a stage's frame from the platform's)
    no_table: str | None  # why nothing of the table can be tested (the angles are not a turntable's), or None
    lag_s: float = 0.0  # the time lag fitted so far (0: none yet): its column is the exact shift by it


def table_inputs(ctx: Context, nom: Nominal, temp: np.ndarray | None, lag_s: float = 0.0) -> TableInputs:
    """The shared inputs of the table-model builders (``lag_s``: see :func:`effect_columns`)."""
    # angles from an attitude reference (a hand-held unit tracked optically) are not a turntable's
    source = ctx.rec.meta.get(ATTITUDE_SOURCE_KEY, "turntable")
    return TableInputs(ctx, nom, temp, nom.body_field(ctx), nom.predict(ctx), np.linalg.norm(nom.M, axis=1),
                       bool(np.any(np.abs(wrap180(ctx.ang[:, 1:])) > 5.0)),
                       None if source == "turntable" else f"needs a turntable (the angles come from: {source})", lag_s)


def _through_M(nom: Nominal, dh: np.ndarray) -> np.ndarray:
    """Raw-count columns from body-field columns (N, 3, p): M dh."""
    return np.einsum("ij,njp->nip", nom.M, dh)


def _none(x: TableInputs) -> np.ndarray:
    """An empty block: the effect is not tested."""
    return np.zeros((len(x.ctx.t), 3, 0))


def _needs_tilt(x: TableInputs) -> str | None:
    """A stage's frame differs from the platform's only in poses tilted about the inner axes."""
    return x.no_table or (None if x.tilted else "needs poses tilted about the inner axes")


#: Basis of symmetric 3x3 matrices, in the order (xx, yy, zz, xy, xz, yz) of physics.effects.symmetric.
_SYM = [np.array(m, float) for m in (
    [[1, 0, 0], [0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 1, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 0], [0, 0, 1]],
    [[0, 1, 0], [1, 0, 0], [0, 0, 0]], [[0, 0, 1], [0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 0, 1], [0, 1, 0]])]
#: Basis of traceless symmetric gradients, in the order (Gxx, Gyy, Gxy, Gxz, Gyz) of physics.effects.gradient_matrix.
_GRAD = [fx.gradient_matrix(np.eye(5)[i]) for i in range(5)]


def _stage_hard_iron(x: TableInputs, stage: str | None) -> Columns:
    """A magnet fixed in the stage: ``h_b += Q m`` (Q turns the stage's frame into body axes)."""
    return _through_M(x.nom, _stage_Q(x.ctx, stage)), ["m[0]", "m[1]", "m[2]"], _needs_tilt(x)


def _stage_soft_iron(x: TableInputs, stage: str | None) -> Columns:
    """Soft iron fixed in the stage: ``h_b += Q A Q^T h_b``, linear in the six entries of the symmetric A."""
    Q = _stage_Q(x.ctx, stage)
    soft = np.stack([np.einsum("nij,jk,nlk,nl->ni", Q, E, Q, x.h) for E in _SYM], axis=2)
    return _through_M(x.nom, soft), ["Axx", "Ayy", "Azz", "Axy", "Axz", "Ayz"], _needs_tilt(x)


def _nonlinearity(x: TableInputs, stage: str | None) -> Columns:
    """A cubic term per axis: ``raw_j += c3_j u_j^3``, u the axis' linear output in field units."""
    u = (x.pred - x.nom.b) / x.k
    return np.stack([np.eye(3)[j] * u[:, j:j + 1] ** 3 for j in range(3)], axis=2), ["c3[0]", "c3[1]", "c3[2]"], None


def _temperature_drift(x: TableInputs, stage: str | None) -> Columns:
    """The bias following the temperature: ``raw += bias_per_c (T - mean T)`` (the mean goes to the bias)."""
    temp = x.temp
    if temp is not None and np.all(np.isfinite(temp)) and np.ptp(temp) > 0.05:
        tc = (temp - temp.mean())[:, None, None] * np.eye(3)[None]
        return tc, ["bias_per_c[0]", "bias_per_c[1]", "bias_per_c[2]"], None
    return _none(x), [], "needs temp_c that changes during the run"


def _field_drift(x: TableInputs, stage: str | None) -> Columns:
    """The lab field drifting linearly in time, seen in body axes through the attitude."""
    ctx = x.ctx
    tt = ctx.t - ctx.t.mean()
    drift = np.einsum("nji,jk->nik", ctx.R, np.eye(3)) * tt[:, None, None]
    return _through_M(x.nom, drift), ["rate_per_s[0]", "rate_per_s[1]", "rate_per_s[2]"], None


def _time_lag(x: TableInputs, stage: str | None) -> Columns:
    """A sample seeing the table ``lag_s`` earlier: ``raw(t - lag) = raw(t) - lag d(raw)/dt``; once a lag
    ``x.lag_s`` is fitted, the secant ``(raw(t - x.lag_s) - raw(t)) / x.lag_s`` with the encoder angles
    interpolated in time, exact at that lag (a lag of 0.2 s left second-order residue on the tilt scans
    that passed for a middle-stage rotation and lab windows)."""
    ctx = x.ctx
    if ctx.moving.sum() < 20:
        return _none(x), [], "needs samples taken while the table turns (a characterize run)"
    dpred = np.zeros_like(x.pred)
    for s in np.unique(ctx.segment[ctx.moving]):
        i = np.flatnonzero(ctx.segment == s)
        if len(i) < 2:
            continue
        t = _strict(ctx.t[i], ctx.rate_hz)
        if abs(x.lag_s) < 1e-4:
            dpred[i] = -np.gradient(x.pred[i], t, axis=0)
            continue
        a = np.degrees(np.unwrap(np.radians(ctx.ang[i]), axis=0))
        shifted = np.column_stack([np.interp(t - x.lag_s, t, a[:, j]) for j in range(3)])
        h = np.einsum("nji,j->ni", platform_attitude(shifted[:, 0], shifted[:, 1], shifted[:, 2]), x.nom.v)
        dpred[i] = (h @ x.nom.M.T + x.nom.b - x.pred[i]) / x.lag_s
    return dpred[:, :, None], ["lag_s"], None


def hysteresis_signs(ang: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sign of the last change larger than HYSTERESIS_STEP of each body-field component (N, 3), as the
    concealed effect defines it. Between consecutive samples the table is followed along a straight
    line in encoder angles (that is how it moves), so a reversal during an unsampled move counts."""
    h = np.einsum("nji,j->ni", platform_attitude(ang[:, 0], ang[:, 1], ang[:, 2]), v)
    # the path of each step over 1 deg, up to 90 points a degree apart, ending at the sample after it
    jump = np.flatnonzero(np.max(np.abs(np.diff(ang, axis=0)), axis=1) > 1.0) + 1
    step = ang[jump] - ang[jump - 1]
    count = np.minimum(90, np.ceil(np.max(np.abs(step), axis=1))).astype(int)
    frac = np.concatenate([np.linspace(0, 1, c + 1)[1:] for c in count]) if len(jump) else np.zeros(0)
    a = np.repeat(ang[jump - 1], count, axis=0) + frac[:, None] * np.repeat(step, count, axis=0)
    along = np.einsum("nji,j->ni", platform_attitude(a[:, 0], a[:, 1], a[:, 2]), v).tolist()
    ends = np.cumsum(count).tolist()
    paths = {int(i): along[e - c:e] for i, c, e in zip(jump, count.tolist(), ends)}
    # the play operator on plain floats (sequential by nature; numpy per sample costs 10x more)
    signs = np.empty_like(h)
    anchor, sign = h[0].tolist(), [0.0] * 3
    for i, row in enumerate(h.tolist()):
        for p in paths.get(i, (row,)):
            for j in range(3):
                d = p[j] - anchor[j]
                if abs(d) > fx.HYSTERESIS_STEP:
                    sign[j], anchor[j] = (1.0 if d > 0 else -1.0), p[j]
        signs[i] = sign
    return signs


def _hysteresis(x: TableInputs, stage: str | None) -> Columns:
    """An offset per body axis with the sign of that field component's last change."""
    s = hysteresis_signs(x.ctx.ang, x.nom.v)
    if np.any(s > 0) and np.any(s < 0):
        return (_through_M(x.nom, np.stack([np.eye(3)[j] * s[:, j:j + 1] for j in range(3)], axis=2)),
                ["offset[0]", "offset[1]", "offset[2]"], None)
    return _none(x), [], "needs holds approached from both sides"


def _table_axis_error(x: TableInputs, stage: str | None) -> Columns:
    """Axis non-perpendicularity and encoder zeros: numerical derivatives of the twin's prediction."""
    ctx, nom = x.ctx, x.nom
    cols = []
    for g in ((1e-3, 0, 0, 0), (0, 1e-3, 0, 0), (0, 0, 1e-3, 0), (0, 0, 0, 1e-3)):
        geo = TableGeometry(nonperp_deg=(g[0], g[1]), encoder_zero_deg=(0.0, g[2], g[3]))
        Rg = platform_attitude(ctx.ang[:, 0], ctx.ang[:, 1], ctx.ang[:, 2], geo)
        cols.append((np.einsum("nji,j->ni", Rg, nom.v) @ nom.M.T + nom.b - x.pred) / 1e-3)
    return (np.stack(cols, axis=2), ["nonperp_deg[0]", "nonperp_deg[1]", "encoder_zero_deg[0]", "encoder_zero_deg[1]"],
            _needs_tilt(x))


def _field_gradient(x: TableInputs, stage: str | None) -> Columns:
    """The sensor off the rotation centre in a gradient: ``h_b += C^T G C r``, linear in each G x r product."""
    R = x.ctx.R
    grad = [np.einsum("nji,jk,nkl,l->ni", R, G, R, e) for G in _GRAD for e in np.eye(3)]
    return (_through_M(x.nom, np.stack(grad, axis=2)),
            [f"G{g}*r{r}" for g in ("xx", "yy", "xy", "xz", "yz") for r in "xyz"], x.no_table)


def _time_lag_where(ctx: Context, contrib: np.ndarray) -> dict[str, Any]:
    """A lag shows only while the table turns, with the sign of the rate: its size by direction of travel."""
    if not ctx.moving.any():
        return {}
    w = ctx.rate[:, 0] if np.ptp(ctx.rate[:, 0]) > 0 else ctx.rate.sum(axis=1)
    return {"direction": {
        "positive_rate_rms_lsb": float(np.sqrt(np.mean(contrib[w > 1] ** 2))) if np.any(w > 1) else None,
        "negative_rate_rms_lsb": float(np.sqrt(np.mean(contrib[w < -1] ** 2))) if np.any(w < -1) else None}}


# --------------------------------------------------------------------------------------------------
# Parameters by name from the coefficients (c) and their 1-sigma (sd; inf where not determined)
# --------------------------------------------------------------------------------------------------

#: (coefficients, their 1-sigma, labels, the line's frequency for the line effect) -> (parameters, sigma).
ParamFormat = Callable[[np.ndarray, np.ndarray, list[str], float | None], tuple[dict[str, Any], dict[str, Any]]]


def _grouped(c: np.ndarray, labels: list[str]) -> dict[str, Any]:
    """Values grouped by label stem: ``m[0], m[1], m[2]`` -> ``m: [...]``; an unindexed label stays a number."""
    groups: dict[str, list[int]] = {}
    for i, lab in enumerate(labels):
        groups.setdefault(lab.split("[")[0], []).append(i)
    return {key: (c[idx].tolist() if len(idx) > 1 or "[" in labels[idx[0]] else float(c[idx[0]]))
            for key, idx in groups.items()}


def _by_label(c: np.ndarray, sd: np.ndarray, labels: list[str], line_hz: float | None) -> tuple[dict, dict]:
    """The default: parameters and sigma grouped by label (the catalogue's parameter names)."""
    return _grouped(c, labels), _grouped(sd, labels)


def _sym(a6: np.ndarray) -> np.ndarray:
    """3x3 symmetric from (xx, yy, zz, xy, xz, yz), infinities allowed (undetermined sigmas)."""
    return sum(x * E for x, E in zip(a6, _SYM)) if np.all(np.isfinite(a6)) else np.array(
        [[a6[0], a6[3], a6[4]], [a6[3], a6[1], a6[5]], [a6[4], a6[5], a6[2]]])


def _soft_iron_params(c: np.ndarray, sd: np.ndarray, labels: list[str], line_hz: float | None) -> tuple[dict, dict]:
    """The catalogue's A is a symmetric 3x3 matrix, fitted as its six entries."""
    return {"A": _sym(c).tolist()}, {"A": _sym(sd).tolist()}


def _gradient_params(c: np.ndarray, sd: np.ndarray, labels: list[str], line_hz: float | None) -> tuple[dict, dict]:
    """Only the products of gradient and offset are identifiable, so they are reported with their labels."""
    return {"gradient_times_offset": c.tolist(), "labels": labels}, {"gradient_times_offset": sd.tolist()}


def _mains_params(c: np.ndarray, sd: np.ndarray, labels: list[str], line_hz: float | None) -> tuple[dict, dict]:
    """The line's cos/sin pairs per axis as signed amplitudes and one phase (one pickup direction)."""
    # a cos(w t + phase) = a cos(phase) cos(w t) - a sin(phase) sin(w t); one phase for the pickup
    # direction, signed amplitudes per axis
    a = np.hypot(c[0::2], c[1::2])
    ph = np.arctan2(-c[1::2], c[0::2])
    ref = float(ph[np.argmax(a)])
    signed = a * np.sign(np.cos(ph - ref))
    return ({"amplitude_lsb": signed.tolist(), "alias_hz": line_hz, "phase_rad": ref},
            {"amplitude_lsb": np.sqrt((sd[0::2] ** 2 + sd[1::2] ** 2) / 2).tolist()})


# --------------------------------------------------------------------------------------------------
# The attitude-free model: blocks of the magnitude and dip residuals (attitude_free.py)
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class FreeRows:
    """What the attitude-free builders read for a set of rows (attitude_free.py fills it in)."""

    t: np.ndarray  # (n,) time stamps, s
    tau: np.ndarray  # (n,) seconds from mid-run
    kbar: float  # mean sensitivity: the magnitude's and the dip's columns are in LSB-equivalent
    u: np.ndarray  # (n, 3) each axis' linear output in field units (NaN on an axis without parameters)
    resolved: np.ndarray  # (3,) axes that carry parameters (the one across a planar recording does not)
    dtemp: np.ndarray | None  # (n,) temperature less the run's reference, when it changes during the run
    line_hz: float | None  # the line the frequency scan found
    h: np.ndarray  # (n, d) calibrated field direction (3-D: sensor axes; planar: in the plane)
    # the dip, when there is one (an accelerometer and 3-D field readings); else None
    f: np.ndarray | None = None  # (n, 3) specific force direction
    h_acc: np.ndarray | None = None  # (n, 3) field direction turned into the accelerometer's triad
    cos_dip: np.ndarray | None = None  # (n,) cos of the field-gravity angle, at least 1e-6
    gyro: np.ndarray | None = None  # (n, 3) body rates, rad/s, when logged


#: Attitude-free builders: block name ("<id>" or "<id>/<variant>") -> columns.
FreeBuilder = Callable[[FreeRows], dict[str, np.ndarray]]


@dataclass(frozen=True)
class FreeFit:
    """How the attitude-free model sees an effect. ``raw`` gives bases (n, 3, q) of a distortion of the raw
    output (``delta_m = basis @ params``: the magnitude sees them through its gradient, the dip as
    nuisance once the magnitude named them); ``magnitude`` and ``dip`` give columns (n, q) of those
    residuals directly. ``variants`` names each block's test; ``generic`` maps a block to the generic
    block of unexplained structure it lies inside (it must carry a share of that block's evidence)."""

    variants: dict[str, str]
    raw: FreeBuilder | None = None
    magnitude: FreeBuilder | None = None
    dip: FreeBuilder | None = None
    generic: dict[str, str] = field(default_factory=dict)


def _axes(x: FreeRows, f: np.ndarray) -> np.ndarray:
    """Per-axis bases (n, 3, q): the sensor-axis identity times ``f``, on the axes with parameters."""
    return (np.broadcast_to(np.eye(3), (len(x.t), 3, 3)) * f)[:, :, x.resolved]


def _nonlinearity_raw(x: FreeRows) -> dict[str, np.ndarray]:
    # physics.effects.Nonlinearity: raw_j += c3_j u_j^3 (u the axis' linear output in field units)
    return {"nonlinearity": _axes(x, np.nan_to_num(x.u ** 3)[:, None, :])}


def _temperature_raw(x: FreeRows) -> dict[str, np.ndarray]:
    if x.dtemp is not None:  # TemperatureDrift: raw += bias_per_c (T - T_ref)
        return {"temperature_drift": _axes(x, x.dtemp[:, None, None])}
    # no temperature that changes: a bias that follows the warm-up, linear in time, fixed in the sensor frame
    return {"temperature_drift/time": _axes(x, x.tau[:, None, None])}


def _mains_raw(x: FreeRows) -> dict[str, np.ndarray]:
    if x.line_hz is None:  # tested only at the line the scan found
        return {}
    # MainsInterference: raw += a cos(2 pi f t) + b sin(2 pi f t), per axis
    w = 2 * np.pi * x.line_hz * x.t
    return {"mains_interference": np.concatenate([_axes(x, np.cos(w)[:, None, None]),
                                                  _axes(x, np.sin(w)[:, None, None])], axis=2)}


def _field_drift_magnitude(x: FreeRows) -> dict[str, np.ndarray]:
    # the lab field drifting by rate (field units / s) changes |H| by its component along the field:
    # attitude-free, so only a magnitude trend (the part across the field is invisible here)
    return {"field_drift": x.kbar * np.column_stack([x.tau, x.tau ** 2])}


def _field_drift_dip(x: FreeRows) -> dict[str, np.ndarray]:
    # the part across the field turns the field against gravity: a trend of the dip
    return {"field_drift/dip": x.kbar * np.column_stack([x.tau, x.tau ** 2])}


def _time_lag_dip(x: FreeRows) -> dict[str, np.ndarray]:
    if x.gyro is None:  # the rate of turn comes from the gyro
        return {}
    # magnetometer lagging by lag_s: h_meas = h(t - lag) = h + lag (w x h) (body frame), so the dip
    # changes by -lag f.(w x R h) / cos(dip)
    return {"time_lag": x.kbar * (-np.sum(x.f * np.cross(x.gyro, x.h_acc), axis=1) / x.cos_dip)[:, None]}


# --------------------------------------------------------------------------------------------------
# The registry
# --------------------------------------------------------------------------------------------------

#: Table-model builder: (shared inputs, the stage of a stage effect's variant or None) -> Columns.
TableBuilder = Callable[[TableInputs, str | None], Columns]


@dataclass(frozen=True)
class Fit:
    """How the analyser fits one catalogue effect (module docstring); what the effect is stays in
    physics.effects.CATALOGUE (``entry``)."""

    id: str
    table: TableBuilder | None
    free: FreeFit | str  # or why the attitude-free model cannot test it
    params: ParamFormat = _by_label
    where: Callable[[Context, np.ndarray], dict[str, Any]] | None = None
    line: Callable[[Context, float], np.ndarray] | None = None  # (context, frequency) -> (N, 3, p)

    @property
    def entry(self) -> fx.Entry:
        """The catalogue entry: title, description, model (frame, form, against), plausible ranges, needs."""
        return fx.CATALOGUE[self.id]

    @property
    def per_stage(self) -> bool:
        """Whether the effect rides on a table stage (one variant per stage)."""
        return self.entry.model[0] == "stage"


REGISTRY: dict[str, Fit] = {f.id: f for f in [
    Fit("stage_hard_iron", _stage_hard_iron,
        "needs table angles: a magnet on a table stage is told apart from the unit's own bias only by how it "
        "turns with the stage"),
    Fit("stage_soft_iron", _stage_soft_iron,
        "needs table angles: soft iron on a stage is told apart from the unit's matrix only through the stage "
        "attitudes", params=_soft_iron_params),
    Fit("nonlinearity", _nonlinearity,
        FreeFit({"nonlinearity": "cubic per axis"}, raw=_nonlinearity_raw,
                generic={"nonlinearity": "unexplained/direction"})),
    Fit("temperature_drift", _temperature_drift,
        FreeFit({"temperature_drift": "bias per deg C",
                 "temperature_drift/time": "bias drifting with time (no temperature logged)"}, raw=_temperature_raw)),
    Fit("field_drift", _field_drift,
        FreeFit({"field_drift": "magnitude: linear + quadratic in time",
                 "field_drift/dip": "dip: linear + quadratic in time"},
                magnitude=_field_drift_magnitude, dip=_field_drift_dip, generic={"field_drift": "unexplained/time"})),
    Fit("time_lag", _time_lag, FreeFit({"time_lag": "dip against rate of turn"}, dip=_time_lag_dip),
        where=_time_lag_where),
    Fit("hysteresis", _hysteresis, "needs table angles: holds at the same attitude approached from both sides"),
    Fit("table_axis_error", _table_axis_error, "needs table angles: there is no table"),
    Fit("field_gradient", _field_gradient,
        "needs table angles: the sensor's path through the gradient follows the table rotations",
        params=_gradient_params),
    # a line at an unknown frequency: analysis.py searches for it first (lrt.line_search), then fits these
    Fit("mains_interference", None, FreeFit({"mains_interference": "line in the spectrum"}, raw=_mains_raw),
        params=_mains_params, line=mains_columns),
]}

#: The effect the table model's line search names (analysis.py fits it before every other).
(LINE,) = [f.id for f in REGISTRY.values() if f.line is not None]


# --------------------------------------------------------------------------------------------------
# What the analysers ask
# --------------------------------------------------------------------------------------------------

def table_variants() -> list[tuple[str, str | None]]:
    """Every (effect id, stage) the table model tests by regressors: the stage variants first, stage by
    stage (the order the report lists the tests in), then the rest in catalogue order."""
    staged = [(f.id, stage) for stage in fx.STAGES for f in REGISTRY.values() if f.table is not None and f.per_stage]
    return staged + [(f.id, None) for f in REGISTRY.values() if f.table is not None and not f.per_stage]


def effect_columns(ctx: Context, nom: Nominal, temp: np.ndarray | None, lag_s: float = 0.0) -> dict[str, Columns]:
    """Regressors (N, 3, p) of every catalogue effect (and stage variants, ``"<id>:<stage>"``), with
    parameter labels, or the reason the effect cannot be tested on this recording. ``lag_s``: a time lag
    already fitted, about which the lag's column is built (`_time_lag`)."""
    x = table_inputs(ctx, nom, temp, lag_s)
    return {effect if stage is None else f"{effect}:{stage}": REGISTRY[effect].table(x, stage)
            for effect, stage in table_variants()}


def parameters(variant: str, c: np.ndarray, sd: np.ndarray, labels: list[str],
               line_hz: float | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """A table-model effect's parameters by name and their 1-sigma, from its coefficients ``c``, their
    standard deviations ``sd`` and labels; a stage variant's parameters name the stage."""
    effect, _, stage = variant.partition(":")
    params, sigma = REGISTRY[effect].params(c, sd, labels, line_hz)
    if stage:
        params["stage"] = stage
    return params, sigma


def frame_of(variant: str) -> str:
    """The frame an effect lives in (the catalogue's model frame; a stage effect's names its stage)."""
    effect, _, stage = variant.partition(":")
    f = fx.CATALOGUE[effect].model[0]
    return f"{stage} stage" if f == "stage" else f


def where_extra(variant: str, ctx: Context, contrib: np.ndarray) -> dict[str, Any]:
    """What a table-model finding adds to where the effect acts (e.g. a lag's direction of travel)."""
    fit = REGISTRY[variant.partition(":")[0]]
    return fit.where(ctx, contrib) if fit.where is not None else {}


def _free(part: str, x: FreeRows) -> dict[str, np.ndarray]:
    """The attitude-free blocks of one part (raw, magnitude, dip) of every effect, in registry order."""
    out: dict[str, np.ndarray] = {}
    for f in REGISTRY.values():
        build = None if isinstance(f.free, str) else getattr(f.free, part)
        if build is not None:
            out.update(build(x))
    return out


def raw_distortions(x: FreeRows) -> dict[str, np.ndarray]:
    """Bases (n, 3, q) of the effects that add to the raw output: delta_m = basis @ params."""
    return _free("raw", x)


def magnitude_columns(x: FreeRows) -> dict[str, np.ndarray]:
    """Columns (n, q) of the effects the magnitude residual sees directly (not through the raw output)."""
    return _free("magnitude", x)


def dip_columns(x: FreeRows) -> dict[str, np.ndarray]:
    """Columns (n, q) of the effects the dip residual tests (x carries the dip)."""
    return _free("dip", x)


def free_blocks() -> dict[str, tuple[str, str]]:
    """Attitude-free block name -> (effect id, the variant its test reports)."""
    return {blk: (f.id, v) for f in REGISTRY.values() if not isinstance(f.free, str) for blk, v in f.free.variants.items()}


def free_generic() -> dict[str, str]:
    """Attitude-free block -> the generic block of unexplained structure it lies inside."""
    return {blk: g for f in REGISTRY.values() if not isinstance(f.free, str) for blk, g in f.free.generic.items()}


def needs_table_angles() -> dict[str, str]:
    """Effects the attitude-free model cannot test, and why."""
    return {f.id: f.free for f in REGISTRY.values() if isinstance(f.free, str)}
