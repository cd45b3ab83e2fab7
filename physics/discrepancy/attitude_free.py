"""Attitude-free discrepancy analysis (issue 6): recordings without table angles, e.g. hand-held ones.

Without table angles the field in body axes is unknown, so the nominal model constrains only what does
not depend on the attitude:

- **magnitude**: the readings lie on one ellipsoid, ``|E (m - B)| = 1`` (the Earth field's magnitude is
  constant; E symmetric, B the bias). The residual ``kbar (|E (m - B)| - 1)`` is expressed in
  *LSB-equivalent* (kbar = the mean sensitivity, the mean row norm of ``E^-1``), so it compares with the
  per-axis noise. When every reading lies in a plane (a turn about one axis only) the ellipsoid is
  undetermined and the ellipse of the in-plane components is used instead (constant horizontal field).
- **dip**, when an accelerometer is present (and the magnetometer data are 3-D): the angle between the
  calibrated field and the calibrated specific force is constant. The accelerometer is calibrated by its
  own ellipsoid when its readings allow it (else plain normalisation), and a small rotation between the
  two triads plus the dip angle I are fitted. Residual ``kbar (dip - I)`` (radians times kbar: the LSB a
  field-direction change of that angle moves the reading by).

Everything else follows the table analyser's contract (physics/discrepancy/; spec: result/series
schema, model ``"attitude_free"``). The steps:

1. **Compare**: fit the nominal model (algebraic ellipsoid of physics.methods.fit_ellipsoid, refined by
   Gauss-Newton on the magnitude residual itself); long recordings are first block-averaged to at most
   MAX_SAMPLES samples (said in the notes). Noise floor per axis from static segments (steps named
   rest_*/warmup/static/hold, or 1 s windows whose spread is at the noise level), else from the high-pass
   (first differences / sqrt 2) of the magnitude residual.
2. **Name**: each catalogue effect the data can show becomes regressors of the residual (its blocks come
   from its entry in physics/discrepancy/registry.py), linearised about the nominal fit (the nominal parameters' Jacobian J stays in every model, so whatever the
   ellipsoid can absorb of an effect is absorbed and not counted as evidence). Each test is a nested
   likelihood-ratio test on AR(1)-prewhitened residuals (feasible GLS, AR(1) coefficient estimated from
   the null model's residual at the recording's own time stamps). Its p-value comes from chi-square(df)
   after a Bartlett correction estimated from ``null_sims`` simulated nulls (AR(1) noise at the same time
   stamps, the noise re-estimated each time), then Bonferroni over the tests run. Effects are selected
   greedily (most significant first, the rest re-tested given those selected); two effects that each
   explain the data alone but not given each other are reported as confusable, with the experiment
   that separates them (physics.effects). The magnitude is analysed first; the dip's tests are run given
   the dip signature of the effects the magnitude named. The mains line is the best of a frequency scan
   (p corrected for the number of independent frequencies), its statistic referred to the spectrum's
   level around it when that is above the white level (coloured residuals do not make lines).
3. **Fall back honestly**: what is left is tested against the field direction in the sensor frame
   (degree 3-4 harmonics), against time (Legendre polynomials to degree 10) and for whiteness
   (Ljung-Box); a significant result is reported as "unexplained structure against <input>". A named
   effect that only stands in for such structure (see ``stand_in`` in analyze_attitude_free) is not
   named; fitted sizes beyond plausibility limits are flagged in the finding ("plausible": false), and
   implausible nominal parameters (anisotropy, non-orthogonality, hard iron) become "parameter_shift"
   findings without a p-value.
4. **Model it**: the selected effects are fitted jointly with the nominal parameters (GLS, standard errors
   inflated by the Bartlett factor); residual RMS before/after in-sample and on held-out data (4
   interleaved time folds: fit on 3, predict the 4th).

Series: column 0 of the residual arrays is the magnitude residual, column 1 the dip residual when the
dip is modelled (NaN otherwise), column 2 NaN; ``heldout_pred_*`` predict ``residual_before`` (so
``residual_before - heldout_pred_*`` is the held-out error).

Pure numpy/scipy; no I/O.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy import stats
from scipy.optimize import least_squares
from scipy.special import eval_legendre

from physics.calibration import json_safe
from physics.discrepancy.discovery import (AGAINST_TEXT, FOUND_BY_SEARCH, FRAME_TEXT, IMPLAUSIBLE, INTERMITTENT, KEEP_SHARE,
                                           N_BINS, SLOW_PREFERENCE, SLOW_SAME_EVIDENCE, Block, _cause, confirming_experiment,
                                           _inverse_roots, _window_stats, search_bins, step_time, ut_per_count, window_text)
from physics.discrepancy.lrt import _orth
from physics.discrepancy.noise import ljung_box, require_noise
from physics.discrepancy.registry import (FreeRows, dip_columns, free_blocks, free_generic, magnitude_columns,
                                          needs_table_angles, raw_distortions)
from physics.discrepancy.schema import Analysis, finding_model
from physics.discrepancy.twin import blocks, runs
from physics.effects import CATALOGUE, PARAMETER_SHIFT, UNEXPLAINED, separating_experiment
from physics.errorsep import InsufficientData
from physics.fit import consecutive_runs
from physics.methods import QUADRIC_MIN_THICKNESS, fit_ellipsoid
from physics.recording import Recording

MODEL = "attitude_free"
#: Longer recordings are block-averaged down to at most this many samples (run time).
MAX_SAMPLES = 20_000
#: Fewer samples than this cannot support the 9 ellipsoid parameters plus tests.
MIN_SAMPLES = 60
#: Held-out scheme: the recording is cut into N_TIME_BLOCKS equal time blocks; block i is in fold i % N_FOLDS.
N_FOLDS = 4
N_TIME_BLOCKS = 16
#: Ljung-Box lags (fewer for short recordings: n / 10).
LB_LAGS = 20
#: Mains scan: frequency grid oversampling, and the lowest frequency in cycles per recording (slower
#: structure belongs to the time tests).
SCAN_OVERSAMPLE = 2
SCAN_MIN_CYCLES = 10.0
#: The line's noise reference: the mean over this many independent frequencies on each side.
SCAN_NEIGHBOURS = 50
#: Unexplained structure against time: Legendre polynomials of degree 1..TIME_DEGREE.
TIME_DEGREE = 10
#: Steps whose name says the unit was held still.
STATIC_LABEL = re.compile(r"^(rest|warm_?up|static|hold)", re.IGNORECASE)
#: Static windows: length (s, at least STATIC_MIN_WINDOW samples); a window is static when every axis'
#: spread is below STATIC_FACTOR times the magnitude residual's high-pass noise.
STATIC_WINDOW_S = 1.0
STATIC_MIN_WINDOW = 10
STATIC_FACTOR = 2.5
#: A time step longer than this many median steps breaks the AR(1) chain (the samples count as independent).
GAP_RATIO = 5.0
#: Relative eigenvalue threshold for rank (collinear regressors) in the small Gram matrices.
RANK_TOL = 1e-9
#: AR(1) coefficients are kept inside this range (a unit root would make the whitening singular).
RHO_RANGE = (-0.9, 0.995)
#: Plausibility limits of the nominal parameters (anything beyond is flagged as a parameter shift).
ANISOTROPY_LIMIT = 0.10  # axis sensitivities differ by more than 10 %
NONORTHOGONALITY_LIMIT_DEG = 3.0
HARD_IRON_LIMIT = 1.0  # bias larger than the field itself
MISALIGNMENT_LIMIT_DEG = 5.0  # magnetometer triad vs accelerometer triad
#: The in-plane ellipse is refused when its two smallest singular values are within this factor (a
#: partial arc determines an ellipse only weakly; the nominal fit's Jacobian stays in every test, so a weak
#: ellipse costs power, not validity).
CONIC_SEPARATION = 1.5
#: Readings in a plane are a turn about one axis only when their spread across it is within this many times its
#: noise (first differences): a real gimbal's spin measured 1.6, 6-s hand-held paths 2.4-6.9.
PLANAR_MAX_SPREAD = 2.0
#: The accelerometer's own ellipsoid is used only when its semi-axes agree within this fraction.
ACC_RADIUS_SPREAD = 0.3
#: The dip is tested only when its nuisance (the triad rotation, the dip and the field ellipsoid's
#: parameters) has no nearly collinear combination: the weakest unit-RMS combination of its columns keeps at
#: least this RMS (a variance inflation below 100). Those columns are evaluated at the noisy readings, and
#: nearly collinear they fit the noise they share with the dip (errors in variables): clean hand-held
#: recordings of 15-25 s left 0.4 LSB of residual against 4.2 of noise once a polynomial in time was added,
#: and structure in time was named at p 1e-50 on 18 of 20 of them (measured 0.006-0.09 there; 0.39-0.51 on
#: 110-s recordings, whose statistic stays chi-square).
DIP_MIN_SEPARATION = 0.1

#: Fitted effects beyond these sizes are flagged as implausible: a cubic term above 2 % of full scale
#: (the catalogue's 100 LSB at 5000 LSB per field), a bias drift over the run above 5 % of full scale.
NONLINEAR_LIMIT = 0.02
WARMUP_LIMIT = 0.05
#: A named effect's block inside a generic block (its registry entry says which, GENERIC_OF) must carry this
#: share of the generic block's evidence.
GENERIC_SHARE = 0.5

#: Catalogue effects the attitude-free model cannot test, and why (physics/discrepancy/registry.py).
NEEDS_ANGLES = needs_table_angles()


# --------------------------------------------------------------------------------------------------
# Data: the recording's columns, and block averaging of long recordings
# --------------------------------------------------------------------------------------------------

@dataclass
class _Data:
    t: np.ndarray
    step: np.ndarray
    mag: np.ndarray
    acc: np.ndarray | None
    temp: np.ndarray | None
    gyro: np.ndarray | None  # rad/s, body axes

    def __len__(self) -> int:
        return len(self.t)


#: Empty cells of an input column (acc, temp_c, the gyro's) are filled by linear interpolation in time when each
#: gap is at most this many rows and all of them at most MAX_FILLED_SHARE of the rows; else the input is not used.
MAX_FILLED_GAP, MAX_FILLED_SHARE = 5, 0.02


def _filled(x: np.ndarray | None, t: np.ndarray, what: str, notes: list[str]) -> np.ndarray | None:
    """``x`` (n,) or (n, k) with its few short gaps filled (one empty cell had made a whole input unused: a
    concealed turn of the axes went unseen, and a gain following temp_c was named a drift in time), or None
    with a note when the gaps are too many or too long to fill."""
    if x is None:
        return None
    bad = ~np.isfinite(x).reshape(len(x), -1).all(axis=1)
    if not bad.any():
        return x
    runs, n_bad = consecutive_runs(bad), int(bad.sum())
    longest = max(len(r) for r in runs)
    if longest > MAX_FILLED_GAP or n_bad > MAX_FILLED_SHARE * len(x) or bad.all():
        notes.append(f"{what} has {n_bad} row(s) with empty cells (the longest gap {longest} rows): {what} is not used")
        return None
    out = np.array(x, dtype=float).reshape(len(x), -1)
    for j in range(out.shape[1]):
        out[bad, j] = np.interp(t[bad], t[~bad], out[~bad, j])
    notes.append(f"{what}: {n_bad} row(s) with empty cells filled by linear interpolation in time (gaps of at most "
                 f"{longest} rows)")
    return out.reshape(np.shape(x))


def _columns(rec: Recording, notes: list[str]) -> _Data:
    t = np.asarray(rec.t, float)
    acc = _filled(None if rec.acc is None else np.asarray(rec.acc, dtype=float), t, "the accelerometer", notes)
    temp = _filled(None if rec.temp_c is None else np.asarray(rec.temp_c, dtype=float), t, "temp_c", notes)
    gyro = None
    if all(k in rec.extra for k in ("gx", "gy", "gz")):
        try:
            g = np.column_stack([np.asarray(rec.extra[k], dtype=float) for k in ("gx", "gy", "gz")])
        except ValueError:
            notes.append("extra columns gx, gy, gz are not all numbers: gyro rates not used")
        else:
            g = _filled(g, t, "the gyro (gx, gy, gz)", notes)
            if g is not None:
                unit = rec.meta.get("gyro_unit", "deg/s").lower()
                gyro = g if "rad" in unit else np.radians(g)  # the importers write deg/s
    return _Data(t, np.asarray(rec.step, dtype=object), np.asarray(rec.mag, float), acc, temp, gyro)


def _decimate(d: _Data, factor: int) -> tuple[_Data, np.ndarray]:
    """Block means of ``factor`` consecutive rows (never across a step change or a time gap).

    Returns the averaged data and each original row's block index.
    """
    n = len(d)
    if factor <= 1:
        return d, np.arange(n)
    block = blocks(runs(d.t, d.step, GAP_RATIO), factor)
    starts = np.r_[0, np.flatnonzero(np.diff(block)) + 1]
    count = np.diff(np.r_[starts, n]).astype(float)

    def mean(a: np.ndarray | None) -> np.ndarray | None:
        if a is None:
            return None
        s = np.add.reduceat(a, starts, axis=0)
        return s / (count[:, None] if a.ndim == 2 else count)

    return _Data(mean(d.t), d.step[starts], mean(d.mag), mean(d.acc), mean(d.temp), mean(d.gyro)), block


# --------------------------------------------------------------------------------------------------
# The nominal model: field ellipsoid (or in-plane ellipse), accelerometer directions, dip
# --------------------------------------------------------------------------------------------------

def _sym_pairs(d: int) -> list[tuple[int, int]]:
    return [(a, a) for a in range(d)] + [(a, b) for a in range(d) for b in range(a + 1, d)]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


class _Shape:
    """``|E (P^T (m - c) - B)| = 1``: the 3-D ellipsoid (P = I, c = 0) or, for readings in a plane, the
    ellipse of their components in that plane (P its 3x2 orthonormal basis, c a point in it)."""

    def __init__(self, P: np.ndarray, c: np.ndarray, B: np.ndarray, E: np.ndarray) -> None:
        self.P, self.c, self.B, self.E = P, c, B, E
        self.d = P.shape[1]
        self.pairs = _sym_pairs(self.d)

    @property
    def planar(self) -> bool:
        return self.d == 2

    def _h(self, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dev = (m - self.c) @ self.P - self.B
        h = dev @ self.E  # E symmetric
        return dev, h, np.linalg.norm(h, axis=1)

    def residual(self, m: np.ndarray) -> np.ndarray:
        """``|h| - 1`` (unitless, field units)."""
        return self._h(m)[2] - 1.0

    def direction(self, m: np.ndarray) -> np.ndarray:
        """Unit field direction in the model's frame (3-D: about the sensor axes; planar: in the plane)."""
        _, h, hn = self._h(m)
        return h / hn[:, None]

    def project(self, m: np.ndarray) -> np.ndarray:
        """The readings moved radially (from the centre, within the model's plane) onto the model surface.

        Regressors are evaluated there, not at the noisy readings: the residual is the readings' radial
        noise, so a regressor built from the raw readings would contain that noise and correlate with the
        residual under the null (e.g. u^3 ~ u_model^3 (1 + 3 r)).
        """
        dev, _, hn = self._h(m)
        return m + (dev / hn[:, None] - dev) @ self.P.T

    def jac(self, m: np.ndarray) -> np.ndarray:
        """d(|h| - 1)/d(B, E-entries) at the model points (see :meth:`project`), (n, d + d(d+1)/2).

        Evaluated at the model points, the overall-scale combination of the E columns is exactly the
        constant 1, so a constant in any effect's regressors is absorbed by the nominal model.
        """
        dev, h, hn = self._h(m)
        hh = h / hn[:, None]
        dev = dev / hn[:, None]
        cols = [-(hh @ self.E)]
        for a, b in self.pairs:
            col = hh[:, a] * dev[:, a] if a == b else hh[:, a] * dev[:, b] + hh[:, b] * dev[:, a]
            cols.append(col[:, None])
        return np.hstack(cols)

    def grad(self, m: np.ndarray) -> np.ndarray:
        """d|h|/dm (n, 3): a raw-count distortion delta changes |h| by grad . delta. Zero on an axis the
        readings do not resolve (a turn in one plane): its column is nearly a resolved axis' (the plane is
        tilted a little), and scaled alike the fit split a distortion between the two (a 20-LSB offset on
        y came out -10.1 +- 0.1 LSB, the rest on the unresolved z, reported n/a)."""
        g = (self.direction(m) @ self.E) @ self.P.T
        g[:, ~self.resolved] = 0.0
        return g

    @property
    def M3(self) -> np.ndarray:
        """Raw counts per field unit, (3, d): m = c + P (B + E^-1 h)."""
        return self.P @ np.linalg.inv(self.E)

    @property
    def centre(self) -> np.ndarray:
        """The bias in raw counts (3,)."""
        return self.c + self.P @ self.B

    @property
    def k(self) -> np.ndarray:
        """Sensitivity of each sensor axis (row norms of M3), LSB per field unit."""
        return np.linalg.norm(self.M3, axis=1)

    @property
    def resolved(self) -> np.ndarray:
        """Sensor axes that see the field change (in planar mode, the axis across the plane does not)."""
        k = self.k
        return k > 0.3 * k.max()

    @property
    def kbar(self) -> float:
        return float(np.mean(self.k[self.resolved]))

    def axis_outputs(self, m: np.ndarray) -> np.ndarray:
        """Each resolved sensor axis' linear output in field units, ``(m_j - bias_j) / k_j`` (NaN otherwise)."""
        u = (self.project(m) - self.centre) / self.k
        u[:, ~self.resolved] = np.nan
        return u

    def refine(self, m: np.ndarray, iters: int = 20) -> None:
        """Gauss-Newton on the magnitude residual with the model-point Jacobian (the algebraic fit is biased).

        Its fixed point makes the residual orthogonal to the Jacobian the tests use (``J' r = 0``); since
        that Jacobian holds no radial noise, the estimating equation is unbiased. Where the full steps
        leave the residual larger than they found it (attitudes that only weakly determine the ellipsoid:
        an 8-s clean recording went 0.010 -> 1e19, and a bad stop left 59 LSB against 3.8 of noise),
        Levenberg-Marquardt from the algebraic fit finds the basin and Gauss-Newton finishes there.
        """
        start = self._params()
        cost0 = float(np.sum(self.residual(m) ** 2))
        self._gauss_newton(m, iters)
        cost = float(np.sum(self.residual(m) ** 2))
        if np.isfinite(cost) and cost <= cost0:
            return
        self._set(start)
        sol = least_squares(lambda x: self._set(x) or self.residual(m), start,
                            jac=lambda x: self._set(x) or self.jac(m), method="lm", xtol=1e-14, ftol=1e-14)
        self._set(sol.x)
        self._gauss_newton(m, iters)
        if not float(np.sum(self.residual(m) ** 2)) <= 2.0 * sol.cost * (1.0 + 1e-6):
            self._set(sol.x)

    def _params(self) -> np.ndarray:
        return np.concatenate([self.B, [self.E[a, b] for a, b in self.pairs]])

    def _set(self, x: np.ndarray) -> None:
        E = np.zeros((self.d, self.d))
        for (a, b), s in zip(self.pairs, x[self.d:]):
            E[a, b] = E[b, a] = s
        self.B, self.E = np.array(x[: self.d], dtype=float), E

    def _gauss_newton(self, m: np.ndarray, iters: int) -> None:
        for _ in range(iters):
            step = np.linalg.lstsq(self.jac(m), -self.residual(m), rcond=None)[0]
            self._set(self._params() + step)
            if np.max(np.abs(step)) < 1e-10 * (1 + np.max(np.abs(self.B))):
                break


def _conic2(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and symmetric E with |E (p - B)| = 1 for 2-D points (algebraic conic fit)."""
    c0 = p.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((p - c0) ** 2, axis=1))))
    x, y = ((p - c0) / s).T
    design = np.column_stack([x * x, y * y, 2 * x * y, 2 * x, 2 * y, np.ones_like(x)])
    _, sv, vt = np.linalg.svd(design, full_matrices=False)
    if sv[-2] < CONIC_SEPARATION * sv[-1]:
        raise InsufficientData("the in-plane readings do not determine an ellipse (singular values "
                               f"{sv[-2]:.3g} and {sv[-1]:.3g}: they cover too little of the turn)")
    a, b, cxy, d, e, f = vt[-1]
    A = np.array([[a, cxy], [cxy, b]])
    centre = -np.linalg.solve(A, [d, e])
    Q = A / (centre @ A @ centre - f)
    w, V = np.linalg.eigh(Q)
    if not np.all(w > 0):
        raise InsufficientData("the in-plane readings fit a hyperbola, not an ellipse")
    return c0 + s * centre, (V * np.sqrt(w)) @ V.T / s


def _quadric3(m: np.ndarray, separation: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """physics.methods.fit_ellipsoid's algebra without its uniqueness guard (for 3-D readings whose
    quadric is only weakly determined, e.g. hand-held turns mostly about one axis): the Gauss-Newton
    refinement and the nominal Jacobian kept in every test take care of the weak directions. With
    ``separation``, a quadric whose two smallest singular values are closer than that factor (a family
    of quadrics fits the readings, one picked by the noise) is refused."""
    c0 = m.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((m - c0) ** 2, axis=1))))
    x, y, z = ((m - c0) / s).T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z,
                              np.ones_like(x)])
    _, sv, vt = np.linalg.svd(design, full_matrices=False)
    if sv[-2] < separation * sv[-1]:
        raise InsufficientData("the readings do not determine an ellipsoid (its two weakest directions, singular "
                               f"values {sv[-2]:.3g} and {sv[-1]:.3g}, are a family the noise picks from)")
    p = vt[-1]
    A = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    centre = -np.linalg.solve(A, p[6:9])
    Q = A / (centre @ A @ centre - p[9])
    w, V = np.linalg.eigh(Q)
    if not np.all(w > 0):
        raise InsufficientData("the best-fitting quadric is not an ellipsoid (eigenvalues "
                               f"{np.array2string(w, precision=3)})")
    return c0 + s * centre, (V * np.sqrt(w)) @ V.T / s


def _highpass_sd(x: np.ndarray) -> float:
    """The white noise of a time series from its first differences (robust: MAD), over sqrt 2."""
    d = np.diff(x)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def _thickness(m: np.ndarray) -> float:
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov((m - m.mean(axis=0)).T)), 0.0))
    return float(spread[0] / spread[2]) if spread[2] > 0 else 0.0


def _fit_shape(mag: np.ndarray, notes: list[str]) -> _Shape:
    try:
        try:
            B, E = fit_ellipsoid(mag)
        except InsufficientData as why:
            if _thickness(mag) < QUADRIC_MIN_THICKNESS:
                raise
            B, E = _quadric3(mag)
            notes.append(f"the field ellipsoid is only weakly determined by these attitudes ({str(why)[:90]}...); "
                         "it is fitted anyway (the readings are 3-D) and refined on the magnitude residual")
        shape = _Shape(np.eye(3), np.zeros(3), B, E)
    except InsufficientData as e3:
        c = mag.mean(axis=0)
        _, sv, vt = np.linalg.svd(mag - c, full_matrices=False)
        P = vt[:2].T
        if sv[2] >= QUADRIC_MIN_THICKNESS * sv[0]:
            # not a turn about one axis either: an ellipse in "the plane" of a 3-D arc (thickness 0.143) left
            # 261 LSB against 7 of noise, and five effects were named
            raise InsufficientData(f"attitude-free model: the field ellipsoid cannot be fitted ({e3}), and the readings "
                                   f"do not lie in a plane either (thickness {sv[2] / sv[0]:.3f} of their extent) for "
                                   "an ellipse; turn the unit through more attitudes (about every axis)") from None
        across = (mag - c) @ vt[2]
        spread, noise = float(np.sqrt(np.mean(across ** 2))), _highpass_sd(across)
        if spread > PLANAR_MAX_SPREAD * noise:
            # thin but not a turn about one axis: the ellipse in the plane takes the field across it as constant,
            # and what it varies by stays in the residual (6 s of hand-held turning, 11 LSB across the plane
            # against 1.6 of noise, left 17 LSB and a field drift was named on clean readings)
            raise InsufficientData(f"attitude-free model: the field ellipsoid cannot be fitted ({e3}), and the readings "
                                   f"vary across their plane by {spread:.3g} LSB against {noise:.3g} of noise: not a "
                                   "turn about one axis either; record longer, turning the unit about every axis (or "
                                   "about one axis only)") from None
        try:
            B2, E2 = _conic2((mag - c) @ P)
        except InsufficientData as e2:
            raise InsufficientData(f"attitude-free model: neither the field ellipsoid ({e3}) nor an ellipse in the "
                                   f"readings' plane ({e2}) can be fitted") from None
        shape = _Shape(P, c, B2, E2)
        notes.append(
            "the readings lie in a plane (thickness "
            f"{sv[2] / sv[0]:.3f} of their extent: a turn about one axis), so the 3-D ellipsoid is undetermined; "
            "the nominal model is the ellipse of the in-plane components (constant field component in the "
            "plane). The axis across the plane, the dip and the tests that need them are not available.")
    shape.refine(mag)
    return shape


class _AccCal:
    """Accelerometer directions: its own ellipsoid when the readings support one, else plain normalisation."""

    def __init__(self, acc: np.ndarray, notes: list[str]) -> None:
        self.B, self.E = np.zeros(3), np.eye(3)
        self.calibrated = False
        try:
            if _thickness(acc) < QUADRIC_MIN_THICKNESS:
                raise InsufficientData("its readings lie in a plane")
            try:
                B, E = fit_ellipsoid(acc)
            except InsufficientData:
                # unlike the magnetometer's, no term of the model takes up the accelerometer's weak directions:
                # they go straight into the dip (a table plan's tilts left a family of quadrics, and the one
                # the noise picked, semi-axes 18528, 16384 and 14845 LSB for a perfect unit, made the dip's
                # residual 23 LSB against 3, and a field drift and a rotation were named)
                B, E = _quadric3(acc, CONIC_SEPARATION)
            radii = 1.0 / np.linalg.eigvalsh(E)
            if radii.max() / radii.min() - 1.0 > ACC_RADIUS_SPREAD:
                raise InsufficientData(f"semi-axes {np.array2string(radii, precision=0)} disagree")
            self.B, self.E, self.calibrated = B, E, True
        except InsufficientData as e:
            notes.append(f"accelerometer not calibrated by its own ellipsoid ({str(e).split(';')[0][:160]}); its "
                         "readings are only normalised")

    def directions(self, acc: np.ndarray) -> np.ndarray:
        return _unit((acc - self.B) @ self.E)


def _skew_rot(w: np.ndarray) -> np.ndarray:
    """Rotation matrix exp([w]x) (Rodrigues)."""
    th = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


class _Dip:
    """Constant angle between the calibrated field and the specific force: ``dip = asin(-f . R h)``.

    R is the small rotation between the magnetometer's ellipsoid frame and the accelerometer's; I the dip.
    Specific force at rest points up and the field down by I, so ``-f . h = sin I`` (PHYSICS.md).
    """

    def __init__(self) -> None:
        self.R, self.I = np.eye(3), 0.0

    def angle(self, h: np.ndarray, f: np.ndarray) -> np.ndarray:
        s = -np.sum(f * (h @ self.R.T), axis=1)
        return np.arcsin(np.clip(s, -1.0, 1.0))

    def jac(self, h: np.ndarray, f: np.ndarray) -> np.ndarray:
        """d(dip - I)/d(rotation vector, I), (n, 4)."""
        Rh = h @ self.R.T
        cos = np.maximum(np.cos(self.angle(h, f)), 1e-6)
        dw = -np.cross(Rh, f) / cos[:, None]
        return np.hstack([dw, -np.ones((len(h), 1))])

    def fit(self, h: np.ndarray, f: np.ndarray) -> None:
        self.I = float(np.mean(self.angle(h, f)))
        for _ in range(10):
            r = self.angle(h, f) - self.I
            step = np.linalg.lstsq(self.jac(h, f), -r, rcond=None)[0]
            self.R = _skew_rot(step[:3]) @ self.R
            self.I += float(step[3])
            if np.max(np.abs(step)) < 1e-12:
                break


def _dip_shape_jac(sh: _Shape, dip: _Dip, m: np.ndarray, h: np.ndarray, f: np.ndarray) -> np.ndarray:
    """d(dip)/d(B, E-entries) of the 3-D ellipsoid at the model points, (n, 9).

    ``sin(dip) = -f . R h^`` with ``h^ = h / |h|``, ``h = E (m - B)``: a change dh moves sin(dip) by
    ``-w . dh`` with ``w = (I - h^ h^') R' f / |h|`` (|h| = 1 at the model point).
    """
    dev = (m - sh.c) @ sh.P - sh.B
    dev = dev / np.linalg.norm(dev @ sh.E, axis=1, keepdims=True)
    g = f @ dip.R  # R' f
    w = g - np.sum(g * h, axis=1, keepdims=True) * h
    cos = np.maximum(np.cos(dip.angle(h, f)), 1e-6)[:, None]
    cols = [(w @ sh.E) / cos]  # d/dB: dh = -E e_j
    for a, b in sh.pairs:
        cols.append((-(w[:, a] * dev[:, a]) if a == b else -(w[:, a] * dev[:, b] + w[:, b] * dev[:, a]))[:, None] / cos)
    return np.hstack(cols)


def _dip_separation(nom: "_Nominal", d: _Data) -> float:
    """The RMS of the weakest unit-RMS combination of the dip's nuisance columns (1: orthogonal, 0:
    collinear), exact null directions (the ellipsoid's overall scale, which does not move the dip) left out."""
    h = nom.shape.direction(d.mag)
    f = nom.acc.directions(d.acc)
    J = np.hstack([nom.dip.jac(h, f), _dip_shape_jac(nom.shape, nom.dip, d.mag, h, f)])
    J = J / np.maximum(np.sqrt(np.mean(J ** 2, axis=0)), 1e-300)
    sv = np.linalg.svd(J, compute_uv=False)
    sv = sv[sv > 1e-8 * sv[0]]
    return float(sv[-1] / np.sqrt(len(J)))


@dataclass
class _Nominal:
    shape: _Shape
    acc: _AccCal | None
    dip: _Dip | None
    t_mid: float
    t_half: float
    temp_ref: float | None
    mains_hz: float | None = None

    @property
    def kbar(self) -> float:
        return self.shape.kbar


# --------------------------------------------------------------------------------------------------
# Regressors of each effect (linearised about the nominal fit), for any set of rows
# --------------------------------------------------------------------------------------------------

#: Blocks of the dictionary of generic building blocks (issue 12) the attitude-free model tests beside the
#: catalogue: the unit's sensitivity following its temperature, or drifting in time (per axis, relative).
GAIN_BLOCKS = {"discovered:sensor/gain/temp_c": ("temp_c", "a change of sensitivity fixed in the sensor frame, "
                                                           "following temp_c (per axis, per deg C)"),
               "discovered:sensor/gain/time": ("time", "a change of sensitivity fixed in the sensor frame, drifting "
                                                       "in time (per axis, over the run)")}
#: The magnetometer's axes turning against the accelerometer's (per axis, small angles), drifting in time or
#: following temp_c: a mount creeping, a board warping as it warms. It turns the calibrated field against
#: gravity, so it shows on the dip, and on the magnitude only through the unit's anisotropy: each is tested on
#: both responses at once with one set of parameters (:func:`_joint_test`), before the window search (whose
#: lab-frame windows turn the dip too).
ROTATION_BLOCKS = {"discovered:sensor/rotation/time": ("time", "the magnetometer's axes turning against the "
                                                               "accelerometer's, drifting in time (about each axis, over the run)"),
                   "discovered:sensor/rotation/temp_c": ("temp_c", "the magnetometer's axes turning against the "
                                                                   "accelerometer's, following temp_c (about each axis, per deg C)")}
#: Where two blocks explain the same structure of the magnitude, which is named over which (see the selection).
PREFERRED = {"discovered:sensor/gain/temp_c": "field_drift", "field_drift": "discovered:sensor/gain/time"}
#: Named blocks that lie partly inside a generic block of unexplained structure: each must carry GENERIC_SHARE
#: of that block's evidence to be named (a change of sensitivity following the temperature or time moves the
#: magnitude partly as a function of time alone, which the time polynomials span).
GENERIC_OF = {**free_generic(), **{name: "unexplained/time" for name in GAIN_BLOCKS}}
#: Block name -> (effect id, variant) of the test it serves: each catalogue effect's blocks (its registry
#: entry), the dictionary's gain blocks, and the generic blocks of structure no entry names.
BLOCKS = {
    **free_blocks(),
    **{name: ("discovered", variant) for name, (_, variant) in {**GAIN_BLOCKS, **ROTATION_BLOCKS}.items()},
    "unexplained/direction": (UNEXPLAINED, "field direction in the sensor frame (degree 3-4 harmonics)"),
    "unexplained/time": (UNEXPLAINED, f"time (Legendre polynomials to degree {TIME_DEGREE})"),
}


@dataclass
class _Design:
    """One response (magnitude or dip): y (LSB-equivalent), nuisance columns J and effect blocks."""

    y: np.ndarray
    J: np.ndarray
    blocks: dict[str, np.ndarray]


def _monomials(h: np.ndarray, degrees: tuple[int, ...]) -> np.ndarray:
    cols = []
    for deg in degrees:
        for i in range(deg + 1):
            for j in range(deg + 1 - i):
                cols.append(h[:, 0] ** i * h[:, 1] ** j * h[:, 2] ** (deg - i - j))
    return np.column_stack(cols)


def _rows(nom: _Nominal, d: _Data, temp_varies: bool) -> FreeRows:
    """What the registry's builders read for the rows ``d`` (the dip's part when there is a dip)."""
    sh = nom.shape
    h = sh.direction(d.mag)
    dip: dict[str, Any] = {}
    if nom.dip is not None and d.acc is not None:
        f = nom.acc.directions(d.acc)
        dip = {"f": f, "h_acc": h @ nom.dip.R.T, "cos_dip": np.maximum(np.cos(nom.dip.angle(h, f)), 1e-6),
               "gyro": d.gyro}
    return FreeRows(t=d.t, tau=d.t - nom.t_mid, kbar=nom.kbar, u=sh.axis_outputs(d.mag), resolved=sh.resolved,
                    dtemp=d.temp - nom.temp_ref if temp_varies else None, line_hz=nom.mains_hz, h=h, **dip)


def _features(nom: _Nominal, d: _Data, temp_varies: bool) -> dict[str, _Design]:
    """The magnitude's (and the dip's) response, nuisance columns and blocks: every catalogue effect's
    (physics/discrepancy/registry.py) and the generic ones."""
    sh, kb = nom.shape, nom.kbar
    m = d.mag
    rows = _rows(nom, d, temp_varies)
    y = kb * sh.residual(m)
    J = kb * sh.jac(m)
    v = sh.grad(m)  # d|h| per raw count along each sensor axis
    tau = rows.tau  # seconds from mid-run
    blocks: dict[str, np.ndarray] = {}
    # Effects that distort the raw output, delta_m = basis (n, 3, q) . params: the magnitude sees
    # kbar grad . delta_m (so the coefficients are the effect's own parameters, in LSB)
    raw = raw_distortions(rows) | _gain_bases(nom, rows) | (_rotation_bases(nom, rows) if rows.f is not None else {})
    for name, basis in raw.items():
        blocks[name] = kb * np.einsum("nj,njq->nq", v, basis)
    blocks.update(magnitude_columns(rows))  # effects the magnitude sees directly (a field drift's trend)
    h = rows.h
    if sh.planar:
        phi = np.arctan2(h[:, 1], h[:, 0])
        blocks["unexplained/direction"] = kb * np.column_stack(
            [np.cos(3 * phi), np.sin(3 * phi), np.cos(4 * phi), np.sin(4 * phi)])
    else:  # degree 3 and 4 monomials span harmonics 0-4; the ellipsoid's J spans 0-2 already
        blocks["unexplained/direction"] = kb * _monomials(h, (3, 4))
    x = np.clip(tau / nom.t_half, -1.0, 1.0)
    blocks["unexplained/time"] = kb * np.column_stack([eval_legendre(k, x) for k in range(1, TIME_DEGREE + 1)])
    out = {"magnitude": _Design(y, J, blocks)}

    if rows.f is not None:
        f = rows.f
        dip = nom.dip
        yd = kb * (dip.angle(h, f) - dip.I)
        # nuisance of the dip: the triad rotation and I, and also the field ellipsoid's parameters (their
        # estimation errors turn the calibrated field slightly, which moves the dip with the attitude)
        Jd = kb * np.hstack([dip.jac(h, f), _dip_shape_jac(sh, dip, m, h, f)])
        bd = dip_columns(rows)  # effects the dip tests (a field drift's turn, a lag against the gyro's rates)
        # the raw distortions move the dip too (by d(dip)/dm . delta_m): nuisance columns for the dip tests
        # once the magnitude has named the effect ("<block>@dip", never tested on their own)
        ddip = _dip_gradient(nom, rows)
        for name, basis in raw.items():
            bd[name + "@dip"] = kb * np.einsum("nj,njq->nq", ddip, basis)
        # the generic block in time for the dip's own unexplained-structure tests (a lag between the sensors or
        # the hand's own acceleration leave the magnitude alone and move the dip only). Not the one in field
        # direction: on a plan of few poses its 25 columns fit each pose's mean, the accelerometer's own
        # small errors among them (660 LSB rms of cancelling columns on a clean table plan stripped of angles)
        bd["unexplained/time"] = blocks["unexplained/time"]
        out["dip"] = _Design(yd, Jd, bd)
    return out


def _gain_bases(nom: _Nominal, rows: FreeRows) -> dict[str, np.ndarray]:
    """Raw-count bases (n, 3, 3) of :data:`GAIN_BLOCKS`: a relative change g_j of axis j's sensitivity moves its
    output by g_j k_j u_j, times the temperature less the run's reference (deg C) or the time from mid-run
    over half the run (so a coefficient is the change per deg C, or from the middle to the end of the run)."""
    u = np.nan_to_num(rows.u) * np.where(rows.resolved, nom.shape.k, 0.0)  # counts on each resolved axis
    out = {}
    for name, (against, _) in GAIN_BLOCKS.items():
        x = _slow_input(nom, rows, against)
        if x is not None:
            out[name] = np.einsum("nj,jk->njk", u * x[:, None], np.eye(3))
    return out


def _slow_input(nom: _Nominal, rows: FreeRows, against: str) -> np.ndarray | None:
    """The temperature less the run's reference (deg C), or the time from mid-run over half the run."""
    return rows.dtemp if against == "temp_c" else rows.tau / nom.t_half


def _rotation_bases(nom: _Nominal, rows: FreeRows) -> dict[str, np.ndarray]:
    """Raw-count bases (n, 3, 3) of :data:`ROTATION_BLOCKS`: the axes turned by small angles w (rad) see the
    field turned the other way, and move the output about the bias by -w x (raw - bias) (PHYSICS.md: M_o's
    rows are the sensor axes, M_o -> M_o R(w)^T), times the slow input (:func:`_slow_input`)."""
    lin = np.nan_to_num(rows.u) * np.where(rows.resolved, nom.shape.k, 0.0)  # counts about the bias
    turn = np.stack([-np.cross(np.eye(3)[j], lin) for j in range(3)], axis=2)  # -e_j x lin: (n, 3, 3)
    out = {}
    for name, (against, _) in ROTATION_BLOCKS.items():
        x = _slow_input(nom, rows, against)
        if x is not None:
            out[name] = turn * x[:, None, None]
    return out


def _dip_gradient(nom: _Nominal, rows: FreeRows) -> np.ndarray:
    """d(dip)/d(raw counts) of each row, (n, 3)."""
    sh, h = nom.shape, rows.h
    g = rows.f @ nom.dip.R
    wv = g - np.sum(g * h, axis=1, keepdims=True) * h
    return -((wv @ sh.E) @ sh.P.T) / rows.cos_dip[:, None]


# --------------------------------------------------------------------------------------------------
# Nested likelihood-ratio tests on AR(1)-prewhitened residuals
# --------------------------------------------------------------------------------------------------

class _Regression:
    """GLS with AR(1) noise at given time stamps for one response, for real data and simulated nulls.

    Columns are scaled to unit RMS. The AR(1) correlation between consecutive samples is
    ``rho ** (dt / median dt)`` (dt quantised to 0.1 median steps, so the Gram matrix of the whitened
    columns is a sum over a few lag classes and costs O(p^2) per simulated null); a step longer than
    GAP_RATIO medians starts an independent chain.
    """

    def __init__(self, name: str, design: _Design, t: np.ndarray) -> None:
        self.name = name
        self.y = design.y
        self.n = len(self.y)
        mats = [design.J] + [design.blocks[k] for k in design.blocks]
        names = ["J"] + list(design.blocks)
        self.slices: dict[str, np.ndarray] = {}
        start = 0
        for nm, a in zip(names, mats):
            self.slices[nm] = np.arange(start, start + a.shape[1])
            start += a.shape[1]
        Z = np.hstack(mats)
        scale = np.sqrt(np.mean(Z ** 2, axis=0))
        self.scale = np.where(scale > 0, scale, 1.0)
        self.Z = Z / self.scale
        dt = np.diff(t)
        med = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
        ratio = np.round(dt / med, 1)
        dep = (ratio > 0) & (ratio <= GAP_RATIO)
        self.ratio = np.r_[0.0, np.where(dep, np.maximum(ratio, 0.1), 0.0)]  # 0 = independent of the previous
        self.first = np.flatnonzero(self.ratio == 0)
        self.pair = np.flatnonzero((self.ratio > 0) & (self.ratio <= 1.5))  # pairs used to estimate rho
        self.bins = [(r, np.flatnonzero(self.ratio == r)) for r in np.unique(self.ratio[self.ratio > 0])]
        Zf = self.Z[self.first]
        self.S_first = Zf.T @ Zf
        self.S = [(r, self.Z[i].T @ self.Z[i], self.Z[i].T @ self.Z[i - 1], self.Z[i - 1].T @ self.Z[i - 1])
                  for r, i in self.bins]

    def cols(self, blocks: list[str] | tuple[str, ...]) -> np.ndarray:
        return np.concatenate([self.slices["J"]] + [self.slices[b] for b in blocks])

    def rank(self, cols: np.ndarray) -> int:
        w = np.linalg.eigvalsh(self.Z[:, cols].T @ self.Z[:, cols])
        return int(np.sum(w > RANK_TOL * w.max()))

    # ---- noise ------------------------------------------------------------------------------------
    def ols_resid(self, cols: np.ndarray, Y: np.ndarray) -> np.ndarray:
        U, s, _ = np.linalg.svd(self.Z[:, cols], full_matrices=False)
        U = U[:, s > RANK_TOL ** 0.5 * s[0]]
        return Y - U @ (U.T @ Y)

    def rho(self, E: np.ndarray) -> np.ndarray:
        """Lag-1 autocorrelation of residual columns E (n, S) over consecutive pairs."""
        i = self.pair
        if i.size < 3:
            return np.zeros(E.shape[1])
        num = np.sum(E[i] * E[i - 1], axis=0)
        den = np.sqrt(np.sum(E[i] ** 2, axis=0) * np.sum(E[i - 1] ** 2, axis=0))
        return np.clip(num / np.where(den > 0, den, 1.0), *RHO_RANGE)

    def row_rho(self, rho: np.ndarray) -> np.ndarray:
        """(n, S) correlation of each row with the previous one."""
        r = self.ratio[:, None]
        out = np.sign(rho)[None, :] * np.abs(rho)[None, :] ** r
        out[self.ratio == 0] = 0.0
        return out

    def whiten(self, Y: np.ndarray, rho: np.ndarray) -> np.ndarray:
        R = self.row_rho(rho)
        out = Y.copy()
        out[1:] = (Y[1:] - R[1:] * Y[:-1]) / np.sqrt(1.0 - R[1:] ** 2)
        return out

    def simulate(self, rho: float, S: int, rng: np.random.Generator) -> np.ndarray:
        """S AR(1) series (unit marginal variance) at the recording's time stamps, (n, S)."""
        R = self.row_rho(np.array([rho]))[:, 0]
        c = np.sqrt(1.0 - R ** 2)
        Z = rng.standard_normal((self.n, S))
        E = np.empty_like(Z)
        E[0] = Z[0]
        for i in range(1, self.n):
            E[i] = R[i] * E[i - 1] + c[i] * Z[i]
        return E

    # ---- GLS forms ---------------------------------------------------------------------------------
    def forms(self, Y: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Whitened Gram G (S, p, p), Z~'y~ (S, p), y~'y~ (S,) and whitened Y (n, S), per column of Y."""
        S = Y.shape[1]
        p = self.Z.shape[1]
        G = np.broadcast_to(self.S_first, (S, p, p)).copy()
        for r, S00, S01, S11 in self.S:
            rb = np.sign(rho) * np.abs(rho) ** r
            c = 1.0 - rb ** 2
            G += S00[None] / c[:, None, None]
            G -= (rb / c)[:, None, None] * (S01 + S01.T)[None]
            G += (rb ** 2 / c)[:, None, None] * S11[None]
        Yw = self.whiten(Y, rho)
        R = self.row_rho(rho)
        C = np.sqrt(1.0 - R ** 2)
        # z~_i = (z_i - R_i z_{i-1}) / C_i  =>  Z~'y~ = Z' (y~ / C) - Z_shift' (R y~ / C)
        A = Yw / C
        b = (self.Z.T @ A).T - (self.Z[:-1].T @ (R[1:] * A[1:])).T
        return G, b, np.sum(Yw ** 2, axis=0), Yw

    @staticmethod
    def rss(G: np.ndarray, b: np.ndarray, yy: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual sum of squares of the GLS fit on ``cols`` and its coefficients (S, k)."""
        Gs = G[:, cols[:, None], cols[None, :]]
        bs = b[:, cols]
        w, V = np.linalg.eigh(Gs)
        keep = w > RANK_TOL * w[:, -1:]
        winv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
        proj = np.einsum("sij,sj->si", V, winv * np.einsum("sji,sj->si", V, bs))
        return yy - np.sum(bs * proj, axis=1), proj

    def lr(self, G: np.ndarray, b: np.ndarray, yy: np.ndarray, base: np.ndarray, alt: np.ndarray) -> np.ndarray:
        r0 = self.rss(G, b, yy, base)[0]
        r1 = self.rss(G, b, yy, alt)[0]
        return self.n * np.log(np.maximum(r0, 1e-300) / np.maximum(r1, 1e-300))

    def gls(self, blocks: list[str]) -> dict[str, Any]:
        """Real-data GLS fit with J + blocks: coefficients (unscaled), covariance, rho, sigma, whitened residual."""
        cols = self.cols(blocks)
        y = self.y[:, None]
        rho = self.rho(self.ols_resid(cols, y))
        G, b, yy, Yw = self.forms(y, rho)
        rss, beta = self.rss(G, b, yy, cols)
        k = self.rank(cols)
        sigma2 = float(rss[0]) / max(self.n - k, 1)
        Gs = G[0][np.ix_(cols, cols)]
        cov = sigma2 * np.linalg.pinv(Gs, rcond=RANK_TOL, hermitian=True)
        sc = self.scale[cols]
        coef = beta[0] / sc
        cov = cov / np.outer(sc, sc)
        fitted = self.Z[:, cols] @ beta[0]
        resid_w = self.whiten((self.y - fitted)[:, None], rho)[:, 0]
        return {"cols": cols, "coef": coef, "beta_scaled": beta[0], "cov": cov, "rho": float(rho[0]),
                "sigma": math.sqrt(max(sigma2, 0.0)), "resid": self.y - fitted, "resid_w": resid_w, "rss": float(rss[0]),
                "G": G, "b": b, "yy": yy}


# --------------------------------------------------------------------------------------------------
# The mains line scan
# --------------------------------------------------------------------------------------------------

def _scan_lines(t: np.ndarray, e: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Projection of the whitened residual e onto span{V_j cos wt, V_j sin wt} on a frequency grid.

    Uses ``q(f) = 2 c^H (V'V)^+ c`` with ``c_j = sum_i e_i V_ij exp(-2 pi i f t_i)`` (the sinusoids' Gram
    matrix is V'V / 2 away from 0 and Nyquist, and whitening a slowly modulated sinusoid keeps its span).
    Returns (frequencies, q, number of independent frequencies).
    """
    T = float(t[-1] - t[0])
    dt = np.diff(t)
    med = float(np.median(dt))
    # the band stops one independent frequency short of 0 and of Nyquist, where the sine column vanishes
    # and the two-column approximation below would double-count (a line exactly at Nyquist is missed)
    f_lo, f_hi = SCAN_MIN_CYCLES / T, 0.5 / med - 1.0 / T
    n_indep = int(max(1, math.floor((f_hi - f_lo) * T)))
    Vi = np.linalg.pinv(V.T @ V, rcond=1e-10)
    EV = e[:, None] * V
    grid = np.round((t - t[0]) / med).astype(int)
    n_freq = SCAN_OVERSAMPLE * (f_hi - f_lo) * T
    if len(t) * n_freq > 5e7:
        # long records: each sample on the nearest point of a uniform grid (exact when sampling is
        # uniform; the few blocks shortened at a step change move by under half a step, two that land on
        # one point are added), then an FFT. The exact fit at the chosen frequency uses the true times.
        L = int(grid[-1]) + 1
        X = np.zeros((L, V.shape[1]))
        np.add.at(X, grid, EV)
        nfft = int(SCAN_OVERSAMPLE * L)
        C = np.fft.rfft(X, n=nfft, axis=0)  # frequencies k / (nfft med)
        f = np.fft.rfftfreq(nfft, d=med)
    else:
        span = T * SCAN_OVERSAMPLE
        f = np.arange(math.ceil(f_lo * span), math.floor(f_hi * span) + 1) / span
        C = np.empty((len(f), V.shape[1]), dtype=complex)
        for a in range(0, len(f), 256):
            ph = np.exp(-2j * np.pi * np.outer(f[a:a + 256], t))
            C[a:a + 256] = ph @ EV
    q = 2.0 * np.real(np.einsum("fi,ij,fj->f", C.conj(), Vi, C))
    keep = (f >= f_lo) & (f <= f_hi)
    return f[keep], q[keep], n_indep


def _neighbour_mean(q: np.ndarray, half: int, gap: int) -> np.ndarray:
    """Mean of q over the bins within ``half`` of each bin but farther than ``gap`` (the line's own main
    lobe), the spectrum mirrored at its ends. A mean, not a median: the projections are a weighted
    chi-square whose median depends on the weights, its mean does not."""
    pad = np.concatenate([q[half:0:-1], q, q[-2:-half - 2:-1]]) if q.size > half + 1 else np.pad(q, half, mode="edge")
    c = np.concatenate([[0.0], np.cumsum(pad)])
    idx = np.arange(q.size) + half
    total = c[idx + half + 1] - c[idx - half]
    inner = c[idx + gap + 1] - c[idx - gap]
    return (total - inner) / (2 * half - 2 * gap)


def _line_at(t: np.ndarray, e: np.ndarray, V: np.ndarray, f: float) -> float:
    """Exact projection of e onto span{V cos, V sin} at one frequency (for refining the peak)."""
    w = 2 * np.pi * f * t
    X = np.hstack([V * np.cos(w)[:, None], V * np.sin(w)[:, None]])
    beta = np.linalg.lstsq(X, e, rcond=None)[0]
    return float(np.sum((X @ beta) ** 2))


# --------------------------------------------------------------------------------------------------
# Noise floor
# --------------------------------------------------------------------------------------------------

def _noise_floor(d: _Data, resid_lsb: np.ndarray, notes: list[str]) -> dict[str, Any]:
    """Per-axis noise (sigma, lag-1 autocorrelation) from static segments, else from the residual's high-pass."""
    n = len(d)
    dt = np.diff(d.t)
    med = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    w = max(STATIC_MIN_WINDOW, int(round(STATIC_WINDOW_S / med)))
    sigma_hp = _highpass_sd(resid_lsb)
    labelled = np.array([bool(STATIC_LABEL.match(str(s))) for s in d.step])
    static = labelled.copy()
    windows: list[tuple[int, int]] = []
    for a in range(0, n - w + 1, w):
        seg = d.mag[a:a + w]
        quiet = bool(np.all(seg.std(axis=0) < STATIC_FACTOR * max(sigma_hp, 1e-9)))
        if quiet or labelled[a:a + w].all():
            static[a:a + w] = True
            windows.append((a, a + w))
    out: dict[str, Any] = {"sigma_hp_lsb": sigma_hp, "static_samples": int(static.sum()),
                           "static_labelled": int(labelled.sum()), "window": w}
    if len(windows) >= 2:
        E = []
        x = np.arange(w) - (w - 1) / 2.0
        for a, b in windows:  # remove each window's mean and slope: what is left is the sample noise
            seg = d.mag[a:b]
            slope = (x @ (seg - seg.mean(axis=0))) / (x @ x)
            E.append(seg - seg.mean(axis=0) - np.outer(x, slope))
        E = np.array(E)  # (windows, w, 3)
        dof = w - 2
        sigma = np.sqrt(np.sum(E ** 2, axis=(0, 1)) / (len(windows) * dof))
        ar1 = np.sum(E[:, 1:] * E[:, :-1], axis=(0, 1)) / np.maximum(np.sum(E ** 2, axis=(0, 1)), 1e-300)
        out.update(sigma=sigma, ar1=ar1, source=f"{len(windows)} static windows of {w} samples")
    else:
        r = resid_lsb - resid_lsb.mean()
        rho = float(np.sum(r[1:] * r[:-1]) / max(np.sum(r ** 2), 1e-300))
        out.update(sigma=np.full(3, sigma_hp), ar1=np.full(3, rho),
                   source="no static segment: the magnitude residual's high-pass (first differences / sqrt 2), "
                          "repeated for the three axes")
        notes.append("no static segment found: the noise floor is the magnitude residual's high-pass (first "
                     "differences / sqrt 2, robust), the same for the three axes; noise_ar1 is the residual's lag-1 "
                     "autocorrelation")
    return out


# --------------------------------------------------------------------------------------------------
# Discovery beyond the catalogue: an offset present for a while (issue 12)
# --------------------------------------------------------------------------------------------------

#: Frames in which the attitude-free model searches for an offset present for a while: fixed to the unit
#: (a magnetised object attached to it: the magnitude sees it through the field's direction in the sensor
#: frame, 3 parameters) or to the room (a steel object nearby, or the unit carried to where the field
#: differs: the magnitude sees the part along the field, the dip the part across it in the vertical
#: plane, a step each; the horizontal part across the field turns only the heading, which needs a
#: heading reference). A stage's frame needs table angles.
WINDOW_FRAMES = ("sensor", "lab")
#: At most this many windows join one recording's model.
MAX_WINDOWS = 3
#: Samples per time bin the window search needs (fewer: a recording of a few seconds, not searched).
MIN_PER_BIN = 10
#: A window's two frames count as alike when their evidence (statistic less twice the parameters) in it
#: differs by less than this.
ALIKE_EVIDENCE = 2.0


def _offset_columns(nom: _Nominal, d: _Data, frame: str) -> dict[str, np.ndarray]:
    """Columns of an offset fixed in ``frame`` on each response (LSB-equivalent per parameter), constant in
    time: per count on each sensor axis (sensor), per field unit along the field and radian of dip (lab)."""
    kb, n = nom.kbar, len(d)
    sensor = frame == "sensor"
    out = {"magnitude": kb * nom.shape.grad(d.mag) if sensor else np.full((n, 1), kb)}
    if nom.dip is not None and d.acc is not None:
        out["dip"] = kb * _dip_gradient(nom, _rows(nom, d, False)) if sensor else np.full((n, 1), kb)
    return out


def _add_window(designs: dict[str, _Design], cols: dict[str, np.ndarray], name: str, mask: np.ndarray) -> None:
    """A windowed offset as a block of the magnitude and a nuisance block of the dip ("<name>@dip")."""
    for resp, X in cols.items():
        if resp in designs:
            designs[resp].blocks[name if resp == "magnitude" else name + "@dip"] = X * mask[:, None]


def _inside(t: np.ndarray, segments: list[list[float]]) -> np.ndarray:
    """Which samples fall in any of the windows [start, end)."""
    m = np.zeros(len(t), bool)
    for a, b in segments:
        m |= (t >= a) & (t < b)
    return m


def _responses(reg: dict[str, _Regression], given: list[str]) -> list[tuple]:
    """Per response (the magnitude, and the dip when there is one): its name, regression, AR(1) coefficient,
    whitening, the whitened basis Q of its model (the magnitude's blocks ``given``, the dip's nuisance share
    of them) and its whitened residual orthogonal to Q scaled to unit noise, with that scale. What every
    frame's :class:`_Sums` of one round shares."""
    out = []
    for resp in ("magnitude", "dip"):
        if resp not in reg:
            continue
        r = reg[resp]
        model = given if resp == "magnitude" else [b + "@dip" for b in given if b + "@dip" in r.slices]
        rho = r.gls(model)["rho"]
        white = lambda M, rho=rho, r=r: r.whiten(M, np.full(M.shape[1], rho))  # noqa: E731
        Q = _orth(white(r.Z[:, r.cols(model)]))
        yw = white(r.y[:, None])[:, 0]
        y = yw - Q @ (Q.T @ yw)
        s = math.sqrt(float(y @ y) / max(len(y) - Q.shape[1], 1))
        out.append((resp, r, rho, white, Q, y / s, s))
    return out


def _joint_test(responses: list[tuple], given: list[str], blk: str, null_sims: int, rng: np.random.Generator,
                n_tests: int) -> "_Test":
    """Block ``blk`` of raw-count distortions tested on the magnitude and the dip at once, one set of parameters
    for both (its columns are ``blk`` on the magnitude and ``blk@dip`` on the dip), given the magnitude's blocks
    ``given`` (and the dip's share of them): each response AR(1)-whitened, its model projected out and scaled
    to unit noise (``responses``: :func:`_responses` of ``given``, shared by the blocks tested), the statistic c' G+ c of the stacked rows. Its Bartlett factor (at least
    1) is the mean over ``null_sims`` simulated nulls treated alike, p from chi-square on the rank, Bonferroni
    over ``n_tests``. The joint estimate and its covariance (parameter units) go in ``extra``."""
    c = np.zeros(3)
    G = np.zeros((3, 3))
    B = np.zeros((3, 3))
    parts = []
    for resp, r, rho, white, Q, y, s in responses:
        name = blk if resp == "magnitude" else blk + "@dip"
        if name not in r.slices:
            continue
        sl = r.slices[name]
        Xw = white(r.Z[:, sl] * r.scale[sl]) / s
        Xp = Xw - Q @ (Q.T @ Xw)
        c, G, B = c + Xp.T @ y, G + Xp.T @ Xp, B + Xw.T @ Xw
        parts.append((r, rho, white, Q, Xp))
    w, V = np.linalg.eigh(0.5 * (G + G.T))
    keep = w > KEEP_SHARE * max(float(np.trace(B)) / 3.0, 1e-300)
    df = int(keep.sum())
    Ginv = (V[:, keep] / w[keep]) @ V[:, keep].T
    raw = float(c @ Ginv @ c)
    scale = 1.0
    if null_sims >= 20 and df > 0:
        cn = np.zeros((null_sims, 3))
        for r, rho, white, Q, Xp in parts:
            Y = white(r.simulate(rho, null_sims, rng))
            Y = Y - Q @ (Q.T @ Y)
            Y = Y / np.sqrt(np.sum(Y ** 2, axis=0) / max(len(Y) - Q.shape[1], 1))
            cn += (Xp.T @ Y).T
        scale = max(1.0, float(np.mean(np.einsum("kp,pq,kq->k", cn, Ginv, cn))) / df)
    tt = _Test("discovered", BLOCKS[blk][1], "magnitude", blk, "joint", tuple(given))
    tt.raw, tt.df = raw, df
    tt.statistic = raw / scale
    tt.p = float(stats.chi2.sf(tt.statistic, df)) if df > 0 else 1.0
    tt.p_adj = min(1.0, tt.p * n_tests)
    tt.extra = {"bartlett": scale, "coef": Ginv @ c, "cov": Ginv * scale}
    return tt


@dataclass
class _Window:
    """The best windows of one frame's offset (one set of parameters), their p corrected for the search."""

    frame: str
    segments: list[list[float]]  # [start, end) in the recording's t
    statistic: float  # at the refined edges, scaled by the nulls' mean (a Bartlett factor)
    df: int
    log_p: float  # of the grid's best, corrected for the search (not yet for the tests run)
    m_eff: float
    scale: float


class _Sums:
    """One frame's offset (columns ``cols`` per response, :func:`_offset_columns`) against the residual of each
    response of ``responses`` (:func:`_responses`), AR(1)-whitened, the current model projected out and
    scaled to unit noise: per sample what a window's statistic is made of, as prefix sums. The offset's
    parameters are shared by the responses: a sensor offset's three counts act on both; a lab offset's two
    visible parts are separate parameters (the step along the field on the magnitude, across it on the dip)."""

    def __init__(self, responses: list[tuple], cols: dict[str, np.ndarray], frame: str) -> None:
        self.parts = []
        A = B = None
        Qx = []
        present = [x for x in responses if x[0] in cols]
        for k, (resp, r, rho, white, Q, y, s) in enumerate(present):
            X = cols[resp]
            if frame == "lab" and len(present) == 2:  # [along, across]: each response sees one
                X = np.column_stack([X[:, 0] * (k == 0), X[:, 0] * (k == 1)])
            Xw = white(X) / s
            A = Xw * y[:, None] + (0.0 if A is None else A)
            B = Xw[:, :, None] * Xw[:, None, :] + (0.0 if B is None else B)
            Qx.append(Q[:, :, None] * Xw[:, None, :])
            self.parts.append((r, rho, Q, Xw, white))
        prefix = lambda M: np.concatenate([np.zeros((1,) + M.shape[1:]), np.cumsum(M, axis=0)])  # noqa: E731
        self.p = B.shape[1]
        self.PA, self.PB, self.PQ = prefix(A), prefix(B), prefix(np.concatenate(Qx, axis=1))

    def stats(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Statistic and rank of each set of windows [lo, hi) (sample indices, (K, m): m windows with one set
        of parameters)."""
        part = lambda P: (P[hi] - P[lo]).sum(axis=1)  # noqa: E731
        B, Cq = part(self.PB), part(self.PQ)
        G = B - np.einsum("wkp,wkq->wpq", Cq, Cq)
        T, df = _inverse_roots(0.5 * (G + np.transpose(G, (0, 2, 1))),
                               KEEP_SHARE * np.maximum(np.trace(B, axis1=1, axis2=2) / self.p, 1e-300))
        return _window_stats(part(self.PA), T), df

    def bins(self, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The grid's sums for :func:`discovery.search_bins`: G (bins, p, bins, p), diag0, c."""
        at = lambda P: P[edges[1:]] - P[edges[:-1]]  # noqa: E731
        d0, Cb = at(self.PB), at(self.PQ)
        G = -np.einsum("jkp,lkq->jplq", Cb, Cb)
        for j in range(len(d0)):
            G[j, :, j, :] += d0[j]
        return G, d0, at(self.PA)

    def null_bins(self, edges: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
        """c of :meth:`bins` for ``count`` simulated nulls (AR(1) at each response's coefficient, whitened and
        projected alike, each scaled to unit noise by its own estimate): (count, bins, p)."""
        out = np.zeros((count, len(edges) - 1, self.p))
        for r, rho, Q, Xw, white in self.parts:
            Y = white(r.simulate(rho, count, rng))
            Y = Y - Q @ (Q.T @ Y)
            Y = Y / np.sqrt(np.sum(Y ** 2, axis=0) / max(len(Y) - Q.shape[1], 1))
            out += np.transpose(np.array([Xw[a:b].T @ Y[a:b] for a, b in zip(edges[:-1], edges[1:])]), (2, 0, 1))
        return out


def _search_window(sums: _Sums, t: np.ndarray, frame: str, null_sims: int, rng: np.random.Generator) -> _Window | None:
    """The windows (one, or two or three with the same parameters: something switched on and off) in which
    the offset of ``sums`` best explains the residuals: the table model's search over a grid of N_BINS equal
    time bins (:func:`discovery.search_bins`, p corrected by the effective number of windows measured on
    ``null_sims`` simulated nulls searched the same way), then each edge refined to the samples."""
    n = len(t)
    edges = np.searchsorted(t, t[0] + np.arange(N_BINS + 1) * max(float(t[-1] - t[0]), 1e-9) / N_BINS)
    edges[-1] = n
    G, d0, c = sums.bins(edges)
    ws = search_bins(G, d0, c, sums.null_bins(edges, null_sims, rng) if null_sims >= 20 else None)
    if ws is None:
        return None
    win = sorted([[int(edges[ws.a]), int(edges[ws.b])]] + [[int(edges[a]), int(edges[b])] for a, b in ws.others])
    width = max(n // N_BINS, 1)
    for _ in range(2):  # each edge in turn to the sample that explains most, within a bin of it
        for k in range(len(win)):
            for side in (0, 1):
                cand = np.arange(max(win[k][side] - width, 0), min(win[k][side] + width, n) + 1)
                lo = np.array([[w[0] for w in win]] * len(cand))
                hi = np.array([[w[1] for w in win]] * len(cand))
                (lo if side == 0 else hi)[:, k] = cand
                good = np.all(hi - lo > sums.p, axis=1) & np.all(lo[:, 1:] >= hi[:, :-1], axis=1)
                good &= ~((lo[:, 0] == 0) & (hi[:, -1] == n) & (len(win) == 1))
                if not good.any():
                    continue
                st, df = sums.stats(lo[good], hi[good])
                j = int(np.argmax(np.where(df == ws.df, st, -np.inf)))
                win[k][side] = int(cand[good][j])
    st, _ = sums.stats(np.array([[w[0] for w in win]]), np.array([[w[1] for w in win]]))

    def edge(k: int) -> float:  # between the samples on either side (the run's own ends at the ends)
        return float(t[0]) if k == 0 else float(t[-1]) + 1e-6 if k >= n else float(0.5 * (t[k - 1] + t[k]))

    return _Window(frame, [[edge(a), edge(b)] for a, b in win], float(st[0]) / ws.scale, ws.df, ws.log_p, ws.m_eff,
                   ws.scale)


def _discover(feats: dict[str, _Design], nom: _Nominal, dec: _Data, base: list[str], null_sims: int,
              rng: np.random.Generator, n_tests: int, alpha: float) -> list["_Test"]:
    """Windowed offsets joining the magnitude's model one at a time (up to MAX_WINDOWS), given the blocks
    ``base``: each round the best windows of each frame (:func:`_search_window`), the one with the smallest p
    kept while its p times ``n_tests`` is below ``alpha``. Each kept window's columns are added to ``feats``
    (the magnitude's block, the dip's nuisance); returns their tests."""
    out: list[_Test] = []
    cols = {fr: _offset_columns(nom, dec, fr) for fr in WINDOW_FRAMES}
    while len(out) < MAX_WINDOWS:
        reg = {nm: _Regression(nm, des, dec.t) for nm, des in feats.items()}
        given = base + [tt.block for tt in out]
        responses = _responses(reg, given)
        sums = {fr: _Sums(responses, cols[fr], fr) for fr in WINDOW_FRAMES}
        found = [w for fr in WINDOW_FRAMES if (w := _search_window(sums[fr], dec.t, fr, null_sims, rng))]
        if not found:
            break
        best = min(found, key=lambda w: (w.log_p, -w.statistic))
        p = float(np.exp(best.log_p))
        if p * n_tests >= alpha:
            break
        segs = best.segments
        name = f"discovered:{best.frame}/offset/segments@" + "".join(f"[{a:.1f},{b:.1f})" for a, b in segs)
        _add_window(feats, cols[best.frame], name, _inside(dec.t, segs))
        # the other frame in the same windows: alike when its evidence (statistic less twice its parameters) is as good
        lo = np.array([[int(np.searchsorted(dec.t, a)) for a, _ in segs]])
        hi = np.array([[int(np.searchsorted(dec.t, b)) for _, b in segs]])
        evidence = {fr: float(x[0][0] - 2 * x[1][0]) for fr in WINDOW_FRAMES if (x := sums[fr].stats(lo, hi))}
        alike = [fr for fr in WINDOW_FRAMES if fr != best.frame and evidence[fr] > evidence[best.frame] - ALIKE_EVIDENCE]
        tt = _Test("discovered", f"an offset {FRAME_TEXT[best.frame]}, present for a while (window search)",
                   "magnitude", name, "window", tuple(given))
        tt.statistic, tt.raw, tt.df, tt.p = best.statistic, best.statistic * best.scale, best.df, p
        tt.p_adj, tt.selected = min(1.0, p * n_tests), True
        tt.extra = {"bartlett": best.scale, "frame": best.frame, "segments": segs, "m_eff": best.m_eff, "alike": alike}
        out.append(tt)
    return out


def _gain_finding(blk: str, tt: "_Test", coef: np.ndarray, se: np.ndarray, nom: _Nominal, d: _Data,
                  cos_dip: float | None) -> dict[str, Any]:
    """A discovered smooth change of the unit's sensitivity (:data:`GAIN_BLOCKS`) as a finding of the one schema."""
    sh = nom.shape
    against = GAIN_BLOCKS[blk][0]
    g, g_sd = np.where(sh.resolved, coef, np.nan), np.where(sh.resolved, se, np.nan)
    rows = _rows(nom, d, against == "temp_c")
    delta = np.einsum("njk,k->nj", _gain_bases(nom, rows)[blk], np.nan_to_num(g))
    pct = lambda v: ", ".join("n/a" if not np.isfinite(x) else f"{100 * x:.3g}" for x in v)  # noqa: E731
    block = Block("sensor", "gain", against)
    if against == "temp_c":
        span = float(np.ptp(d.temp))
        params, sigma = {"gain_per_degC": g.tolist()}, {"gain_per_degC": g_sd.tolist()}
        size = f"({pct(g)}) % per deg C (+- {pct(g_sd)}) on x, y, z"
    else:
        span = 2.0
        params, sigma = {"gain_over_half_run": g.tolist()}, {"gain_over_half_run": g_sd.tolist()}
        size = f"({pct(g)}) % from the middle of the run to its end (+- {pct(g_sd)}) on x, y, z"
    plausible = bool(np.max(np.nan_to_num(np.abs(g)) * span) < 0.2)  # a fifth of the sensitivity over the run is a fault
    expl = (f"A change of sensitivity of {size}, {FRAME_TEXT['sensor']}, {AGAINST_TEXT[against]}: {_cause(block)}. "
            + FOUND_BY_SEARCH + ("" if plausible else " " + IMPLAUSIBLE))
    return {"effect": "discovered", "variant": tt.variant, "statistic": tt.statistic, "df": tt.df, "p_value": tt.p,
            "p_adjusted": tt.p_adj, "parameters": params, "sigma": sigma,
            "heading_impact_deg": _perp_impact(sh, d.mag, delta, cos_dip),
            "where": {"response": "magnitude", "frame": "sensor"},
            "model": {"frame": "sensor", "form": "gain", "against": against, "segments": []},
            "plausible": plausible, "explanation": expl, "confusable_with": [],
            "separating_experiment": confirming_experiment(block, [])}


def _rotation_finding(blk: str, tt: "_Test", nom: _Nominal, d: _Data, cos_dip: float | None) -> dict[str, Any]:
    """A discovered turn of the magnetometer's axes against the accelerometer's (:data:`ROTATION_BLOCKS`), with
    the joint estimate of :func:`_joint_test`, as a finding of the one schema."""
    against = ROTATION_BLOCKS[blk][0]
    w = np.asarray(tt.extra["coef"], float)
    w_sd = np.sqrt(np.maximum(np.diag(np.asarray(tt.extra["cov"], float)), 0.0))
    deg, deg_sd = np.degrees(w), np.degrees(w_sd)
    rows = _rows(nom, d, against == "temp_c")
    delta = np.einsum("njk,k->nj", _rotation_bases(nom, rows)[blk], w)
    size = "(" + ", ".join(f"{x:.3g} +- {e:.2g}" for x, e in zip(deg, deg_sd)) + ") deg about x, y, z"
    if against == "temp_c":
        span = float(np.ptp(d.temp))
        params, sigma = {"rotation_deg_per_degC": deg.tolist()}, {"rotation_deg_per_degC": deg_sd.tolist()}
        size += " per deg C"
        cause = "the board or the mount warps as it warms, turning the magnetometer against the accelerometer"
    else:
        span = 2.0
        params, sigma = {"rotation_deg_over_half_run": deg.tolist()}, {"rotation_deg_over_half_run": deg_sd.tolist()}
        size += " from the middle of the run to its end"
        cause = "the magnetometer's mount creeping against the accelerometer's (adhesive, clamp, thermal settling)"
    # a turn beyond the largest misalignment a unit is built with is a fault or a stand-in
    plausible = bool(float(np.linalg.norm(deg)) * span < MISALIGNMENT_LIMIT_DEG)
    block = Block("sensor", "rotation", against)
    expl = (f"The magnetometer's axes turning against the accelerometer's by {size}, {AGAINST_TEXT[against]}: "
            f"{cause}. It turns the field against gravity (the dip), not its magnitude. "
            + FOUND_BY_SEARCH + ("" if plausible else " " + IMPLAUSIBLE))
    return {"effect": "discovered", "variant": tt.variant, "statistic": tt.statistic, "df": tt.df, "p_value": tt.p,
            "p_adjusted": tt.p_adj, "parameters": params, "sigma": sigma,
            "heading_impact_deg": _perp_impact(nom.shape, d.mag, delta, cos_dip),
            "where": {"response": "magnitude and dip", "frame": "sensor"},
            "model": {"frame": "sensor", "form": "rotation", "against": against, "segments": []},
            "plausible": plausible, "explanation": expl, "confusable_with": [],
            "separating_experiment": confirming_experiment(block, [])}


def _window_finding(tt: _Test, coef: np.ndarray, se: np.ndarray, nom: _Nominal, d: _Data, uc: float | None,
                    cos_dip: float | None, dip: tuple[float, float] | None) -> dict[str, Any]:
    """A discovered windowed offset as a finding of the one schema (effect "discovered"). ``dip``: the
    dip's step in the window (rad, and its sigma) for a lab-frame offset, when there is a dip."""
    sh, kb = nom.shape, nom.kbar
    frame, segs = tt.extra["frame"], tt.extra["segments"]
    mask = _inside(d.t, segs)
    block = Block(frame, "offset", "segments")
    # the bias (an offset on the unit) and the field's size (one in the room) take in what is constant
    # through the run: a window that reaches its start or end is one change at one time
    step = step_time(segs, d.t)
    cause = INTERMITTENT if len(segs) > 1 else _cause(block, step is not None)
    when = window_text(segs, step)
    impact: float | None
    if frame == "sensor":
        lsb, lsb_sd = np.where(sh.resolved, coef, np.nan), np.where(sh.resolved, se, np.nan)  # an axis in-plane data leave unseen: n/a
        params: dict[str, Any] = {"labels": ["d[0]", "d[1]", "d[2]"], "values": lsb.tolist(), "offset_lsb": lsb.tolist()}
        sigma: dict[str, Any] = {"values": lsb_sd.tolist(), "offset_lsb": lsb_sd.tolist()}
        params["offset_field_units"] = (lsb / sh.k).tolist()
        size = "(" + ", ".join("n/a" if not np.isfinite(x) else f"{x:.3g} +- {e:.2g}" for x, e in zip(lsb, lsb_sd)) + ") LSB"
        if uc is not None:
            params["offset_ut"], sigma["offset_ut"] = (lsb * uc).tolist(), (lsb_sd * uc).tolist()
            size += f" = ({_fmt3(lsb * uc, '.3g')}) uT"
        else:
            size += f" ({100 * float(np.linalg.norm(np.nan_to_num(lsb / sh.k))):.2g} % of the field)"
        impact = _perp_impact(sh, d.mag, mask[:, None] * np.nan_to_num(lsb)[None, :], cos_dip)
        plausible = bool(np.linalg.norm(np.nan_to_num(lsb / sh.k)) < 2.0)
        expl = f"An offset of {size} {FRAME_TEXT['sensor']}{when}: {cause}."
    else:
        along, along_sd = float(coef[0]), float(se[0])
        params = {"labels": ["along_field"], "values": [along], "along_field_pct": 100 * along,
                  "along_field_lsb": along * kb}
        sigma = {"values": [along_sd], "along_field_pct": 100 * along_sd, "along_field_lsb": along_sd * kb}
        part = f"{100 * along:.2g} +- {100 * along_sd:.1g} % of the field along it"
        if dip is not None:
            params["dip_change_deg"], sigma["dip_change_deg"] = math.degrees(dip[0]), math.degrees(dip[1])
            part += f" and a turn of {math.degrees(dip[0]):.2g} +- {math.degrees(dip[1]):.1g} deg of its dip"
        impact = None  # the horizontal part across the field turns the heading, but needs a heading reference
        plausible = bool(abs(along) < 1.0)
        expl = (f"A change of the field {FRAME_TEXT['lab']}{when}: {part}; {cause}. Its horizontal "
                "part across the field, which turns the heading, does not show without a heading reference.")
    expl += " " + FOUND_BY_SEARCH + ("" if plausible else " " + IMPLAUSIBLE)
    alike = list(tt.extra.get("alike", []))
    experiment = confirming_experiment(block, segs, step)
    if alike:
        expl += f" This recording cannot tell it from an offset {FRAME_TEXT[alike[0]]}; the one named fits better."
        experiment += ("; to tell them apart, turn the unit through several attitudes during that time (an offset on "
                       "the unit turns with it, one in the room does not)")
    return {"effect": "discovered", "variant": tt.variant, "statistic": tt.statistic, "df": tt.df,
            "p_value": tt.p, "p_adjusted": tt.p_adj, "parameters": params, "sigma": sigma,
            "heading_impact_deg": impact, "where": {"response": "magnitude", "frame": frame},
            "model": {"frame": frame, "form": "offset", "against": None, "segments": [[float(a), float(b)] for a, b in segs]},
            "plausible": plausible, "explanation": expl, "confusable_with": [f"discovered:{a}/offset" for a in alike],
            "separating_experiment": experiment, "effective_windows": tt.extra.get("m_eff")}


# --------------------------------------------------------------------------------------------------
# The analysis
# --------------------------------------------------------------------------------------------------

@dataclass
class _Test:
    effect: str
    variant: str
    response: str
    block: str | None  # None: whiteness
    kind: str  # "lr" | "scan" | "whiteness"
    given: tuple[str, ...] = ()
    statistic: float = float("nan")  # Bartlett-corrected
    raw: float = float("nan")
    df: int = 0
    p: float = float("nan")
    p_adj: float = float("nan")
    selected: bool = False
    extra: dict[str, Any] = field(default_factory=dict)


def _p_value(test: _Test, c: float, n_indep: int) -> float:
    stat = test.raw / c
    test.statistic = stat
    p1 = float(stats.chi2.sf(stat, test.df)) if test.df > 0 else 1.0
    if test.kind == "scan":  # the line was the best of n_indep independent frequencies
        return float(-np.expm1(n_indep * np.log1p(-min(p1, 1.0 - 1e-16)))) if p1 < 1 else 1.0
    return p1


def analyze_attitude_free(rec: Recording, *, alpha: float = 0.01, null_sims: int = 200,
                          rng: np.random.Generator | None = None,
                          progress: Callable[[str, float], None] | None = None) -> Any:
    """Analyse a recording without table angles (see module docstring); returns an Analysis.

    Table angles, when present, are not used (the series carries them through). Raises InsufficientData
    when the readings cannot support the nominal model.
    """
    def report(stage: str, frac: float) -> None:
        if progress is not None:
            progress(stage, frac)

    rng = np.random.default_rng(20240606) if rng is None else rng
    notes: list[str] = []
    if len(rec) < MIN_SAMPLES:
        raise InsufficientData(f"attitude-free model: needs at least {MIN_SAMPLES} samples, got {len(rec)}")
    report("prepare", 0.0)
    full = _columns(rec, notes)
    if rec.has_angles:
        notes.append("the recording has table angles; the attitude-free model does not use them")
    factor = int(math.ceil(len(full) / MAX_SAMPLES))
    dec, block_of_row = _decimate(full, factor)
    if factor > 1:
        notes.append(f"{len(full)} samples block-averaged by {factor} (blocks never straddle a step or a time gap) "
                     f"to {len(dec)} for the fits and tests; a line above the new Nyquist frequency "
                     f"{0.5 / float(np.median(np.diff(dec.t))):.3g} Hz is attenuated and folded. Residuals, RMS "
                     "and the noise floor are given per original sample")

    # ---- nominal model ----------------------------------------------------------------------------
    shape = _fit_shape(dec.mag, notes)
    t0, t1 = float(full.t[0]), float(full.t[-1])
    duration = t1 - t0
    if duration <= 0:
        raise InsufficientData("attitude-free model: all samples have the same time stamp")
    temp_varies = dec.temp is not None and float(np.ptp(dec.temp)) >= 0.2
    if dec.temp is not None and not temp_varies:
        notes.append("temp_c is logged but constant (within 0.2 deg C): temperature drift is tested against time")
    nom = _Nominal(shape=shape, acc=None, dip=None, t_mid=0.5 * (t0 + t1), t_half=0.5 * duration,
                   temp_ref=float(np.mean(full.temp)) if full.temp is not None else None)
    untestable: list[dict[str, str]] = [{"effect": e, "reason": r} for e, r in NEEDS_ANGLES.items()]
    lag_ok = False

    def dip_not_tested(why: str, record: str) -> None:
        notes.append(f"the dip (the field's angle to gravity) is not tested: {why}; the tests that need it (a turn of "
                     f"the field or of the axes, a lag between the sensors) are not available: {record}")

    if dec.acc is not None and not shape.planar:
        nom.acc = _AccCal(dec.acc, notes)
        if not nom.acc.calibrated:
            # its bias and scale errors move the dip from pose to pose, which no test here can tell from physics:
            # a clean table plan stripped of its angles named a turn of the axes (0.9 deg, p 3e-57) and lab windows
            dip_not_tested("the accelerometer's own calibration is not determined by these attitudes, and its bias "
                           "and scale errors would move the dip from attitude to attitude",
                           "record the unit through more attitudes")
        else:
            nom.dip = _Dip()
            nom.dip.fit(shape.direction(dec.mag), nom.acc.directions(dec.acc))
            if (separation := _dip_separation(nom, dec)) < DIP_MIN_SEPARATION:
                nom.dip = None
                dip_not_tested(f"these attitudes leave its nuisance (the field ellipsoid's calibration and the triads' "
                               f"rotation) nearly collinear (weakest combination {separation:.3f} of its RMS, at least "
                               f"{DIP_MIN_SEPARATION} needed), where its columns would fit the noise",
                               "record longer, turning the unit about every axis")
            elif dec.gyro is not None:
                lag_ok = True
    if not lag_ok:
        needs = ["an accelerometer" if dec.acc is None else "3-D field readings (a dip)" if shape.planar else
                 "the dip, not tested here (see the notes)" if nom.dip is None else None,
                 "gyro rates (extra columns gx, gy, gz)" if dec.gyro is None else None]
        why = "needs " + " and ".join(x for x in needs if x)
        untestable.append({"effect": "time_lag", "reason": f"attitude-free: the lag is seen as a dip change "
                                                           f"proportional to the rate of turn; {why}"})

    feats = _features(nom, dec, temp_varies)
    if lag_ok:  # a rotation about the vertical does not change the dip, so the lag may still be invisible
        x = feats["dip"].blocks["time_lag"][:, 0]
        sig = float(np.std(feats["dip"].y))
        if not np.std(x) * 0.05 > 1e-3 * max(sig, 1e-9):  # 50 ms of lag would move the dip by < 0.1 % of its spread
            del feats["dip"].blocks["time_lag"]
            lag_ok = False
            untestable.append({"effect": "time_lag", "reason": "the rotations barely change the angle between the "
                                                               "field and gravity (turns about the vertical), so a lag "
                                                               "does not show without a heading reference"})
    report("nominal", 0.1)

    # ---- mains scan (magnitude response, null model J) ------------------------------------------------
    reg = {name: _Regression(name, des, dec.t) for name, des in feats.items()}
    base_fit = reg["magnitude"].gls([])
    V = shape.kbar * shape.grad(dec.mag)
    f_grid, q, n_indep = _scan_lines(dec.t, base_fit["resid_w"], V)
    mains_ok = f_grid.size > 0
    scan_info: dict[str, Any] = {"n_independent_frequencies": n_indep}
    mains_scale = 1.0
    if mains_ok:
        # A line is an excess over its own neighbourhood of the spectrum: the residual may be coloured
        # beyond AR(1) (slow hand-motion structure), so each frequency's projection is compared with the
        # mean of its neighbours (SCAN_NEIGHBOURS independent frequencies each side, the line's own lobe
        # left out), converted to a noise level through the projection's dimension.
        dof = 2 * int(np.linalg.matrix_rank(V.T @ V, tol=1e-8 * np.abs(V.T @ V).max()))
        local = _neighbour_mean(q, SCAN_NEIGHBOURS * SCAN_OVERSAMPLE, 2 * SCAN_OVERSAMPLE)
        level_global = base_fit["rss"] / reg["magnitude"].n
        if f_grid.size > 4 * SCAN_NEIGHBOURS * SCAN_OVERSAMPLE:
            # never below the white level: the neighbourhood mean scatters by ~10 %, and the largest ratio
            # would favour spots where it happens to be low (only a raised floor, red noise, is corrected)
            local = np.maximum(local / dof, level_global)
        else:
            local = np.full_like(q, level_global)
        k = int(np.argmax(q / local))
        step = float(f_grid[1] - f_grid[0]) if f_grid.size > 1 else 0.0
        cand = np.linspace(f_grid[k] - step, f_grid[k] + step, 21) if step > 0 else np.array([f_grid[k]])
        cand = cand[(cand >= f_grid[0]) & (cand <= f_grid[-1])]
        qs = [_line_at(dec.t, base_fit["resid_w"], V, f) for f in cand]
        nom.mains_hz = float(cand[int(np.argmax(qs))])
        mains_scale = level_global / float(local[k])
        scan_info.update(peak_hz=nom.mains_hz, band_hz=[float(f_grid[0]), float(f_grid[-1])],
                         local_over_white_level=1.0 / mains_scale)
        feats = _features(nom, dec, temp_varies)
        if not lag_ok and "dip" in feats:
            feats["dip"].blocks.pop("time_lag", None)
        reg = {name: _Regression(name, des, dec.t) for name, des in feats.items()}
    else:
        untestable.append({"effect": "mains_interference", "reason": "the recording is too short for a line scan"})

    # ---- round 1: every named effect against the nominal model --------------------------------------
    tests: list[_Test] = []
    for name, r in reg.items():
        for blk in feats[name].blocks:
            if "@" in blk or blk in ROTATION_BLOCKS:  # nuisance for the dip, or tested on both responses at once
                continue
            eff, variant = BLOCKS[blk]
            if eff == UNEXPLAINED:
                continue
            tests.append(_Test(eff, variant, name, blk, "scan" if blk == "mains_interference" else "lr"))
    # the unexplained-structure tests, on each response: what a model of the magnitude alone cannot see
    # (a lag between the sensors, the hand's own acceleration) moves the dip by many times its noise
    unexplained = [_Test(UNEXPLAINED, variant, name, b, "whiteness" if b is None else "lr")
                   for name in reg for b, variant in (("unexplained/direction", BLOCKS["unexplained/direction"][1]),
                                                      ("unexplained/time", BLOCKS["unexplained/time"][1]),
                                                      (None, "whiteness (Ljung-Box on the prewhitened residual)"))
                   if b is None or b in reg[name].slices]
    # the window search of each frame (WINDOW_FRAMES) counts as one test each; it needs some samples per bin
    searchable = len(dec) >= MIN_PER_BIN * N_BINS
    turns = [b for b in ROTATION_BLOCKS if "dip" in reg and b in reg["magnitude"].slices]
    n_tests = len(tests) + len(unexplained) + (len(WINDOW_FRAMES) if searchable else 0) + len(turns)
    lb_lags = int(min(LB_LAGS, max(5, reg["magnitude"].n // 10)))

    # Bartlett factors from simulated nulls (null model J; AR(1) re-estimated in each simulation)
    bartlett: dict[tuple[str, str | None], float] = {}
    sims_used = 0
    for name, r in reg.items():
        jcols = r.cols([])
        y_fit = r.gls([])
        mine = [tt for tt in tests + unexplained if tt.response == name]
        for tt in mine:
            if tt.block is not None:
                tt.df = r.rank(r.cols([tt.block])) - r.rank(jcols)
        if null_sims <= 0:
            continue
        S_total, lr_sum, lb_sum = 0, {tt.block: 0.0 for tt in mine}, 0.0
        for a in range(0, null_sims, 50):
            S = min(50, null_sims - a)
            Y = r.simulate(y_fit["rho"], S, rng)
            rho_s = r.rho(r.ols_resid(jcols, Y))
            G, b, yy, _ = r.forms(Y, rho_s)
            for tt in mine:
                if tt.block is not None and tt.df > 0:
                    lr_sum[tt.block] += float(np.sum(r.lr(G, b, yy, jcols, r.cols([tt.block]))))
            if any(tt.kind == "whiteness" for tt in mine):
                _, beta = r.rss(G, b, yy, jcols)
                Ew = r.whiten(Y - r.Z[:, jcols] @ beta.T, rho_s)
                lb_sum += float(np.sum(ljung_box(Ew, lb_lags)))
            S_total += S
            report("nulls", 0.2 + 0.5 * (a + S) / null_sims * (list(reg).index(name) + 1) / len(reg))
        sims_used = S_total
        for tt in mine:
            if tt.kind == "whiteness":
                tt.df = lb_lags - 1
                bartlett[(name, None)] = max(1.0, lb_sum / S_total / tt.df)
            elif tt.df > 0:
                bartlett[(name, tt.block)] = max(1.0, lr_sum[tt.block] / S_total / tt.df)
    if null_sims <= 0:
        notes.append("null_sims = 0: no Bartlett correction (plain chi-square)")
    for tt in unexplained:
        if tt.kind == "whiteness":
            tt.df = lb_lags - 1

    def run(tt: _Test, given: tuple[str, ...]) -> _Test:
        """Fill in the real-data statistic of tt given the selected blocks."""
        r = reg[tt.response]
        out = _Test(tt.effect, tt.variant, tt.response, tt.block, tt.kind, given)
        c = bartlett.get((tt.response, tt.block), 1.0)
        base = r.cols(list(given))
        if tt.kind == "whiteness":
            g = r.gls(list(given))
            out.df = lb_lags - 1
            out.raw = float(ljung_box(g["resid_w"][:, None], lb_lags)[0])
            out.extra = {"lags": lb_lags, "residual_ar1": g["rho"]}
        else:
            alt = r.cols(list(given) + [tt.block])
            out.df = r.rank(alt) - r.rank(base)
            if out.df <= 0:
                out.raw, out.p = 0.0, 1.0
            else:
                y = r.y[:, None]
                rho = r.rho(r.ols_resid(base, y))
                G, b, yy, _ = r.forms(y, rho)
                out.raw = float(r.lr(G, b, yy, base, alt)[0])
                if tt.kind == "scan":  # referred to the spectrum's local level around the line
                    out.raw *= mains_scale
        if out.df > 0:
            out.p = _p_value(out, c, n_indep)
        else:
            out.statistic, out.p = 0.0, 1.0
        out.p_adj = min(1.0, out.p * n_tests)
        out.extra["bartlett"] = c
        return out

    report("tests", 0.75)
    done: list[_Test] = []
    # ---- greedy selection per response (magnitude first: the dip tests are run given the dip's share of
    # the effects the magnitude named, "<block>@dip") ------------------------------------------------------
    selected: dict[str, list[str]] = {name: [] for name in reg}
    fixed: dict[str, tuple[str, ...]] = {name: () for name in reg}
    sel_tests: dict[str, _Test] = {}
    absorbed: dict[str, str] = {}
    dropped: list[str] = []
    share: dict[str, float] = {}
    first: list[_Test] = []

    def select(name: str) -> None:
        """Greedy forward selection among the response's named tests (except those dropped)."""
        if selected[name] or any(tt.response == name for tt in done):  # a rerun without the dropped stand-ins
            for tt in done:
                if tt.response == name and "[superseded" not in tt.variant:
                    tt.selected = False
                    tt.variant += f" [superseded: selection rerun without {', '.join(dropped)}]"
        selected[name] = []
        for blk in [b for b in sel_tests if reg[name].slices.get(b) is not None]:
            del sel_tests[blk]
        round1 = [run(tt, fixed[name]) for tt in tests if tt.response == name and tt.block not in dropped]
        first.extend(round1)
        done.extend(round1)
        current = {tt.block: tt for tt in round1}
        while True:
            sig = [tt for tt in current.values() if tt.p_adj < alpha and tt.block not in selected[name]]
            if not sig:
                return
            best = min(sig, key=lambda tt: (tt.p, -tt.statistic))
            best.selected = True
            selected[name].append(best.block)
            sel_tests[best.block] = best
            rest = [b for b in current if b not in selected[name]]
            current = {b: current[b] for b in selected[name]}
            for b in rest:
                template = next(x for x in tests if x.block == b and x.response == name)
                tt = run(template, fixed[name] + tuple(selected[name]))
                done.append(tt)
                current[b] = tt
                if round1[[x.block for x in round1].index(b)].p_adj < alpha and tt.p_adj >= alpha:
                    absorbed.setdefault(b, best.block)

    def stand_in(blk: str) -> str | None:
        """Why a selected magnitude effect is only a stand-in for broader structure (None: it is not).

        Never forced onto a name: an effect whose regressors lie inside a generic block (a cubic
        non-linearity is one shape of structure against the field direction, a quadratic drift one shape
        against time) must carry at least GENERIC_SHARE of that block's evidence (likelihood ratio); any
        other must stay significant given both generic blocks (a hand-held path ties attitude to time, so
        direction structure can pose as a drift).
        """
        r = reg["magnitude"]
        others = [b for b in selected["magnitude"] if b != blk]
        if blk in GENERIC_OF:
            y = r.y[:, None]
            base = r.cols(others)
            G, b, yy, _ = r.forms(y, r.rho(r.ols_resid(base, y)))
            lr_named = float(r.lr(G, b, yy, base, r.cols(others + [blk]))[0])
            lr_block = float(r.lr(G, b, yy, base, r.cols(others + [blk, GENERIC_OF[blk]]))[0])
            share[blk] = lr_named / lr_block if lr_block > 0 else 1.0
            if share[blk] >= GENERIC_SHARE:
                return None
            return f"it carries only {100 * share[blk]:.0f} % of the structure against {BLOCKS[GENERIC_OF[blk]][1]}"
        tt = run(next(x for x in tests if x.block == blk and x.response == "magnitude"),
                 tuple(others) + ("unexplained/direction", "unexplained/time"))
        tt.variant += " (robustness: given the unexplained-structure blocks)"
        done.append(tt)
        if tt.p_adj < alpha:
            return None
        return f"it is not significant given smooth structure against direction and time (p_adj {tt.p_adj:.2g})"

    # magnitude: select, drop stand-ins, select again without them, until every name holds
    while True:
        select("magnitude")
        why = {b: stand_in(b) for b in selected["magnitude"]}
        bad = [b for b, w in why.items() if w is not None]
        if not bad:
            break
        for b in bad:
            dropped.append(b)
            notes.append(f"{BLOCKS[b][0]} ({BLOCKS[b][1]}) was significant but is not named: {why[b]}; its "
                         "structure is left to the unexplained-structure tests")
    # ---- discovery: an offset present for a while, in the unit's frame or the room's ----------------------
    def prune(catalogue: list[str], wins: list[str]) -> tuple[list[str], list[_Test]]:
        """The catalogue effects still significant given the windows ``wins`` (the least significant dropped
        first, one at a time), and the tests that said so."""
        keep, checks = list(catalogue), []
        while keep:
            tts = [run(next(x for x in tests if x.block == b and x.response == "magnitude"),
                       tuple(x for x in keep if x != b) + tuple(wins)) for b in keep]
            for tt in tts:
                tt.variant += " (given the discovered windows)"
            checks += tts
            worst = max(tts, key=lambda tt: tt.p)
            if worst.p_adj < alpha:
                break
            keep.remove(worst.block)
        return keep, checks

    def evidence(model: list[str], wins: list[_Test]) -> float:
        """The magnitude's likelihood ratio of ``model`` over the nominal one, less twice the parameters added
        and, for each window, twice the log of its search's effective number of windows (the best of m
        windows gains about 2 ln m in the statistic by chance alone)."""
        r = reg["magnitude"]
        y, base, alt = r.y[:, None], r.cols([]), r.cols(model)
        G, b, yy, _ = r.forms(y, r.rho(r.ols_resid(alt, y)))
        searched = sum(2.0 * math.log(max(tt.extra["m_eff"], 1.0)) for tt in wins)
        return float(r.lr(G, b, yy, base, alt)[0]) - 2.0 * (r.rank(alt) - r.rank(base)) - searched

    def turned(given: list[str]) -> _Test | None:
        """The significant rotation of the magnetometer's axes (:data:`ROTATION_BLOCKS`) given ``given``, tested on
        the magnitude and the dip at once. Time and the temperature are nearly one input in a warm-up: the likelier
        one for axes that turn (discovery.SLOW_PREFERENCE: time, by creep) unless the other explains
        SLOW_SAME_EVIDENCE more."""
        responses = _responses(reg, given)  # one whitening and projection for both blocks
        tts = [_joint_test(responses, given, b, null_sims, rng, n_tests) for b in turns]
        done.extend(tts)
        sig = sorted((tt for tt in tts if tt.p_adj < alpha), key=lambda tt: -tt.statistic)
        if not sig:
            return None
        likelier = next((tt for tt in sig if ROTATION_BLOCKS[tt.block][0] == SLOW_PREFERENCE["rotation"][0]), None)
        return likelier if likelier is not None and likelier.statistic > sig[0].statistic - SLOW_SAME_EVIDENCE else sig[0]

    def search(catalogue: list[str], fixed_blocks: list[str]) -> tuple[list[str], list[_Test], list[_Test]]:
        """The windows given the catalogue's effects and ``fixed_blocks`` (searched after and before the catalogue,
        the model with more evidence standing), and the catalogue's effects still significant given them."""
        nonlocal reg
        wins = _discover(feats, nom, dec, catalogue + fixed_blocks, null_sims, rng, n_tests, alpha) if searchable else []
        reg = {nm: _Regression(nm, des, dec.t) for nm, des in feats.items()}
        model, checks = catalogue + fixed_blocks, []
        if wins:  # a catalogue effect that only stood in for a window is not named
            kept, checks = prune(catalogue, fixed_blocks + [tt.block for tt in wins])
            model = kept + fixed_blocks + [tt.block for tt in wins]
        if catalogue and searchable:
            # the windows searched before the catalogue's effects: one of those may have taken a window's
            # structure first (a drift for something that came and went); the model with more evidence stands
            alt = _discover(feats, nom, dec, fixed_blocks, null_sims, rng, n_tests, alpha)
            reg = {nm: _Regression(nm, des, dec.t) for nm, des in feats.items()}
            if alt:
                kept, alt_checks = prune(catalogue, fixed_blocks + [tt.block for tt in alt])
                alt_model = kept + fixed_blocks + [tt.block for tt in alt]
                # only where the windows leave a catalogue effect out (it stood in for them): else the catalogue
                # first had its windows searched already
                if len(kept) < len(catalogue) and evidence(alt_model, alt) > evidence(model, wins):
                    model, wins, checks = alt_model, alt, alt_checks
        return model, wins, checks

    def joint_evidence(model: list[str], wins: list[_Test]) -> float:
        """:func:`evidence` on both responses: the magnitude's and the dip's likelihood ratios of ``model`` (the
        dip: its share of the blocks) over the nominal one, less twice the parameters each adds and, per window,
        twice the log of its search's effective number of windows."""
        total = -sum(2.0 * math.log(max(tt.extra["m_eff"], 1.0)) for tt in wins)
        for resp, r in reg.items():
            blocks = model if resp == "magnitude" else [b + "@dip" for b in model if b + "@dip" in r.slices]
            y, base, alt = r.y[:, None], r.cols([]), r.cols(blocks)
            G, b, yy, _ = r.forms(y, r.rho(r.ols_resid(alt, y)))
            total += float(r.lr(G, b, yy, base, alt)[0]) - 2.0 * (r.rank(alt) - r.rank(base))
        return total

    report("discovery", 0.75)
    catalogue = list(selected["magnitude"])
    model, wins, checks = search(catalogue, [])
    # The magnetometer turning against the accelerometer: a lab window turns the dip for a while and can take a
    # slow turn's structure piece by piece, and a turn can take part of an offset present for a while. So the
    # windows are searched given the turn too; the turn stays only if it is still significant given the windows
    # found with it, and that model stands only where it has more evidence, on both responses, than the windows'.
    turn = turned(catalogue) if turns else None
    if turn is not None:
        t_model, t_wins, t_checks = search(catalogue, [turn.block])
        again = turned([b for b in t_model if b != turn.block])
        if again is not None:
            t_model = [again.block if b == turn.block else b for b in t_model]
        if again is not None and joint_evidence(t_model, t_wins) > joint_evidence(model, wins):
            model, wins, checks, turn = t_model, t_wins, t_checks, again
        else:
            notes.append(f"a turn of the magnetometer's axes ({ROTATION_BLOCKS[turn.block][1]}) was significant but "
                         "is not named: the offsets found present for a while explain the data better")
            turn = None
    if turn is not None:
        turn.selected = True
        sel_tests[turn.block] = turn
    chosen = {tt.block for tt in wins}
    for des in feats.values():  # the windows of the model that lost leave the design
        des.blocks = {k: v for k, v in des.blocks.items()
                      if "/segments@" not in k or k.removesuffix("@dip") in chosen}
    reg = {nm: _Regression(nm, des, dec.t) for nm, des in feats.items()}
    windows = [(tt.block, tt.extra["frame"], tt.extra["segments"]) for tt in wins]
    done.extend(checks + wins)
    for tt in wins:
        sel_tests[tt.block] = tt
    for blk in catalogue:
        if blk not in model:
            sel_tests.pop(blk).selected = False
            notes.append(f"{BLOCKS[blk][0]} ({BLOCKS[blk][1]}) was significant but is not named: it is not, given "
                         f"the offset found present for a while")
    selected["magnitude"] = model
    def dip_nuisance() -> tuple[str, ...]:
        """The dip's share of the magnitude's named blocks (their "@dip" columns), fixed in its model."""
        return tuple(b + "@dip" for b in selected["magnitude"] if b + "@dip" in reg["dip"].slices)

    if "dip" in reg:
        fixed["dip"] = dip_nuisance()
        select("dip")

    # confusable pairs: B absorbed by A, and A not significant given B either
    confusable: dict[str, list[str]] = {}
    for b, a in absorbed.items():
        if a not in sel_tests or b in dropped or b in sel_tests:
            continue
        resp = next(x.response for x in tests if x.block == b)
        others = fixed[resp] + tuple(s for s in selected[resp] if s != a) + (b,)
        tt = run(next(x for x in tests if x.block == a and x.response == resp), others)
        done.append(tt)
        if tt.p_adj >= alpha:
            confusable.setdefault(a, []).append(b)
    # The magnitude cannot tell a field that changes in time from a sensitivity that changes the same on
    # every axis (they are one change of the magnitude). Where the two explain the same structure, the
    # likelier cause is named and the other kept as its alike: a sensitivity that follows the logged
    # temperature (every magnetometer's scale factor has a temperature coefficient) over a field that would
    # have to follow the unit's warm-up; a field drift (2 parameters, a catalogue effect) over a sensitivity
    # drifting in time (3).
    for named, alike_of in PREFERRED.items():
        if named in selected["magnitude"] or alike_of not in selected["magnitude"]:
            continue
        if named not in confusable.get(alike_of, []):
            continue
        swap = next(tt for tt in reversed(first) if tt.block == named)
        selected["magnitude"][selected["magnitude"].index(alike_of)] = named
        sel_tests.pop(alike_of).selected = False
        sel_tests[named], swap.selected = swap, True
        confusable[named] = [alike_of] + [b for b in confusable.pop(alike_of) if b != named]
        notes.append(f"{alike_of} and {named} explain the same structure; {named} is named, as the likelier cause "
                     f"(the other is listed as its alike)")
        if "dip" in reg:
            fixed["dip"] = dip_nuisance()

    # ---- unexplained structure given the named effects -----------------------------------------------
    unexpl_done = [run(tt, tuple(fixed[tt.response]) + tuple(selected[tt.response])) for tt in unexplained]
    done += unexpl_done
    report("fit", 0.85)

    # ---- final joint fits ------------------------------------------------------------------------------
    full_feats = _features(nom, full, temp_varies)
    for name, frame, segs in windows:
        _add_window(full_feats, _offset_columns(nom, full, frame), name, _inside(full.t, segs))
    for name in list(full_feats):
        if name not in reg:
            del full_feats[name]
        else:
            full_feats[name].blocks = {k: v for k, v in full_feats[name].blocks.items() if k in feats[name].blocks}
    full_Z = {name: np.hstack([full_feats[name].J] + [full_feats[name].blocks[k] for k in feats[name].blocks])
              / reg[name].scale for name in reg}

    N = len(full)
    col_of = {"magnitude": 0, "dip": 1}
    # held-out: 4 interleaved time folds
    fold_dec = (np.minimum(((dec.t - t0) / duration * N_TIME_BLOCKS).astype(int), N_TIME_BLOCKS - 1)) % N_FOLDS
    fold_full = (np.minimum(((full.t - t0) / duration * N_TIME_BLOCKS).astype(int), N_TIME_BLOCKS - 1)) % N_FOLDS
    nominal_fit: dict[str, np.ndarray] = {}
    for name, r in reg.items():
        jc = r.cols([])
        nominal_fit[name] = full_Z[name][:, jc] @ np.linalg.lstsq(r.Z[:, jc], r.y, rcond=None)[0]

    def heldout(name: str, blocks: list[str]) -> np.ndarray:
        """The held-out prediction of residual_before by the nominal model plus ``blocks``, each fold's
        from the other three (residual_before - prediction is its error)."""
        r, out = reg[name], np.full(N, np.nan)
        cols = r.cols(blocks)
        for k in range(N_FOLDS):
            beta = np.linalg.lstsq(r.Z[fold_dec != k][:, cols], r.y[fold_dec != k], rcond=None)[0]
            rows = fold_full == k
            out[rows] = full_Z[name][rows][:, cols] @ beta - nominal_fit[name][rows]
        return out

    def heldout_ss(model: dict[str, list[str]]) -> float:
        """The held-out sum of squares of ``model`` (each response's blocks), pooled over the responses."""
        total = 0.0
        for name in reg:
            e = full_feats[name].y - nominal_fit[name] - heldout(name, model[name])
            total += float(np.mean(e[np.isfinite(e)] ** 2)) if np.isfinite(e).any() else 0.0
        return total

    def model_of(mag_blocks: list[str], dip_blocks: list[str]) -> dict[str, list[str]]:
        out = {"magnitude": list(mag_blocks)}
        if "dip" in reg:  # the dip's share of the magnitude's blocks, and its own
            out["dip"] = [b + "@dip" for b in mag_blocks if b + "@dip" in reg["dip"].slices] + list(dip_blocks)
        return out

    # The final model is never worse held-out than the nominal one (as the table model's): a block whose
    # removal improves the held-out fit goes, the worst first, until the model does no harm.
    ss_before = heldout_ss(model_of([], []))
    while True:
        dip_own = selected.get("dip", [])
        if heldout_ss(model_of(selected["magnitude"], dip_own)) <= ss_before:
            break
        trial = {(resp, b): heldout_ss(model_of([x for x in selected["magnitude"] if x != b] if resp == "magnitude"
                                                else selected["magnitude"],
                                                [x for x in dip_own if x != b] if resp == "dip" else dip_own))
                 for resp in selected for b in selected[resp]}
        if not trial:
            break
        resp, worst = min(trial, key=trial.get)
        selected[resp].remove(worst)
        gone = sel_tests.pop(worst)
        gone.selected = False
        confusable.pop(worst, None)
        if resp == "magnitude" and "dip" in reg:
            fixed["dip"] = dip_nuisance()
        notes.append(f"{gone.effect} ({gone.variant}) left out: with it the model predicted held-out data worse "
                     "than without")
    finals = {name: r.gls(list(fixed[name]) + selected[name]) for name, r in reg.items()}

    resid_before = np.full((N, 3), np.nan)
    resid_after = np.full((N, 3), np.nan)
    pred_before = np.full((N, 3), np.nan)
    pred_after = np.full((N, 3), np.nan)
    for name, r in reg.items():
        j = col_of[name]
        y_full = full_feats[name].y
        fin = finals[name]
        # in-sample residuals: least-squares fits of the nominal model (its linearised parameters J, which
        # for the dip include the ellipsoid's) and of the nominal model plus the selected effects (so
        # "after" never exceeds "before"); the reported parameters and sigma come from the GLS fit
        resid_before[:, j] = y_full - nominal_fit[name]
        beta_ls = np.linalg.lstsq(r.Z[:, fin["cols"]], r.y, rcond=None)[0]
        resid_after[:, j] = y_full - full_Z[name][:, fin["cols"]] @ beta_ls
        pred_before[:, j] = heldout(name, [])
        pred_after[:, j] = heldout(name, list(fixed[name]) + selected[name])
    report("heldout", 0.95)

    # ---- results --------------------------------------------------------------------------------------------
    # a mains line fitted is not noise: the floor is the residual's without it (its first differences carry the
    # line whole: 4.7 LSB were said against 3 of noise, and the residual after came out "below the floor")
    line = "mains_interference" in selected.get("magnitude", [])
    noise = _noise_floor(full, (resid_after if line else resid_before)[:, 0], notes)
    require_noise(noise["sigma"])
    kb = shape.kbar

    def rms(a: np.ndarray) -> float | None:
        a = a[np.isfinite(a)]
        return float(np.sqrt(np.mean(a ** 2))) if a.size else None

    rms_before = [rms(resid_before[:, j]) for j in range(3)]
    rms_after = [rms(resid_after[:, j]) for j in range(3)]
    ho_before = [rms(resid_before[:, j] - pred_before[:, j]) for j in range(3)]
    ho_after = [rms(resid_before[:, j] - pred_after[:, j]) for j in range(3)]
    ss_b = sum(x ** 2 for x in ho_before if x is not None)
    ss_a = sum(x ** 2 for x in ho_after if x is not None)
    improvement = 100.0 * (1.0 - math.sqrt(ss_a / ss_b)) if ss_b > 0 else 0.0

    dip_deg = float(np.degrees(nom.dip.I)) if nom.dip is not None else None
    cos_dip = math.cos(nom.dip.I) if nom.dip is not None else None
    findings = _findings(nom, dec, reg, finals, sel_tests, selected, confusable, unexpl_done, alpha, cos_dip,
                         share, ut_per_count(rec.meta))
    findings += _parameter_shifts(nom)
    findings.sort(key=lambda f: (-(f["heading_impact_deg"] if f["heading_impact_deg"] is not None else -1.0),
                                 -(f["statistic"] or 0.0)))
    # as the table model's: a departure is what the analysis reports (a named, discovered or unexplained finding;
    # a parameter shift flags the nominal fit itself). A test significant on the way whose name did not hold (a
    # stand-in not significant given smooth structure, which the generic tests then did not find) reports none.
    reported = any(f["effect"] != "parameter_shift" for f in findings)
    verdict = "discrepancy" if reported else "consistent"
    if not reported and any(tt.p_adj < alpha for tt in done):
        notes.append("some tests were significant on the way, but nothing they named held (see the notes above): "
                     "no departure is reported")

    tests_json = [{"effect": tt.effect, "variant": tt.variant + (f" | given {', '.join(tt.given)}" if tt.given else ""),
                   "response": tt.response, "statistic": tt.statistic, "raw_statistic": tt.raw, "df": tt.df,
                   "p_value": tt.p, "p_adjusted": tt.p_adj, "selected": tt.selected,
                   "bartlett": tt.extra.get("bartlett", 1.0)} for tt in done]
    mag_final = finals["magnitude"]
    locate = _locate(full, shape, resid_before, scan_info, f_grid if mains_ok else None, q if mains_ok else None,
                     unexpl_done, lb_lags, mag_final)
    notes.append(f"Bonferroni over {n_tests} tests ({len(tests)} named effects, {len(unexplained)} unexplained-structure "
                 f"tests ({' and '.join(reg)})"
                 + (f", the window search of an offset in each of {len(WINDOW_FRAMES)} frames" if searchable else "")
                 + (f", {len(turns)} turns of the magnetometer's axes on the magnitude and dip at once" if turns else "")
                 + "); conditional re-tests during selection use the same factor")
    if sims_used:  # (with none, the note above says there is no correction)
        notes.append(f"Bartlett factors from {sims_used} simulated AR(1) nulls per response (null model: the nominal "
                     "fit); factors below 1 are taken as 1 (conservative)")
    notes.append("heading impact without table angles: the fitted distortion's component across the field, divided "
                 "by cos(dip) when an accelerometer gives the dip" + (
                     f" ({dip_deg:.1f} deg here)" if dip_deg is not None else
                     "; here the dip is unknown, so the impact is given for a horizontal field (a lower bound)"
                     if not shape.planar else "; in the plane of a single-axis turn the field is the horizontal one"))

    result = {
        "verdict": verdict,
        "model": MODEL,
        "samples": int(N),
        "duration_s": float(duration),
        "alpha": float(alpha),
        "noise_floor_lsb": [float(x) for x in noise["sigma"]],
        "noise_ar1": [float(x) for x in noise["ar1"]],
        "residual_rms_before_lsb": rms_before,
        "residual_rms_after_lsb": rms_after,
        "residual_columns": ["magnitude", "dip" if "dip" in reg else None, None],
        "heldout": {"scheme": f"{N_FOLDS} interleaved time folds ({N_TIME_BLOCKS} equal time blocks, block i in fold "
                              f"i mod {N_FOLDS}); nominal model (linearised refit) and selected effects fitted on 3 "
                              "folds, the 4th predicted; improvement pooled over the residual columns",
                    "rms_before_lsb": ho_before, "rms_after_lsb": ho_after, "improvement_pct": float(improvement)},
        "heading_error_deg": {"before": None, "after": None},
        "findings": findings,
        "tests": tests_json,
        "untestable": untestable,
        "locate": locate,
        "nominal": _nominal_json(nom),
        "noise": {"source": noise["source"], "static_samples": noise["static_samples"],
                  "residual_sigma_lsb": mag_final["sigma"], "residual_ar1": mag_final["rho"],
                  "highpass_sigma_lsb": noise["sigma_hp_lsb"], "decimation": factor},
        "notes": notes,
    }
    series = {
        "t": full.t, "step": full.step,
        "psi_t": np.asarray(rec.psi_t, float), "theta_t": np.asarray(rec.theta_t, float),
        "phi_t": np.asarray(rec.phi_t, float),
        "residual_before": resid_before, "residual_after": resid_after,
        "heldout_pred_before": pred_before, "heldout_pred_after": pred_after,
        "fold": fold_full.astype(int),
    }
    report("done", 1.0)
    return Analysis(result=json_safe(result), series=series)


# --------------------------------------------------------------------------------------------------
# Findings
# --------------------------------------------------------------------------------------------------

def _perp_impact(shape: _Shape, mag: np.ndarray, delta_raw: np.ndarray, cos_dip: float | None) -> float:
    """Largest heading change (deg) of a raw-count distortion delta_raw (n, 3): its component across the
    calibrated field, in field units, over cos(dip) (planar: the in-plane field is the horizontal one)."""
    h = shape.direction(mag)
    dh = (delta_raw @ shape.P) @ shape.E  # change of the calibrated field (E symmetric)
    perp = dh - np.sum(dh * h, axis=1)[:, None] * h
    ang = np.linalg.norm(perp, axis=1)
    if not shape.planar and cos_dip is not None:
        ang = ang / max(abs(cos_dip), 0.05)
    return float(np.degrees(np.max(ang))) if ang.size else 0.0


def _fmt3(values: np.ndarray, spec: str) -> str:
    """x, y, z values for an explanation ("n/a" for an axis without a parameter)."""
    return ", ".join("n/a" if not np.isfinite(x) else format(float(x), spec) for x in values)


def _full3(values: np.ndarray, res: np.ndarray) -> np.ndarray:
    """Per-axis values of the resolved axes spread to x, y, z (NaN for an axis without a parameter)."""
    out = np.full(3, np.nan)
    out[res] = values
    return out


def _positions(cols: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Where each of ``wanted`` (column numbers) sits in ``cols`` (a fit's column list, not sorted)."""
    where = {int(c): i for i, c in enumerate(cols)}
    return np.array([where[int(c)] for c in wanted], dtype=int)


def _coef(fin: dict[str, Any], reg: _Regression, block: str, c: float) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of ``block`` in a final fit, and their standard errors inflated by the Bartlett factor."""
    idx = _positions(fin["cols"], reg.slices[block])
    coef = fin["coef"][idx]
    se = np.sqrt(np.maximum(np.diag(fin["cov"])[idx], 0.0) * c)
    return coef, se


def _findings(nom: _Nominal, dec: _Data, reg: dict[str, _Regression], finals: dict[str, Any],
              sel_tests: dict[str, _Test], selected: dict[str, list[str]], confusable: dict[str, list[str]],
              unexpl: list[_Test], alpha: float, cos_dip: float | None,
              share: dict[str, float], uc: float | None = None) -> list[dict[str, Any]]:
    sh, kb = nom.shape, nom.kbar
    res = sh.resolved
    out: list[dict[str, Any]] = []
    t = dec.t
    for resp, blocks in selected.items():
        r, fin = reg[resp], finals[resp]
        for blk in blocks:
            tt = sel_tests[blk]
            c = tt.extra.get("bartlett", 1.0)
            coef, se = _coef(fin, r, blk, c)
            if blk in ROTATION_BLOCKS:
                out.append(_rotation_finding(blk, tt, nom, dec, cos_dip))
                continue
            if blk in GAIN_BLOCKS:
                f = _gain_finding(blk, tt, coef, se, nom, dec, cos_dip)
                f["confusable_with"] = [_alike_name(b) for b in confusable.get(blk, [])]
                if f["confusable_with"]:
                    f["separating_experiment"] += ("; a field that changes in the room (not with the unit's "
                                                   "temperature) shows the same on a second magnetometer nearby")
                out.append(f)
                continue
            if blk.startswith("discovered:"):
                dip = None
                if tt.extra["frame"] == "lab" and "dip" in finals and blk + "@dip" in reg["dip"].slices:
                    dc, ds = _coef(finals["dip"], reg["dip"], blk + "@dip", c)
                    dip = (float(dc[0]), float(ds[0]))
                out.append(_window_finding(tt, coef, se, nom, dec, uc, cos_dip, dip))
                continue
            eff = tt.effect
            where: dict[str, Any] = {"response": resp, "frame": "sensor", "time_span_s": [float(t[0]), float(t[-1])]}
            impact: float | None = None
            if blk == "nonlinearity":
                c3 = np.full(3, np.nan)
                s3 = np.full(3, np.nan)
                c3[res], s3[res] = coef, se
                params, sig = {"c3": c3.tolist()}, {"c3": s3.tolist()}
                u = sh.axis_outputs(dec.mag)
                impact = _perp_impact(sh, dec.mag, np.nan_to_num(c3) * np.nan_to_num(u) ** 3, cos_dip)
                where["axes"] = ["xyz"[j] for j in range(3) if res[j]]
                expl = (f"The sensor's output is not linear in the field: a cubic term of "
                        f"{', '.join(f'{x:.1f}' for x in c3 if np.isfinite(x))} LSB at full field on the resolved axes "
                        f"(of about {kb:.0f} LSB), which the {'ellipse' if sh.planar else 'ellipsoid'} (linear) "
                        "cannot absorb.")
            elif blk in ("temperature_drift", "temperature_drift/time"):
                coef, se = _full3(coef, res), _full3(se, res)
                if blk == "temperature_drift":
                    params, sig = {"bias_per_c": coef.tolist()}, {"bias_per_c": se.tolist()}
                    dT = dec.temp - nom.temp_ref
                    delta = np.outer(dT, np.nan_to_num(coef))
                    expl = (f"The bias follows the logged temperature: {_fmt3(coef, '.2f')} LSB per deg C on x, y, z.")
                else:
                    params = {"bias_rate_lsb_per_s": coef.tolist()}
                    sig = {"bias_rate_lsb_per_s": se.tolist()}
                    delta = np.outer(t - nom.t_mid, np.nan_to_num(coef))
                    span = float(t[-1] - t[0])
                    expl = (f"The sensor's bias drifts with time, fixed in the sensor frame (as after power-on, a "
                            f"warm-up): {_fmt3(coef * span, '.1f')} LSB over the {span:.0f} s run on x, y, z. No "
                            "temperature was logged, so this is read as temperature drift.")
                impact = _perp_impact(sh, dec.mag, delta, cos_dip)
            elif blk == "field_drift":
                params = {"rate_along_field_per_s": float(coef[0]), "accel_along_field_per_s2": float(coef[1])}
                sig = {"rate_along_field_per_s": float(se[0]), "accel_along_field_per_s2": float(se[1])}
                where["frame"] = "lab (attitude-independent magnitude trend)"
                span = float(t[-1] - t[0])
                change = coef[0] * span  # field units
                expl = (f"The field's magnitude changes during the run, whatever the attitude: "
                        f"{100 * change:.2f} % of the field over {span:.0f} s (linear part), plus a quadratic part. "
                        "A lab field that changes (a vehicle, a lift, an instrument) does this; the part of the change "
                        "across the field, which turns the heading, is invisible without attitudes.")
            elif blk == "field_drift/dip":
                params = {"dip_rate_deg_per_s": float(np.degrees(coef[0])),
                          "dip_accel_deg_per_s2": float(np.degrees(coef[1]))}
                sig = {"dip_rate_deg_per_s": float(np.degrees(se[0])), "dip_accel_deg_per_s2": float(np.degrees(se[1]))}
                where["frame"] = "lab (the field's angle to gravity)"
                span = float(t[-1] - t[0])
                impact = float(abs(np.degrees(coef[0])) * span / 2 + abs(np.degrees(coef[1])) * span ** 2 / 4)
                expl = (f"The angle between the field and gravity drifts during the run "
                        f"({np.degrees(coef[0]) * span:.2f} deg over {span:.0f} s): the lab field's direction changes.")
            elif blk == "mains_interference":
                nr = int(res.sum())
                a, b = _full3(coef[:nr], res), _full3(coef[nr:], res)
                sea, seb = _full3(se[:nr], res), _full3(se[nr:], res)
                amp = np.hypot(a, b)
                ph = np.arctan2(b, a)  # a cos + b sin = amp cos(wt - ph)
                jd = int(np.nanargmax(amp))
                signed = amp * np.sign(np.cos(ph - ph[jd]))
                sa = np.sqrt((sea * a) ** 2 + (seb * b) ** 2) / np.maximum(amp, 1e-300)
                params = {"amplitude_lsb": signed.tolist(), "alias_hz": nom.mains_hz, "phase_rad": float(-ph[jd])}
                sig = {"amplitude_lsb": sa.tolist(), "alias_hz": 1.0 / (2 * np.pi * (t[-1] - t[0])) * math.sqrt(12.0),
                       "phase_rad": float(sa[jd] / max(amp[jd], 1e-300))}
                w = 2 * np.pi * nom.mains_hz * dec.t
                delta = np.outer(np.cos(w), np.nan_to_num(a)) + np.outer(np.sin(w), np.nan_to_num(b))
                impact = _perp_impact(sh, dec.mag, delta, cos_dip)
                where["frequency_hz"] = nom.mains_hz
                expl = (f"A narrow line at {nom.mains_hz:.4g} Hz with amplitudes {_fmt3(amp, '.1f')} LSB "
                        f"on x, y, z, fixed in the sensor frame: pickup at the mains frequency (or another periodic "
                        f"source) folded by the sampling.")
            elif blk == "time_lag":
                params, sig = {"lag_s": float(coef[0])}, {"lag_s": float(se[0])}
                f = nom.acc.directions(dec.acc)
                yaw_rate = np.abs(np.sum(dec.gyro * -f, axis=1))
                impact = float(abs(coef[0]) * np.degrees(np.percentile(yaw_rate, 99)))
                expl = (f"The magnetometer sample lags the accelerometer by {1000 * coef[0]:.1f} ms: while turning, "
                        "the field it reports belongs to an earlier attitude (a sensor filter or a time-stamp skew).")
            else:  # pragma: no cover
                continue
            conf = [_alike_name(b) for b in confusable.get(blk, [])]
            sep = [separating_experiment(eff, b) for b in conf]
            plausible, why = _plausible(blk, params, sh, t)
            if not plausible:
                expl += (f" This is beyond a plausible size ({why}): more likely the effect stands in for something "
                         "the model lacks.")
            if blk in share and share[blk] < GENERIC_SHARE:
                against = "the field direction" if GENERIC_OF[blk].endswith("direction") else "time"
                conf.append(UNEXPLAINED)
                sep.append(f"the structure against {against} is broader than this shape: a recording that separates "
                           f"the candidate causes (table angles, temperature logged) would say which")
                expl += (f" It carries only {100 * share[blk]:.0f} % of the structure against {against} (likelihood "
                         f"ratio), so read it as one shape of unexplained structure against {against}.")
            where["share_of_generic_structure"] = share.get(blk)
            finding = {
                "effect": eff, "variant": BLOCKS[blk][1], "statistic": tt.statistic, "df": tt.df,
                "p_value": tt.p, "p_adjusted": tt.p_adj, "parameters": params, "sigma": sig,
                "heading_impact_deg": impact, "where": where, "explanation": expl,
                "confusable_with": conf, "plausible": plausible,
                "separating_experiment": "; ".join(sep) if sep else "",
            }
            if blk.endswith("/time"):  # fitted against time (no temperature logged to follow): the model says so
                finding["model"] = {**finding_model(finding), "against": "time"}
            out.append(finding)
    for tt in unexpl:
        if tt.p_adj >= alpha:
            continue
        if tt.kind == "whiteness":
            params = {"against": "lag (whiteness)", "ljung_box_lags": tt.extra.get("lags"),
                      "residual_ar1": tt.extra.get("residual_ar1")}
            expl = ("unexplained structure against lag: after the named effects the residual is not AR(1) noise "
                    "(Ljung-Box); the noise is coloured beyond AR(1) or something the catalogue lacks varies "
                    "with time or attitude")
        else:
            r = reg[tt.response]
            cols = r.cols(list(tt.given) + [tt.block])
            g = r.gls(list(tt.given) + [tt.block])
            part = r.Z[:, r.slices[tt.block]] @ g["beta_scaled"][_positions(cols, r.slices[tt.block])]
            against = "field direction in the sensor frame" if tt.block.endswith("direction") else "time"
            params = {"against": against, "rms_lsb": float(np.sqrt(np.mean(part ** 2))),
                      "peak_lsb": float(np.max(np.abs(part)))}
            expl = (f"unexplained structure against {against}: {params['rms_lsb']:.1f} LSB rms "
                    f"({tt.variant}) that no catalogue entry testable here explains")
        if tt.response == "dip":
            expl = expl.replace("unexplained structure", "unexplained structure in the dip (the angle between the "
                                "field and the accelerometer's gravity)", 1) + (
                "; the magnitude does not show it: a lag between the magnetometer's and the accelerometer's samples "
                "(log the gyro's rates to test one), accelerations beyond gravity (the unit moved while it was "
                "read), or the accelerometer's own errors")
        out.append({"effect": UNEXPLAINED, "variant": tt.variant, "statistic": tt.statistic, "df": tt.df,
                    "p_value": tt.p, "p_adjusted": tt.p_adj, "parameters": params, "sigma": {},
                    "heading_impact_deg": None, "where": {"response": tt.response}, "explanation": expl,
                    "confusable_with": [], "separating_experiment": ""})
    return out


def _alike_name(blk: str) -> str:
    """How a finding names a look-alike block: its effect id, or the block itself for a dictionary block."""
    return blk if BLOCKS[blk][0] == "discovered" else BLOCKS[blk][0]


def _plausible(blk: str, params: dict[str, Any], sh: _Shape, t: np.ndarray) -> tuple[bool, str]:
    """Whether a fitted effect's size is physically plausible (catalogue limits, relative where the
    catalogue's absolute limit assumes another sensitivity)."""
    if blk == "nonlinearity":
        rel = np.nanmax(np.abs(np.asarray(params["c3"], float)) / sh.k)
        return bool(rel <= NONLINEAR_LIMIT), f"{100 * rel:.1f} % of full scale, limit {100 * NONLINEAR_LIMIT:.0f} %"
    if blk == "temperature_drift":
        v = float(np.nanmax(np.abs(np.asarray(params["bias_per_c"], float))))
        lim = CATALOGUE["temperature_drift"].plausible["bias_per_c"]
        return v <= lim, f"{v:.1f} LSB per deg C, limit {lim:g}"
    if blk == "temperature_drift/time":
        v = float(np.nanmax(np.abs(np.asarray(params["bias_rate_lsb_per_s"], float)) / sh.k) * (t[-1] - t[0]))
        return v <= WARMUP_LIMIT, f"{100 * v:.1f} % of full scale over the run, limit {100 * WARMUP_LIMIT:.0f} %"
    if blk == "field_drift":
        v = abs(params["rate_along_field_per_s"])
        lim = CATALOGUE["field_drift"].plausible["rate_per_s"]
        return v <= lim, f"{v:.2g} of the field per s, limit {lim:g}"
    if blk == "field_drift/dip":  # the field turning: rad/s against the catalogue's field units per s
        v = abs(math.radians(params["dip_rate_deg_per_s"]))
        lim = CATALOGUE["field_drift"].plausible["rate_per_s"]
        return v <= lim, f"{v:.2g} rad/s, limit {lim:g}"
    if blk == "mains_interference":
        v = float(np.nanmax(np.abs(np.asarray(params["amplitude_lsb"], float))))
        lim = CATALOGUE["mains_interference"].plausible["amplitude_lsb"]
        return v <= lim, f"{v:.1f} LSB, limit {lim:g}"
    if blk == "time_lag":
        v = abs(params["lag_s"])
        lim = CATALOGUE["time_lag"].plausible["lag_s"]
        return v <= lim, f"{v:.3f} s, limit {lim:g}"
    return True, ""


def _axis_angles(M: np.ndarray) -> np.ndarray:
    """Pairwise angles (deg) between the rows of M: xy, xz, yz."""
    U = M / np.linalg.norm(M, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip([U[0] @ U[1], U[0] @ U[2], U[1] @ U[2]], -1, 1)))


def _parameter_shifts(nom: _Nominal) -> list[dict[str, Any]]:
    """Nominal parameters outside plausibility limits: effects the nominal model absorbs completely."""
    sh = nom.shape
    out = []

    def shift(name: str, value: Any, limit: Any, expl: str, where: dict[str, Any] | None = None) -> None:
        out.append({"effect": PARAMETER_SHIFT, "variant": name, "statistic": None, "df": 0, "p_value": None,
                    "p_adjusted": None, "parameters": {"parameter": name, "value": value, "limit": limit},
                    "sigma": {}, "heading_impact_deg": None, "where": where or {"frame": "sensor"},
                    "explanation": expl, "confusable_with": [], "separating_experiment": ""})

    radii = np.sort(1.0 / np.linalg.eigvalsh(sh.E))  # semi-axes, LSB per field unit
    spread = float(radii[-1] / radii[0] - 1.0)
    if spread > ANISOTROPY_LIMIT:
        shift("sensitivity_ratio", float(radii[-1] / radii[0]), 1.0 + ANISOTROPY_LIMIT,
              f"The field {'ellipse' if sh.planar else 'ellipsoid'}'s semi-axes ({_fmt3(radii, '.0f')} "
              f"LSB per field; per sensor axis {', '.join(f'{x:.0f}' for x in sh.k[sh.resolved])}) differ by "
              f"{100 * spread:.0f} %. The nominal model absorbs this completely, so it leaves no residual, but "
              "matched sensor axes differ by a few % at most: soft iron next to the sensor, or axes with different "
              "gain settings, would do this.",
              {"frame": "sensor", "semi_axes_lsb": radii.tolist(), "k_lsb": sh.k.tolist()})
    if not sh.planar:
        ang = _axis_angles(sh.M3)
        worst = float(np.max(np.abs(ang - 90.0)))
        if worst > NONORTHOGONALITY_LIMIT_DEG:
            shift("non_orthogonality_deg", worst, NONORTHOGONALITY_LIMIT_DEG,
                  f"The fitted sensor axes are {worst:.1f} deg from perpendicular (xy, xz, yz: "
                  f"{', '.join(f'{a:.1f}' for a in ang)} deg); a sensor die is orthogonal within about 1 deg, so this "
                  "is soft iron near the sensor (which the ellipsoid absorbs).")
    # the bias in field units: the calibrated length of the centre (in planar mode, its in-plane part)
    bias = float(np.linalg.norm(sh.centre @ sh.P))
    bias_rel = float(np.linalg.norm((sh.centre @ sh.P) @ sh.E))
    if bias_rel > HARD_IRON_LIMIT:
        shift("hard_iron_over_field", bias_rel, HARD_IRON_LIMIT,
              f"The bias ({bias:.0f} LSB) is {bias_rel:.1f} times the field it measures: magnetised parts near the "
              "sensor (hard iron) dominate. The model absorbs a constant bias, but such parts may also be "
              "magnetised further by handling or move with the cable.",
              {"frame": "sensor", "bias_lsb": sh.centre.tolist()})
    if nom.dip is not None:
        angle = float(np.degrees(np.arccos(np.clip((np.trace(nom.dip.R) - 1) / 2, -1, 1))))
        if angle > MISALIGNMENT_LIMIT_DEG:
            shift("mag_acc_misalignment_deg", angle, MISALIGNMENT_LIMIT_DEG,
                  f"The magnetometer's and the accelerometer's axes differ by a {angle:.1f} deg rotation; the "
                  "dip model absorbs it, but parts of one board should agree within a few deg.")
    return out


# --------------------------------------------------------------------------------------------------
# Locate, nominal parameters, JSON
# --------------------------------------------------------------------------------------------------

def _locate(full: _Data, shape: _Shape, before: np.ndarray, scan: dict[str, Any], f_grid: np.ndarray | None,
            q: np.ndarray | None, unexpl: list[_Test], lags: int, mag_final: dict[str, Any]) -> dict[str, Any]:
    """Where the mismatch lives: per step, per dominant axis, in time, in the spectrum, against witnesses."""
    def rms(a: np.ndarray) -> float | None:
        a = a[np.isfinite(a)]
        return float(np.sqrt(np.mean(a ** 2))) if a.size else None

    by_step = []
    for s in dict.fromkeys(full.step.tolist()):
        m = full.step == s
        by_step.append({"step": str(s), "samples": int(m.sum()), "rms_lsb": [rms(before[m, j]) for j in range(3)]})
    # which part of the sphere: residual rms where each sensor axis is the one most aligned with the field
    u = shape.axis_outputs(full.mag)
    dom = np.nanargmax(np.abs(np.nan_to_num(u, nan=0.0)), axis=1)
    by_axis = {"note": "attitude-free: the residual is the field magnitude (and dip), not per axis; rms_lsb is "
                       "the magnitude residual where each sensor axis is the one most aligned with the field",
               "rms_lsb": [rms(before[dom == j, 0]) for j in range(3)],
               "samples": [int(np.sum(dom == j)) for j in range(3)]}
    T = full.t[-1] - full.t[0]
    edges = full.t[0] + T * np.arange(11) / 10
    bins = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (full.t >= a) & (full.t <= b)
        bins.append({"t0": float(a), "t1": float(b), "mean_lsb": float(np.mean(before[m, 0])) if m.any() else None,
                     "rms_lsb": rms(before[m, 0])})
    harmonics: dict[str, Any] = {"spectrum": scan}
    if f_grid is not None and q is not None and q.size:
        top = np.argsort(q)[::-1][:5]
        harmonics["spectrum"]["top_lines"] = [{"hz": float(f_grid[i]), "projection_lsb2": float(q[i])} for i in top]
    wit: dict[str, Any] = {}
    r0 = before[:, 0]
    for name, x in (("time", full.t), ("temp_c", full.temp),
                    ("acc_magnitude", None if full.acc is None else np.linalg.norm(full.acc, axis=1)),
                    ("rate_of_turn", None if full.gyro is None else np.linalg.norm(full.gyro, axis=1))):
        if x is None or np.std(x) == 0:
            continue
        wit[name] = {"correlation": float(np.corrcoef(x, r0)[0, 1])}
    white = next((tt for tt in unexpl if tt.kind == "whiteness" and tt.response == "magnitude"), None)
    return {
        "by_axis": by_axis,
        "by_step": by_step,
        "harmonics": harmonics,
        "time": {"bins": bins},
        "frame": {"note": "attitude-free: a trend in the magnitude whatever the attitude is lab-fixed (field_drift); "
                          "one that depends on the attitude through a fixed sensor-frame vector is a sensor bias drift "
                          "(temperature_drift)",
                  "tests": {tt.block: tt.statistic for tt in unexpl if tt.block and tt.response == "magnitude"}},
        "whiteness": {"ljung_box": white.statistic if white else None, "lags": lags,
                      "p_value": white.p if white else None, "residual_ar1": mag_final["rho"],
                      "residual_sigma_lsb": mag_final["sigma"]},
        "witness": wit,
    }


def _nominal_json(nom: _Nominal) -> dict[str, Any]:
    sh = nom.shape
    out = {"kind": "ellipse in the readings' plane" if sh.planar else "ellipsoid",
           "bias_lsb": sh.centre.tolist(), "k_lsb": sh.k.tolist(), "kbar_lsb": sh.kbar,
           "matrix_lsb_per_field": sh.M3.tolist(), "resolved_axes": ["xyz"[j] for j in range(3) if sh.resolved[j]]}
    if nom.dip is not None:
        out["dip_deg"] = float(np.degrees(nom.dip.I))
    if nom.acc is not None:
        out["accelerometer"] = "own ellipsoid" if nom.acc.calibrated else "normalised only"
    return out
