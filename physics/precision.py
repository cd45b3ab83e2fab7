"""How well a calibration will point, predicted from the data it came from, and which pose buys the most.

The joint fit's parameters have the covariance ``(J^T J)^-1`` of its whitened Jacobian (errorsep:
``raw = M R^T v + b`` for the magnetometer and the accelerometer alike; parameters [M, b, t]). A heading
error is a function of the magnetometer's M, b and the accelerometer's (the compass levels itself with
it); linearised about the fit, ``e(attitude) = G_mag dp_mag + G_acc dp_acc``, with the gradients G taken
numerically on the fitted model's own noise-free readings (the fitted unit in the fitted world). The
prediction of a target (the level turn, or every heading at pitch and roll up to 60 deg) is a bound on
the largest |e| over its attitudes, over draws of dp; the bounds of the targets hold together in 95 % of
the draws (simultaneous bounds: each is a quantile of its own error at one common level, about 97 % for
two). A unit meets the targets "at 95 % confidence" when every bound is within its target: it then
meets both with 95 % probability, not each with 95 % (both with about 90 %).

Each pose of a plan adds ``n J_pose^T J_pose`` to the information (n samples at one attitude); the
information after a candidate pose is known before the pose is made, so a procedure can choose the
pose that lowers the worst predicted error the most per second of table time. The same information
prices a design before any pose is made: :func:`best_design` spreads a number of samples over candidate
attitudes to minimise the predicted error, with no time for moves (what no plan of that many samples
could beat by much), and :meth:`UnitPrecision.meet_probability` says how likely the unit then meets the
targets. Pure functions, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
from scipy.optimize import minimize

from physics import errorsep as es
from physics.calibration import Calibration, attitude_grid, level_turn, truth_errors
from physics.recording import Recording
from physics.sensor import LinearSensor, Unit
from physics.simulate import World
from physics.table import TableGeometry, platform_attitude

#: The targets of the production line (PHYSICS.md): max level and max tilted (+-60 deg) heading error, deg.
TARGET_LEVEL_DEG, TARGET_TILTED_DEG = 0.02, 0.05
#: Confidence at which a unit is said to meet the targets (all of them together).
CONFIDENCE = 0.95
#: Draws of the parameters for the bounds (fixed, so that predictions compare without noise; enough that the
#: common level of two targets' bounds, about 0.97, rests on a few dozen draws beyond it).
DRAWS = 1000


@dataclass
class SensorInfo:
    """One vector sensor's fit as the precision model needs it: M, b, the unit field (or specific force)
    in the table's base frame v with its tangent basis, each axis's noise (LSB), and the information
    matrix over [M (row-major), b, t] gathered so far."""

    M: np.ndarray
    b: np.ndarray
    v: np.ndarray
    basis: np.ndarray
    noise: np.ndarray
    info: np.ndarray

    def per_sample(self, angles: np.ndarray) -> np.ndarray:
        """Information (14, 14) one sample adds at each of ``angles`` (K, 3): (K, 14, 14)."""
        R = platform_attitude(angles[:, 0], angles[:, 1], angles[:, 2])
        out = np.empty((len(angles), 14, 14))
        for k in range(len(angles)):
            J = es._jacobian(R[k:k + 1], self.M, self.v, self.basis, 1.0 / self.noise)
            out[k] = J.T @ J
        return out

    def covariance(self, extra: np.ndarray | None = None) -> np.ndarray:
        """Covariance (12, 12) of M and b, with ``extra`` information added."""
        F = self.info if extra is None else self.info + extra
        try:  # the plan makes F regular; the pseudo-inverse (an SVD, 10x slower) only if it is not
            C = np.linalg.inv(F)
            if np.all(np.isfinite(C)):
                return C[..., :12, :12]
        except np.linalg.LinAlgError:
            pass
        return np.linalg.pinv(F)[..., :12, :12]


def sensor_info(R: np.ndarray, raw: np.ndarray, sensor: LinearSensor) -> SensorInfo:
    """The information of a fitted sensor on readings ``raw`` (N, 3) made at nominal attitudes R (N, 3, 3):
    v is the direction that its corrected readings give in the base frame, the noise their residual."""
    M, b = sensor.M, sensor.bias
    h = np.linalg.solve(M, (raw - b).T).T  # = R^T v per sample
    v = np.einsum("nij,nj->i", R, h)
    v /= np.linalg.norm(v)
    r = raw - np.einsum("ij,nkj,k->ni", M, R, v) - b
    noise = np.maximum(np.sqrt(np.mean(r * r, axis=0)), 1e-9 * np.abs(raw).max())
    basis = es._tangent_basis(v)
    J = es._jacobian(R, M, v, basis, 1.0 / noise)
    return SensorInfo(M, b, v, basis, noise, J.T @ J)


@dataclass
class UnitPrecision:
    """A unit's calibration, its information so far and its heading gradients at the targets' attitudes."""

    mag: SensorInfo
    acc: SensorInfo | None
    gradients: dict[str, tuple[np.ndarray, np.ndarray | None]]  # target -> (G_mag (K, 12), G_acc (K, 12))

    def sigma_max(self, extra_mag: np.ndarray | None = None, extra_acc: np.ndarray | None = None) -> dict[str, Any]:
        """Largest 1-sigma heading error (deg) over each target's attitudes: a float, or an array when the
        extra information is a stack (B, 14, 14) of alternatives (the extension scores its candidates so)."""
        Cm = self.mag.covariance(extra_mag)
        Ca = self.acc.covariance(extra_acc) if self.acc is not None else None
        out: dict[str, Any] = {}
        for name, (Gm, Ga) in self.gradients.items():
            var = np.sum((Gm @ Cm) * Gm, axis=-1)  # G C G^T's diagonal, per alternative (matmul: BLAS)
            if Ga is not None and Ca is not None:
                var = var + np.sum((Ga @ Ca) * Ga, axis=-1)
            worst = np.sqrt(np.maximum(var.max(axis=-1), 0.0))
            out[name] = float(worst) if worst.ndim == 0 else worst
        return out

    def quantile(self, confidence: float = CONFIDENCE, draws: int = DRAWS, extra_mag: np.ndarray | None = None,
                 extra_acc: np.ndarray | None = None) -> dict[str, float]:
        """Bounds (deg) on the largest |heading error| over each target's attitudes that hold together with
        probability ``confidence`` (with ``extra`` information, as :meth:`sigma_max`: what poses not yet made
        would add). Each bound is its error's quantile at one common level, chosen so that in ``confidence``
        of the draws no target's error passes its bound; with one target, the plain quantile."""
        E = self._largest_errors(draws, extra_mag, extra_acc)
        # a draw stays within bounds at level u when each target's error ranks at or below u in its own draws
        rank = (np.argsort(np.argsort(E, axis=1), axis=1) + 1) / draws
        level = float(np.quantile(rank.max(axis=0), confidence))
        return {name: float(np.quantile(E[i], level)) for i, name in enumerate(self.gradients)}

    def meet_probability(self, targets: dict[str, float], draws: int = DRAWS, extra_mag: np.ndarray | None = None,
                         extra_acc: np.ndarray | None = None) -> float:
        """The probability that the largest |heading error| of every target is within it (deg), all together:
        the share of the parameter draws that meet them (with ``extra`` information, as :meth:`quantile`)."""
        E = self._largest_errors(draws, extra_mag, extra_acc)
        return float(np.mean(np.all(E <= np.array([targets[name] for name in self.gradients])[:, None], axis=0)))

    def before_any_data(self) -> UnitPrecision:
        """The same unit and targets with no information gathered yet (to price a design from scratch)."""
        return replace(self, mag=replace(self.mag, info=np.zeros_like(self.mag.info)),
                       acc=None if self.acc is None else replace(self.acc, info=np.zeros_like(self.acc.info)))

    def _largest_errors(self, draws: int, extra_mag: np.ndarray | None, extra_acc: np.ndarray | None) -> np.ndarray:
        """Largest |heading error| over each target's attitudes, (targets, draws), for draws of the parameters'
        errors from the covariance (fixed seed, so that predictions compare without noise)."""
        rng = np.random.default_rng(0)
        zm = _factor(self.mag.covariance(extra_mag)) @ rng.standard_normal((12, draws))
        za = None
        if self.acc is not None:
            za = _factor(self.acc.covariance(extra_acc)) @ rng.standard_normal((12, draws))
        worst = []
        for Gm, Ga in self.gradients.values():
            e = Gm @ zm
            if Ga is not None and za is not None:
                e = e + Ga @ za
            worst.append(np.max(np.abs(e), axis=0))
        return np.array(worst)


def _factor(C: np.ndarray) -> np.ndarray:
    """A square root of a covariance (symmetric, possibly singular)."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def target_attitudes() -> dict[str, np.ndarray]:
    """Encoder angles of each target, as the accuracy benchmark scores them: the level turn (5-deg steps) and
    the +-60 deg grid (every 30 deg of pitch and roll, headings every 15 deg)."""
    return {"level": level_turn(5.0), "tilted": attitude_grid()}


def heading_gradients(cal: Calibration, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """d(heading error)/d[M, b] (deg per unit) of the magnetometer and of the accelerometer at ``angles``,
    on the noise-free readings of the fitted unit in the fitted world (central differences)."""
    world = World(cal.inclination_deg, cal.declination_deg, TableGeometry(base_tilt_deg=tuple(cal.base_tilt_deg)))
    unit = Unit("fit", replace(cal.mag, noise_lsb=0.0), None if cal.acc is None else replace(cal.acc, noise_lsb=0.0))

    def grad(which: str) -> np.ndarray:
        s: LinearSensor = getattr(cal, which)
        p0 = np.r_[s.M.ravel(), s.bias]
        G = np.empty((len(angles), 12))
        for j in range(12):
            h = 1e-6 * max(abs(p0[j]), np.abs(s.M).max() * 1e-3)
            out = []
            for sign in (1.0, -1.0):
                p = p0.copy()
                p[j] += sign * h
                moved = replace(cal, **{which: LinearSensor.from_matrix(p[:9].reshape(3, 3), p[9:])})
                out.append(truth_errors(moved, unit, world, angles))
            G[:, j] = (out[0] - out[1]) / (2 * h)
        return G
    return grad("mag"), (grad("acc") if cal.acc is not None else None)


def unit_precision(rec: Recording, cal: Calibration) -> UnitPrecision:
    """The precision model of ``cal`` fitted (joint) to ``rec``'s rows that the fit kept."""
    dropped = {row["index"] for row in cal.quality.get("rejected_rows", [])} if cal.quality else set()
    keep = np.setdiff1d(np.arange(len(rec)), np.fromiter(dropped, int, len(dropped)))
    good = rec.select(keep)
    R = es.rotations(good)
    mag = sensor_info(R, good.mag, cal.mag)
    acc = None
    if cal.acc is not None and good.acc is not None and np.all(np.isfinite(good.acc)):
        acc = sensor_info(R, good.acc, cal.acc)
    grads = {name: heading_gradients(cal, a) for name, a in target_attitudes().items()}
    return UnitPrecision(mag, acc, grads)


#: Sharpness of the smooth maximum in :func:`best_design` (over the errors' variances relative to the largest).
_SMOOTH_MAX = 30.0


class Design(NamedTuple):
    """Samples per candidate attitude, and the information they add (as ``extra_mag``/``extra_acc`` of
    :meth:`UnitPrecision.quantile`)."""

    samples: np.ndarray
    extra_mag: np.ndarray
    extra_acc: np.ndarray | None


def best_design(u: UnitPrecision, angles: np.ndarray, samples: float, targets: dict[str, float]) -> Design:
    """Samples to take at each of ``angles`` (K, 3 encoder angles), ``samples`` in all, that minimise ``u``'s
    largest predicted 1-sigma heading error over its target (every attitude of every target) on top of the
    information ``u`` has gathered, and the information they add: a continuous optimal design, with no
    table time for moves. A smooth maximum of the variances is minimised (L-BFGS on softmax weights,
    analytic gradient), so the design is near-optimal for the probability of meeting the targets, not
    exactly optimal for it."""
    info_m = u.mag.per_sample(angles)
    info_a = u.acc.per_sample(angles) if u.acc is not None else None
    pad = lambda G: np.pad(G, ((0, 0), (0, 2)))  # noqa: E731  (the field direction's two parameters: no gradient)
    grads = [(pad(Gm), None if Ga is None or info_a is None else pad(Ga), targets[name])
             for name, (Gm, Ga) in u.gradients.items()]
    ridge = 1e-9 * np.eye(14)  # a design on few attitudes leaves F singular

    def weights(a: np.ndarray) -> np.ndarray:
        w = np.exp(a - a.max())
        return samples * w / w.sum()

    def objective(a: np.ndarray) -> tuple[float, np.ndarray]:
        w = weights(a)
        Cm = np.linalg.inv(u.mag.info + np.einsum("c,cij->ij", w, info_m) + ridge)
        Ca = None if info_a is None or u.acc is None else np.linalg.inv(u.acc.info + np.einsum("c,cij->ij", w, info_a) + ridge)
        var, dvar = [], []  # per attitude: variance over target^2, and its derivative in each weight
        for Gm, Ga, t in grads:
            U = Gm @ Cm
            v, dv = np.sum(U * Gm, axis=1), -np.einsum("ak,ckl,al->ac", U, info_m, U)
            if Ga is not None and Ca is not None and info_a is not None:
                U = Ga @ Ca
                v, dv = v + np.sum(U * Ga, axis=1), dv - np.einsum("ak,ckl,al->ac", U, info_a, U)
            var.append(v / t ** 2)
            dvar.append(dv / t ** 2)
        v, dv = np.concatenate(var), np.concatenate(dvar)
        top = v.max()
        e = np.exp(_SMOOTH_MAX * (v / top - 1.0))
        smooth = top * (1.0 + np.log(e.sum()) / _SMOOTH_MAX)
        dw = (e / e.sum()) @ dv
        da = w * dw - w * (w @ dw) / samples  # through the softmax
        return float(np.log(smooth)), da / smooth

    best = minimize(objective, np.zeros(len(angles)), jac=True, method="L-BFGS-B", options={"maxiter": 300})
    w = weights(best.x)
    return Design(w, np.einsum("c,cij->ij", w, info_m), None if info_a is None else np.einsum("c,cij->ij", w, info_a))
