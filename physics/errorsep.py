"""The paper's error-separation calibration in PHYSICS.md's conventions, and the joint refinement.

Stepwise (the paper, Gao et al. 2017):
1. find the sweeps in a recording from its table angles (samples where one gimbal turns and the
   other two stand still), whatever their labels say;
2. locate where each sensor axis peaks in each sweep, by fitting the whole sinusoid (or, as
   published, by picking the largest reading);
3. solve the peak phases for the sensor axes' directions in the body (M_o) and the field direction;
4. fit the line ``m_i = k_i H_i + b_i`` over the sweeps in which axis i sees the field from -1 to +1.

Joint: every sample at once, ``raw = M h_b + b`` with ``h_b = R(angles)^T v``, linear in M and b
for a fixed field direction v, which is found by a two-parameter search (variable projection). Its
covariance gives the 1-sigma uncertainty of every reported number. The accelerometer is the same
problem with v the specific force in the base frame, which is where the base tilt comes from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from physics.frames import SPECIFIC_FORCE_L, field_angles, rot_x, rot_y, rot_z
from physics.heading import pitch_roll, wrap180
from physics.recording import Recording, RecordingError
from physics.sensor import LinearSensor, Mo_to_angles, split_matrix
from physics.table import base_rotation, platform_attitude

AXES = "xyz"
#: Column index in ``angles`` (psi, theta, phi) of the encoder turning about each body axis.
TURNING_COLUMN = {2: 0, 1: 1, 0: 2}


class InsufficientData(ValueError):
    """The recording lacks the attitudes a parameter needs; the message names both."""


# --------------------------------------------------------------------------------------------------
# Sweeps
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Sweep:
    """Samples taken while one gimbal turned and the other two stood still."""

    axis: int                 # 0: inner x (phi_t), 1: middle y (theta_t), 2: outer z (psi_t)
    index: np.ndarray         # sample indices into the recording
    angle_deg: np.ndarray     # the turning encoder angle at each sample
    fixed_deg: np.ndarray     # (psi, theta, phi) with the turning one set to 0
    positions: int            # distinct angles visited
    coverage_deg: float       # how much of the circle the visited angles cover

    @property
    def name(self) -> str:
        """``sweep about z at theta=0, phi=0`` style label for messages."""
        others = [f"{n}={v:g}" for n, v, c in zip(("psi_t", "theta_t", "phi_t"), self.fixed_deg, range(3))
                  if c != TURNING_COLUMN[self.axis]]
        return f"sweep about {AXES[self.axis]} at {', '.join(others)}"


def table_angles(rec: Recording) -> np.ndarray:
    """Encoder angles (N, 3) as (psi_t, theta_t, phi_t) in degrees."""
    return np.column_stack([rec.psi_t, rec.theta_t, rec.phi_t])


def coverage_deg(angles_deg: np.ndarray) -> float:
    """How much of the circle a set of angles covers: 360 minus the largest gap between neighbours."""
    a = np.sort(np.unique(np.round(angles_deg % 360.0, 2)))
    if a.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, a[:1] + 360.0]))
    return float(360.0 - gaps.max())


def find_sweeps(angles: np.ndarray, min_positions: int = 3, min_coverage_deg: float = 90.0) -> list[Sweep]:
    """Every sweep in a recording, found from the table angles alone (labels are not trusted).

    A sample may belong to two sweeps (a level pose is both on the z turn and on a tilt sweep).
    """
    sweeps = []
    rounded = np.round(angles, 2)
    for axis in (2, 1, 0):
        col = TURNING_COLUMN[axis]
        others = np.delete(rounded, col, axis=1)
        keys, inverse = np.unique(others, axis=0, return_inverse=True)
        for g in range(len(keys)):
            idx = np.flatnonzero(inverse.ravel() == g)
            turning = angles[idx, col]
            positions = np.unique(np.round(turning % 360.0, 2)).size
            cov = coverage_deg(turning)
            if positions >= min_positions and cov >= min_coverage_deg:
                fixed = np.median(angles[idx], axis=0)
                fixed[col] = 0.0
                sweeps.append(Sweep(axis, idx, turning, fixed, positions, cov))
    return sweeps


def _sweep_frames(sw: Sweep) -> tuple[np.ndarray, np.ndarray]:
    """(Q, P) with ``R(angle) = P R_axis(angle) Q``: the fixed rotations outside and inside the turning gimbal."""
    psi, theta, phi = sw.fixed_deg
    if sw.axis == 2:
        return rot_y(theta) @ rot_x(phi), np.eye(3)
    if sw.axis == 1:
        return rot_x(phi), rot_z(psi)
    return np.eye(3), rot_z(psi) @ rot_y(theta)


def fit_sinusoid(angle_deg: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``y = c0 + c cos(a) + s sin(a)`` per column; returns (coef (3, ncol), residual rms (ncol,))."""
    a = np.radians(angle_deg)
    X = np.column_stack([np.ones_like(a), np.cos(a), np.sin(a)])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    dof = max(len(a) - 3, 1)
    rms = np.sqrt(np.sum((y - X @ coef) ** 2, axis=0) / dof)
    return coef, rms


# --------------------------------------------------------------------------------------------------
# Step 2-3: peak phases and the geometry they imply
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PeakPhase:
    """Where sensor axis ``sensor`` peaks in a sweep (radians of the turning angle) and how well that is known."""

    sweep: Sweep
    sensor: int
    phase: float
    sigma: float
    amplitude: float


def require_signal(mag: np.ndarray, sw: Sweep) -> None:
    """Refuse a sweep in which no magnetometer axis changes at all while the table turns (a dead or
    disconnected magnetometer, or readings that are not the magnetometer's): it has no phase to give."""
    if not np.ptp(mag[sw.index], axis=0).any():
        raise RecordingError(f"{sw.name}: mx, my and mz do not change while the table turns "
                             f"(constant {', '.join(f'{x:g}' for x in mag[sw.index[0]])}): "
                             "a dead or disconnected magnetometer?")


def phases_by_sinusoid(mag: np.ndarray, sweeps: list[Sweep]) -> list[PeakPhase]:
    """Peak phases from the whole sinusoid of each sweep (PHYSICS.md: the peak is flat, the sinusoid is not)."""
    out = []
    for sw in sweeps:
        require_signal(mag, sw)
        coef, rms = fit_sinusoid(sw.angle_deg, mag[sw.index])
        amps = np.hypot(coef[1], coef[2])
        for i in range(3):
            amp = float(amps[i])
            # noise-free data would give infinite weights; the floor scales with the sweep's largest
            # signal so that an axis almost along the turning axis keeps a weak, not exact, phase
            noise = max(float(rms[i]), 1e-6 * float(amps.max()))
            # an axis with no sinusoid at all in this sweep has no phase to give: no weight
            sigma = noise / (amp * np.sqrt(len(sw.index) / 2.0)) if amp > 0 else np.inf
            out.append(PeakPhase(sw, i, float(np.arctan2(coef[2, i], coef[1, i])), sigma, amp))
    return out


def phases_by_peak(mag: np.ndarray, sweeps: list[Sweep]) -> list[PeakPhase]:
    """Peak phases as published: the table angle of the largest mean reading among the poses of a sweep."""
    out = []
    for sw in sweeps:
        require_signal(mag, sw)
        pos = np.round(sw.angle_deg % 360.0, 2)
        uniq = np.unique(pos)
        means = np.array([mag[sw.index[pos == p]].mean(axis=0) for p in uniq])
        spacing = np.radians(360.0 / len(uniq))
        for i in range(3):
            amp = 0.5 * float(means[:, i].max() - means[:, i].min())
            out.append(PeakPhase(sw, i, float(np.radians(uniq[np.argmax(means[:, i])])), spacing / np.sqrt(12.0), amp))
    return out


def _axes_from_params(p: np.ndarray) -> np.ndarray:
    """Unit sensor axes near the body axes: row i = normalise(e_i + two free components)."""
    U = np.eye(3)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        U[i, others] = p[2 * i: 2 * i + 2]
    return U / np.linalg.norm(U, axis=1)[:, None]


def _unit(el: float, az: float) -> np.ndarray:
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


#: How far a sensor axis is expected to be from its body axis (1 sigma, deg): a weak prior that leads the
#: phase solution's search where the phases alone do not (a unit of 1000 LSB with 5 LSB of noise at
#: I = 70 deg had its axes and field turned 72 deg together, k 29 and 4 LSB instead of 1000, until
#: 2026-11-28; 5 of 300 random units were refused).
AXIS_PRIOR_DEG = 10.0
#: A phase solution with an axis further than this from its body axis is not the unit's (the analysis's
#: plausible misalignment is 10 deg): kept only when no other is found.
AXIS_LIMIT_DEG = 20.0


def solve_geometry(phases: list[PeakPhase]) -> tuple[np.ndarray, np.ndarray, float]:
    """Sensor axes (rows of M_o) and the field direction in the base frame from peak phases.

    The output of axis u over a sweep ``R = P R_a(angle) Q`` is ``(R_a w) . g`` with w = Q u, g = P^T v,
    i.e. ``w_a g_a + cos(angle) (w.g - w_a g_a) + sin(angle) (w x g)_a``: its phase is predicted exactly.
    Eight unknowns (two per axis, two for the field), one phase per sensor axis per sweep. Solved by
    weighted least squares on wrapped phase differences, started from the fixture's nominal axes and a
    few dips; a solution with an implausible axis (:data:`AXIS_LIMIT_DEG`) sends the search again with a
    weak prior on the axes (:data:`AXIS_PRIOR_DEG`). Returns (M_o, v_base, the phases' chi2 per degree
    of freedom).
    """
    frames = [_sweep_frames(ph.sweep) for ph in phases]
    Q = np.array([f[0] for f in frames])
    P = np.array([f[1] for f in frames])
    axis = np.array([ph.sweep.axis for ph in phases])
    sensor = np.array([ph.sensor for ph in phases])
    measured = np.array([ph.phase for ph in phases])
    sigma = np.array([ph.sigma for ph in phases])
    rows = np.arange(len(phases))

    def phase_residual(x: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        U, v = _axes_from_params(x[:6]), _unit(x[6], x[7])
        w = np.einsum("nij,nj->ni", Q, U[sensor])
        g = np.einsum("nji,j->ni", P, v)
        cos_part = np.sum(w * g, axis=1) - w[rows, axis] * g[rows, axis]
        sin_part = np.cross(w, g)[rows, axis]
        return np.angle(np.exp(1j * (np.arctan2(sin_part, cos_part) - measured))) / sigma

    def residual(x: np.ndarray, sigma: np.ndarray, prior: float) -> np.ndarray:
        return np.r_[phase_residual(x, sigma), x[:6] * prior]

    # The sensor axes are near the body axes: nine phases for eight unknowns leave the three weak ones (an
    # axis along the turning one) to tell the true geometry from axes and field turned together by tens of
    # degrees, and in their noise the turned one can fit the phases better. So of the solutions found,
    # those whose axes are all within AXIS_LIMIT_DEG of the body's are kept, and the one that fits the
    # phases best is the answer (the prior does not pull a plausible solution). When none is, the search
    # is made again with a weak prior on the axes (AXIS_PRIOR_DEG), which leads it into the basins the
    # phases alone miss; failing that, the likeliest with the prior.
    prior = 1.0 / np.tan(np.radians(AXIS_PRIOR_DEG))
    z_x = [ph for ph in phases if ph.sweep.axis == 2 and ph.sensor == 0]
    az_starts = [z_x[0].phase] if z_x else list(np.radians(np.arange(0, 360, 60)))
    found: list[np.ndarray] = []
    for weight in (0.0, prior):
        for el0 in np.radians([-70.0, -35.0, 0.0, 35.0, 70.0]):
            for az0 in az_starts:
                # x_scale=1: the parameters are all angles of similar size (scipy's default scales by the
                # Jacobian, which stalls on the very uneven weights of near-noise-free data)
                # First with the weights capped (sigma >= 0.01 rad) to find the basin, since near-noise-free
                # data give weights so uneven that the search stalls; then with the true weights.
                sol = least_squares(residual, np.r_[np.zeros(6), el0, az0], args=(np.maximum(sigma, 1e-2), weight),
                                    method="lm", x_scale=1.0)
                found.append(least_squares(residual, sol.x, args=(sigma, weight), method="lm", x_scale=1.0).x)
        plausible = [x for x in found if np.degrees(np.arctan(np.linalg.norm(x[:6].reshape(3, 2), axis=1).max()))
                     <= AXIS_LIMIT_DEG]
        if plausible:
            break
    cost = lambda x, w: float(np.sum(residual(x, sigma, w) ** 2))  # noqa: E731
    best = min(plausible, key=lambda x: cost(x, 0.0)) if plausible else min(found, key=lambda x: cost(x, prior))
    dof = max(len(phases) - 8, 1)
    r = phase_residual(best, sigma)
    return _axes_from_params(best[:6]), _unit(best[6], best[7]), float(r @ r / dof)


def fit_lines(mag: np.ndarray, h_b: np.ndarray, U: np.ndarray, sweeps: list[Sweep]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 8: per sensor axis, the line ``m_i = k_i H_i + b_i`` with ``H_i = u_i . h_b``.

    Uses the sweeps in which axis i sees at least half of the -1..+1 span (a z_m axis sees almost no
    change during a level turn); returns (k, b, standard errors (3, 2)).
    """
    k, b, se = np.zeros(3), np.zeros(3), np.zeros((3, 2))
    H = h_b @ U.T
    for i in range(3):
        spans = [np.ptp(H[sw.index, i]) for sw in sweeps]
        keep = [sw.index for sw, s in zip(sweeps, spans) if s >= min(1.0, 0.9 * max(spans))]
        idx = np.unique(np.concatenate(keep))
        X = np.column_stack([H[idx, i], np.ones(idx.size)])
        coef, *_ = np.linalg.lstsq(X, mag[idx, i], rcond=None)
        r = mag[idx, i] - X @ coef
        s2 = r @ r / max(idx.size - 2, 1)
        se[i] = np.sqrt(np.diag(s2 * np.linalg.inv(X.T @ X)))
        k[i], b[i] = coef
    return k, b, se


def require_sweeps(sweeps: list[Sweep], axes: tuple[int, ...] = (0, 1, 2)) -> None:
    """Refuse a recording that lacks a sweep about one of ``axes``, naming what it leaves undetermined."""
    have = {sw.axis for sw in sweeps}
    missing = [a for a in axes if a not in have]
    if not missing:
        return
    what = {
        2: "the azimuths of the sensor axes and the field azimuth D (and the x_m, y_m lines)",
        1: "the elevations of the sensor axes in the body x-z plane, the dip I and the z_m line (k_z, bias_z)",
        0: "the elevations of the sensor axes in the body y-z plane, the dip I and the z_m line (k_z, bias_z)",
    }
    found = ", ".join(sorted({f"about {AXES[a]}" for a in have})) or "none"
    lines = [f"no sweep about the table's {AXES[a]} axis: leaves undetermined {what[a]}" for a in missing]
    raise InsufficientData(
        "recording lacks the attitudes error separation needs (sweeps found: " + found + "; a sweep is at least "
        "3 poses covering 90 deg or more of one gimbal while the other two stand still):\n  " + "\n  ".join(lines)
    )


# --------------------------------------------------------------------------------------------------
# Joint least squares with covariance
# --------------------------------------------------------------------------------------------------

PARAM_NAMES = [f"M[{AXES[i]}m,{AXES[j]}b]" for i in range(3) for j in range(3)] + [f"bias[{a}]" for a in AXES] + [
    "direction[1]", "direction[2]"]


@dataclass
class VectorFit:
    """``raw = M R(angles)^T v + b`` fitted to every sample; covariance over [M (row-major), b, t (2)].

    ``t`` are two coordinates of the unit vector v on its tangent plane (``basis`` rows), zero at the
    solution, so v's uncertainty is ``basis^T cov_t basis``.
    """

    M: np.ndarray
    b: np.ndarray
    v: np.ndarray
    basis: np.ndarray
    cov: np.ndarray
    noise: np.ndarray
    residuals: np.ndarray
    scatter: float = 1.0  # the pose means' scatter over the noise's, when significant: the factor on cov (pose_scatter)

    def propagate(self, fn: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Value and 1-sigma of ``fn(M, b, v)`` by linear propagation of the covariance."""
        def at(p: np.ndarray) -> np.ndarray:
            v = self.v + p[12:14] @ self.basis
            return np.ravel(fn(p[:9].reshape(3, 3), p[9:12], v / np.linalg.norm(v)))

        p0 = np.r_[self.M.ravel(), self.b, 0.0, 0.0]
        f0 = at(p0)
        sd = np.sqrt(np.maximum(np.diag(self.cov), 0.0))
        J = np.zeros((f0.size, p0.size))
        for j in range(p0.size):
            h = max(sd[j], 1e-9) * 1e-3
            dp = np.zeros_like(p0)
            dp[j] = h
            J[:, j] = (at(p0 + dp) - at(p0 - dp)) / (2 * h)
        return f0, np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", J, self.cov, J), 0.0))


def _tangent_basis(v: np.ndarray) -> np.ndarray:
    a = np.eye(3)[np.argmin(np.abs(v))]
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(v, e1)])


def _linear_solve(R: np.ndarray, raw: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h = np.einsum("nji,j->ni", R, v)
    X = np.column_stack([h, np.ones(len(h))])
    coef, *_ = np.linalg.lstsq(X, raw, rcond=None)
    return coef, raw - X @ coef


def _jacobian(R: np.ndarray, M: np.ndarray, v: np.ndarray, basis: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """d(residual)/d[M, b, t] for residual = raw - M h - b, rows grouped by sensor axis, weighted."""
    n = len(R)
    h = np.einsum("nji,j->ni", R, v)
    dh = np.einsum("nji,kj->nki", R, basis)  # (n, 2, 3): dh/dt_k
    J = np.zeros((3 * n, 14))
    for i in range(3):
        rows = slice(i * n, (i + 1) * n)
        J[rows, 3 * i: 3 * i + 3] = -h
        J[rows, 9 + i] = -1.0
        J[rows, 12:14] = -np.einsum("nkj,j->nk", dh, M[i])
        J[rows] *= weights[i]
    return J


def check_identifiable(R: np.ndarray, v_guess: np.ndarray, what: str, hint: str) -> None:
    """Refuse a design whose Jacobian is rank-deficient, naming the parameters that cannot be told apart."""
    J = _jacobian(R, np.eye(3), v_guess, _tangent_basis(v_guess), np.ones(3))
    J = J / np.maximum(np.linalg.norm(J, axis=0), 1e-300)
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    bad = s < 1e-6 * s[0]
    if not bad.any():
        return
    names = sorted({PARAM_NAMES[j] for vec in Vt[bad] for j in np.flatnonzero(np.abs(vec) > 0.2)},
                   key=PARAM_NAMES.index)
    raise InsufficientData(f"{what}: the recording's attitudes cannot determine {', '.join(names)} "
                           f"(they trade off against each other without changing the fit). {hint}")


#: A recording longer than this is thinned to about this many samples to choose among the starts of
#: :func:`fit_vector_sensor` (shorter ones are searched whole).
START_SAMPLES = 4000


def fit_vector_sensor(R: np.ndarray, raw: np.ndarray, starts: list[np.ndarray]) -> VectorFit:
    """Joint fit of ``raw = M R^T v + b`` over every sample; the best of several starting directions.

    Each axis is weighted by its own residual noise (estimated from the residuals, then the field refined, twice over), so the
    covariance reflects the noise actually present.
    """
    def objective(t: np.ndarray, ref: np.ndarray, basis: np.ndarray, w: np.ndarray,
                  R: np.ndarray, raw: np.ndarray) -> np.ndarray:
        v = ref + t @ basis
        _, r = _linear_solve(R, raw, v / np.linalg.norm(v))
        return (r * w).ravel()

    weights = np.ones(3)
    best_v, best_cost = None, np.inf
    # the starts only pick the basin, which about START_SAMPLES evenly spread samples show as well as all of
    # them; the refinement below is on every sample (a 19 000-sample recording's thirteen starts took a second)
    step = -(-len(R) // START_SAMPLES)
    for v0 in starts:
        v0 = v0 / np.linalg.norm(v0)
        basis = _tangent_basis(v0)
        sol = least_squares(objective, np.zeros(2), args=(v0, basis, weights, R[::step], raw[::step]), method="lm")
        if sol.cost < best_cost:
            v = v0 + sol.x @ basis
            best_v, best_cost = v / np.linalg.norm(v), sol.cost
    assert best_v is not None
    for _ in range(2):  # reweight by each axis's own noise and refine
        _, r = _linear_solve(R, raw, best_v)
        noise = np.sqrt(np.sum(r * r, axis=0) / max(len(raw) - 5, 1))
        weights = 1.0 / np.maximum(noise, 1e-9 * np.abs(raw).max())
        basis = _tangent_basis(best_v)
        sol = least_squares(objective, np.zeros(2), args=(best_v, basis, weights, R, raw), method="lm")
        v = best_v + sol.x @ basis
        best_v = v / np.linalg.norm(v)
    coef, r = _linear_solve(R, raw, best_v)
    M, b = coef[:3].T, coef[3]
    noise = np.sqrt(np.sum(r * r, axis=0) / max(len(raw) - 5, 1))
    weights = 1.0 / np.maximum(noise, 1e-9 * np.abs(raw).max())
    basis = _tangent_basis(best_v)
    J = _jacobian(R, M, best_v, basis, weights)
    scatter = pose_scatter(R, r, noise, J.shape[1])
    return VectorFit(M=M, b=b, v=best_v, basis=basis, cov=np.linalg.pinv(J.T @ J) * scatter, noise=noise, residuals=r,
                     scatter=scatter)


#: The pose means' scatter is taken for errors the samples' noise does not show only when it is this unlikely
#: for noise alone (white noise keeps its covariance as it was).
POSE_SCATTER_P = 0.01


def pose_scatter(R: np.ndarray, r: np.ndarray, noise: np.ndarray, n_params: int) -> float:
    """How many times the variance the samples' noise predicts the pose means' residuals scatter with (chi-square
    over its degrees of freedom), when that is significant at :data:`POSE_SCATTER_P`; else 1. An error the same
    for every sample of a pose (the table's axes 0.05 deg off, the rounding of a noise-free reading) does not
    average down with the pose's samples: taken as independent, they made the stated 1-sigma 8-14 times too
    small. Samples that are not held in poses (a continuous sweep) give 1."""
    _, pose = np.unique(np.round(R.reshape(len(R), 9), 6), axis=0, return_inverse=True)
    pose = pose.ravel()
    n = np.bincount(pose)
    dof = 3 * len(n) - n_params
    if dof < 3 or np.median(n) < 2:
        return 1.0
    mean = np.column_stack([np.bincount(pose, r[:, a]) / n for a in range(3)])
    chi2 = float(np.sum(n[:, None] * mean ** 2 / np.maximum(noise, 1e-12) ** 2))
    return chi2 / dof if chi2 > stats.chi2.ppf(1.0 - POSE_SCATTER_P, dof) else 1.0


def _sphere_starts(n: int = 12) -> list[np.ndarray]:
    """Roughly even directions on the sphere (Fibonacci lattice) to start the field search from."""
    i = np.arange(n) + 0.5
    el = np.arcsin(1 - 2 * i / n)
    az = np.pi * (1 + 5 ** 0.5) * i
    return [_unit(e, a) for e, a in zip(el, az)]


def _fix_sign(fit: VectorFit) -> VectorFit:
    """Readings cannot tell the field's sign from the sensor's; choose M_o with a positive diagonal."""
    if np.trace(split_matrix(fit.M)[0]) < 0:
        fit.M, fit.v, fit.basis = -fit.M, -fit.v, -fit.basis
    return fit


def joint_magnetometer(R: np.ndarray, mag: np.ndarray, v_start: np.ndarray | None = None) -> VectorFit:
    """Joint fit of the magnetometer; v is the unit field in the table's base frame."""
    check_identifiable(
        R, np.array([0.5, 0.3, 0.81]) / np.linalg.norm([0.5, 0.3, 0.81]), "magnetometer",
        "Add sweeps about the table's x and y axes (tilting the unit) so that every sensor axis sees the field from -1 to +1.")
    starts = ([v_start] if v_start is not None else []) + _sphere_starts()
    return _fix_sign(fit_vector_sensor(R, mag, starts))


def joint_accelerometer(R: np.ndarray, acc: np.ndarray) -> VectorFit:
    """Joint fit of the accelerometer; v is the specific force (g) in the base frame, nearly (0, 0, -1)."""
    # judged at a level base: a guess tilted by 0.01 rad let a design with no roll pass (the 0.01 g its y axis
    # would see "determined" its sensitivity, fitted as 31812 counts per g +- 0.0006 against 16700)
    check_identifiable(
        R, np.array([0.0, 0.0, -1.0]), "accelerometer",
        "Tilt the unit: sweeps about the table's x and y axes, or the six-position poses (each body axis up and down).")
    fit = fit_vector_sensor(R, acc, [np.array([0.0, 0.0, -1.0])])
    if fit.v[2] > 0:  # gravity points down in the base frame: z of the specific force is negative
        fit.M, fit.v, fit.basis = -fit.M, -fit.v, -fit.basis
    return fit


def tilt_from_specific_force(v_base: np.ndarray) -> np.ndarray:
    """Base tilt (about x, about y) in degrees from the specific force in base coordinates."""
    pitch, roll = pitch_roll(v_base)
    return np.array([roll[0], pitch[0]])


def field_in_lab(v_base: np.ndarray, tilt_deg: np.ndarray) -> np.ndarray:
    """(I, D) in degrees of a base-frame field direction, given the base tilt."""
    return np.array(field_angles(base_rotation(tilt_deg) @ v_base))


def tilt_by_reversal(psi_deg: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Base tilt (about x, about y) from a level turn about z, by reversal (PHYSICS.md, "Levelling").

    The tilt, seen in body axes, turns with psi_t while the accelerometer's own bias and misalignment
    do not: the once-per-turn sinusoids of a_x and a_y are the tilt.
    """
    coef, _ = fit_sinusoid(psi_deg, acc[:, :2])
    k = float(np.linalg.norm(acc.mean(axis=0)))
    # a_x ~ k (v_x cos psi + v_y sin psi); a_y ~ k (v_y cos psi - v_x sin psi)
    vx = 0.5 * (coef[1, 0] - coef[2, 1]) / k
    vy = 0.5 * (coef[2, 0] + coef[1, 1]) / k
    v = np.array([vx, vy, -np.sqrt(max(1.0 - vx * vx - vy * vy, 0.0))])
    return tilt_from_specific_force(v)


def six_position(angles: np.ndarray, acc: np.ndarray, tol_deg: float = 2.0) -> LinearSensor | None:
    """Six-position accelerometer calibration when the recording holds each body axis up and down.

    Column j of A is half the difference of the readings with +e_j and -e_j along the specific force;
    the bias is the mean of all six. Returns None when a position is missing.
    """
    R = platform_attitude(angles[:, 0], angles[:, 1], angles[:, 2])
    f = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, -1.0]))
    cols, means = [], []
    for j in range(3):
        pair = []
        for sign in (1.0, -1.0):
            near = f[:, j] * sign > np.cos(np.radians(tol_deg))
            if not near.any():
                return None
            pair.append(acc[near].mean(axis=0))
        cols.append(0.5 * (pair[0] - pair[1]))
        means += pair
    return LinearSensor.from_matrix(np.column_stack(cols), np.mean(means, axis=0))


# --------------------------------------------------------------------------------------------------
# Derived numbers with uncertainties
# --------------------------------------------------------------------------------------------------

def sensor_sigmas(fit: VectorFit) -> dict[str, np.ndarray]:
    """1-sigma of the reported numbers of a linear sensor: angles_deg (3x3), k (3), bias (3)."""
    _, s_ang = fit.propagate(lambda M, b, v: Mo_to_angles(split_matrix(M)[0]))
    _, s_k = fit.propagate(lambda M, b, v: split_matrix(M)[1])
    # (a variance a hair below zero is the rounding of a near-singular covariance, as in propagate)
    return {"angles_deg": s_ang.reshape(3, 3), "k": s_k, "bias": np.sqrt(np.maximum(np.diag(fit.cov)[9:12], 0.0))}


def field_and_tilt(mag_fit: VectorFit, acc_fit: VectorFit | None) -> dict[str, np.ndarray]:
    """I, D and base tilt with 1-sigma; without an accelerometer the base is taken as level."""
    if acc_fit is None:
        tilt, s_tilt = np.zeros(2), np.full(2, np.nan)
    else:
        tilt, s_tilt = acc_fit.propagate(lambda M, b, v: tilt_from_specific_force(v))
    d0 = field_in_lab(mag_fit.v, tilt)[1]

    def field(v: np.ndarray, t: np.ndarray) -> np.ndarray:
        inc, dec = field_in_lab(v, t)
        return np.array([inc, d0 + wrap180(dec - d0)])  # keep D continuous for differencing

    ang, s_mag = mag_fit.propagate(lambda M, b, v: field(v, tilt))
    ang[1] %= 360.0
    if acc_fit is not None:
        # the tilt's own uncertainty moves I and D too (independent estimates: add in quadrature)
        J = np.zeros((2, 2))
        for j in range(2):
            d = np.zeros(2)
            d[j] = 1e-4
            J[:, j] = (field(mag_fit.v, tilt + d) - field(mag_fit.v, tilt - d)) / 2e-4
        s_mag = np.sqrt(s_mag ** 2 + (J ** 2) @ (s_tilt ** 2))
    return {"field": ang, "field_sigma": s_mag, "tilt": tilt, "tilt_sigma": s_tilt}


# --------------------------------------------------------------------------------------------------
# The accelerometer step shared by every method, and the two pipelines
# --------------------------------------------------------------------------------------------------

@dataclass
class Accel:
    """The accelerometer calibration and base tilt every magnetometer method is given."""

    sensor: LinearSensor | None
    tilt_deg: np.ndarray
    fit: VectorFit | None = None
    method: str = "none"
    notes: tuple[str, ...] = ()

    def sigma(self) -> dict[str, np.ndarray]:
        """1-sigma of the accelerometer's reported numbers (empty without a joint fit)."""
        return sensor_sigmas(self.fit) if self.fit is not None else {}


def rotations(rec: Recording) -> np.ndarray:
    """Nominal (ideal-table, level-base) platform attitudes R (N, 3, 3) of every sample."""
    a = table_angles(rec)
    return platform_attitude(a[:, 0], a[:, 1], a[:, 2])


def specific_force(rec: Recording, sensor: LinearSensor | None) -> np.ndarray:
    """f_b (g) per sample: from the calibrated accelerometer when there is one, else the table's nominal f_b.

    Rows whose accelerometer cells are empty (NaN) fall back to the nominal value too.
    """
    nominal = np.einsum("nji,j->ni", rotations(rec), SPECIFIC_FORCE_L)
    if sensor is None or rec.acc is None:
        return nominal
    f = sensor.correct(rec.acc)
    bad = ~np.all(np.isfinite(f), axis=1)
    f[bad] = nominal[bad]
    return f


def accelerometer(rec: Recording) -> Accel:
    """Accelerometer and base tilt from the same attitudes as the magnetometer (joint fit with reversal).

    Six-position data alone (no reversal about z) is used when the joint fit cannot be made; a
    recording without accelerometer columns gives a level base and no model.
    """
    if rec.acc is None:
        levelled = ("heading levelled by table angles" if rec.has_angles else
                    "no table angles either, so headings are not levelled (they are a level unit's)")
        return Accel(None, np.zeros(2), notes=(f"no accelerometer data: base taken as level, {levelled}",))
    if not rec.has_angles:  # (its fit against the table's attitudes on empty angles ended in "SVD did not converge")
        return Accel(None, np.zeros(2), notes=("accelerometer not calibrated: it is calibrated against the table's "
                                               "angles, and this recording has none",))
    ok = np.all(np.isfinite(rec.acc), axis=1)
    R, acc = rotations(rec)[ok], rec.acc[ok]
    try:
        fit = joint_accelerometer(R, acc)
    except InsufficientData as e:
        angles = table_angles(rec)[ok]
        level = (np.abs(angles[:, 1]) < 0.01) & (np.abs(angles[:, 2]) < 0.01)
        tilt = np.zeros(2)
        if coverage_deg(angles[level, 0]) >= 180.0:
            tilt = tilt_by_reversal(angles[level, 0], acc[level])
        six = six_position(angles, acc)
        if six is None:
            return Accel(None, tilt, method="reversal", notes=(
                f"accelerometer not calibrated ({e}); base tilt by reversal on the level turn, heading levelled by table angles",))
        return Accel(six, tilt, method="six-position",
                     notes=(f"accelerometer by six positions; base tilt by reversal only ({e})",))
    return Accel(LinearSensor.from_matrix(fit.M, fit.b), tilt_from_specific_force(fit.v), fit, "joint")


def error_separation(rec: Recording, acc: Accel, peak: str = "sinusoid") -> tuple[LinearSensor, np.ndarray, dict[str, object]]:
    """The paper's stepwise method: sweeps -> peak phases -> M_o, field -> lines -> k, b.

    ``peak`` is "sinusoid" (ours: fit the whole sinusoid) or "pick" (as published). Returns the
    magnetometer model, the field direction in the base frame and diagnostics.
    """
    angles = table_angles(rec)
    sweeps = find_sweeps(angles)
    require_sweeps(sweeps)
    phases = (phases_by_sinusoid if peak == "sinusoid" else phases_by_peak)(rec.mag, sweeps)
    U, v, chi2 = solve_geometry(phases)
    h_b = np.einsum("nji,j->ni", rotations(rec), v)
    k, b, se = fit_lines(rec.mag, h_b, U, sweeps)
    return LinearSensor(U, k, b), v, {"sweeps": [sw.name for sw in sweeps], "phase_chi2": chi2, "line_se": se}
