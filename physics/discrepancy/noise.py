"""The noise floor: AR(1) plus white noise per axis, its Kalman whitening, and simulated nulls."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from scipy import signal

from physics.recording import RecordingError

if TYPE_CHECKING:
    from physics.discrepancy.twin import Context


# --------------------------------------------------------------------------------------------------
# Noise: AR(1) per axis, whitening, simulation
# --------------------------------------------------------------------------------------------------

#: A noise floor below this (LSB, 0.01 nT at the nominal scale) is no sensor's: the readings repeat
#: exactly, as a simulation without noise (or a saturated axis) gives them.
MIN_FLOOR_LSB = 1e-3


def require_noise(floor: np.ndarray) -> None:
    """Refuse (RecordingError) a recording whose magnetometer axes (per-sample ``floor``, LSB) show no noise:
    every test judges a departure against the noise, and against none the smallest rounding would be one."""
    quiet = [axis for axis, f in zip(("mx", "my", "mz"), np.asarray(floor, float)) if not f >= MIN_FLOOR_LSB]
    if quiet:
        raise RecordingError(
            f"no measurable noise on {', '.join(quiet)} (a noise floor under {MIN_FLOOR_LSB:g} LSB: the readings "
            "repeat exactly, as a simulation without noise or a saturated axis gives them): the analysis judges "
            "every departure against the sensor's noise, so it needs a recording that has it (a real one, or a "
            "simulated one with noise, e.g. compasscal simulate --noise 3)")


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
        # the Riccati fixed point Pm = p^2 Pm q / (Pm + q) + e2, a quadratic's positive root, written
        # without cancellation for either sign of B
        B = q * (1.0 - p * p) - e2
        root = np.sqrt(B * B + 4.0 * e2 * q)
        Pm = np.where(B > 0, 2.0 * e2 * q / np.maximum(B + root, 1e-300), 0.5 * (root - B))
        return Pm / np.maximum(Pm + q, 1e-300), np.sqrt(Pm + q)

    def spectrum(self, f: np.ndarray, rate_hz: float) -> np.ndarray:
        """Noise power (arbitrary scale) at frequencies ``f`` per axis: (len(f), 3)."""
        z = np.exp(-2j * np.pi * f / rate_hz)[:, None]
        return self.sigma ** 2 * (1 - self.phi ** 2) / np.abs(1.0 - self.phi * z) ** 2 + self.white ** 2


#: Lags of the differences' autocovariance that the noise model is fitted to.
NOISE_LAGS = 12

#: The AR part must show in the differences' autocovariance at lags 2..NOISE_LAGS (z-score of their
#: negated sum) for the noise to be modelled as coloured; below it the noise is white.
AR_Z = 2.0


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
        # the mean of the products over the kept pairs, without the products' array (many nulls at once)
        g.append(np.einsum("n,n...,n...->...", ok.astype(float), d[k:], d[:len(d) - k]) / ok.sum()
                 if ok.any() else np.zeros(d.shape[1:]))
    g = np.array(g)  # (lags, 3, ...)
    shape = g.shape[1:]
    G = g.reshape(len(g), -1)
    sig, phi, white = np.empty(G.shape[1]), np.empty(G.shape[1]), np.empty(G.shape[1])
    k = np.arange(len(g))
    n = max(int(same.sum()), 1)
    for i in range(G.shape[1]):
        if ar_evidence(G[:, i], n) < AR_Z:
            # White noise: a fitted AR part would be the lags' sampling noise, and a spurious slow part
            # (phi 0.7 on 1 LSB of 3) nearly doubles the noise every slow effect's test is judged against.
            sig[i], phi[i], white[i] = 0.0, 0.0, float(np.sqrt(max((2.0 * G[0, i] - G[1, i]) / 5.0, 1e-300)))
        else:
            sig[i], phi[i], white[i] = _fit_difference_acov(G[:, i], k)
    return NoiseModel(sig.reshape(shape), phi.reshape(shape), white.reshape(shape))


def ljung_box(E: np.ndarray, lags: int) -> np.ndarray:
    """The Ljung-Box statistic of each column of the whitened residuals ``E`` (n, S), over ``lags`` lags:
    chi-square with ``lags`` degrees of freedom for each column that is white."""
    n = E.shape[0]
    # contiguous, and the lag products summed without forming them: on 200 nulls of a 19 000-sample
    # recording each product was a 90-MB temporary, and the test took 1.4 s instead of 0.2
    x = np.ascontiguousarray(E - E.mean(axis=0))
    den = np.maximum(np.einsum("ij,ij->j", x, x), 1e-300)
    q = np.zeros(E.shape[1])
    for k in range(1, lags + 1):
        q += (np.einsum("ij,ij->j", x[k:], x[:-k]) / den) ** 2 / (n - k)
    return n * (n + 2) * q


def ar_evidence(g: np.ndarray, n: int) -> float:
    """z-score of an AR part in the first differences' autocovariance ``g`` (lags 0..), from ``n``
    differences: the negated sum of the autocorrelations at lags >= 2. White noise's differences are
    MA(1) (rho_1 = -1/2, zero beyond), and by Bartlett's formula that sum's variance is ~1/n (the
    neighbouring lags' covariances cancel most of the 1.5/n each lag has alone); an AR(1) part adds
    u phi^(k-1) / g(0) to each lag's negation."""
    return float(-np.sum(g[2:]) / max(g[0], 1e-300) * np.sqrt(n))


def _fit_difference_acov(g: np.ndarray, k: np.ndarray) -> tuple[float, float, float]:
    """(s, phi, sqrt q) of AR(1)-plus-white noise from its differences' autocovariance g(k)."""
    from scipy.optimize import least_squares

    g0 = max(g[0], 1e-300)
    phi1 = float(np.clip(1.0 + 2.0 * g[1] / g0, 0.01, 0.98))  # AR(1) alone, the start (a sensor's noise is low-passed: phi >= 0)

    def model(x: np.ndarray) -> np.ndarray:
        u, ph, q = x[0] ** 2, x[1], x[2] ** 2
        m = -u * ph ** np.maximum(k - 1, 0)
        m[0] = 2 * u / (1 - ph) + 2 * q
        m[1] -= q
        return m

    def jac(x: np.ndarray) -> np.ndarray:  # analytic: the fit runs once per axis of every null simulation
        u, ph = x[0] ** 2, x[1]
        J = np.zeros((len(k), 3))
        J[:, 0] = -2 * x[0] * ph ** np.maximum(k - 1, 0)
        J[2:, 1] = -u * (k[2:] - 1) * ph ** (k[2:] - 2)
        J[0] = [4 * x[0] / (1 - ph), 2 * u / (1 - ph) ** 2, 4 * x[2]]
        J[1] = [-2 * x[0], 0.0, -2 * x[2]]
        return J / g0

    u0 = g0 * (1 - phi1) / 2 * (1 - phi1)
    sol = least_squares(lambda x: (model(x) - g) / g0, [np.sqrt(max(u0, 1e-300)), phi1, np.sqrt(0.1 * g0)],
                        jac=jac, bounds=([0.0, 0.0, 0.0], [np.inf, 0.985, np.inf]), x_scale=1.0, ftol=1e-6, xtol=1e-6)
    u, ph, q = sol.x[0] ** 2, float(sol.x[1]), sol.x[2] ** 2
    s = float(np.sqrt(max(u, 1e-12)) / (1 - ph))
    if s * s < 0.02 * q:  # no AR part to speak of: white noise, and its phi means nothing
        return s, 0.0, float(np.sqrt(q))
    return s, ph, float(np.sqrt(q))


def estimate_noise(r: np.ndarray, ctx: "Context") -> NoiseModel:
    """The noise floor: the restricted likelihood of the static holds (:func:`reml_noise`) when their
    chunks hold 200 samples or more (the table at rest: nothing but the sensor's noise), else
    :func:`noise_model` on every contiguous run of samples."""
    hold = ctx.hold >= 0
    if hold.sum() - len(np.unique(ctx.hold[hold])) >= 200:
        got = reml_noise(r[hold], ctx.hold[hold])
        return got if got is not None else noise_model(r[hold], ctx.hold[hold])
    return noise_model(r, ctx.segment)


# --------------------------------------------------------------------------------------------------
# The restricted (exact) likelihood of the holds
# --------------------------------------------------------------------------------------------------

#: The holds are cut into chunks of one length, at most this (the likelihood's grid holds an L x L
#: matrix per point); each chunk's mean is left free, so no pose's mean or slow model error enters.
REML_CHUNK = 60
#: Shortest chunk worth it (shorter holds: the differences' fit).
REML_MIN_CHUNK = 8
#: The share of the samples in holds that the chunks must cover (the longest such chunk length is taken).
REML_COVER = 0.5
#: The grid: phi = 1 - exp(-u) with u evenly spaced (dense near 1, where the slow noise hangs on phi's
#: second decimal), and the AR part's share of the variance.
_U = np.linspace(0.0, -np.log(1.0 - 0.985), 36)
REML_PHI = 1.0 - np.exp(-_U)
REML_SHARE = np.linspace(0.0, 1.0, 17)
#: Twice the log-likelihood an AR part must gain over white noise to be kept. On 3 000 simulated white
#: series of 28 holds x 60 samples (3 LSB) 1 % reach it; a faint slow part (phi 0.95, 0.86 LSB: it
#: triples the slow noise) reaches it in three cases of four, phi 0.2 at 1.5 LSB always. (The
#: differences' z gate let the faint one through in 4 % of its draws, no more often than white noise.)
AR_LR = 7.5


#: A chunk whose largest step (the two-segment mean difference's statistic, :func:`_steps`) exceeds this
#: many times the median chunk's holds a change of level, not noise, and is left out. On 2 000 simulated
#: series of 28 x 60 samples it leaves out 2e-4 of white chunks and 1 % at phi 0.9.
STEP_TRIM = 6.0


def _steps(x: np.ndarray) -> np.ndarray:
    """The largest single-step statistic of each chunk (H, L, n) -> (H, n): max over the split k of
    S_k^2 L / (k (L - k)), S_k the cumulative sum of the chunk less its mean."""
    L = x.shape[1]
    S = np.cumsum(x - x.mean(axis=1, keepdims=True), axis=1)[:, :-1]
    k = np.arange(1, L)[None, :, None]
    return np.max(S * S * L / (k * (L - k)), axis=1)


def _lags(L: int) -> np.ndarray:
    """|i - j| for a chunk of L samples (the exponent of the AR(1) correlation)."""
    return np.abs(np.subtract.outer(np.arange(L), np.arange(L)))


def _restricted(phi: np.ndarray, share: np.ndarray, L: int) -> tuple[np.ndarray, np.ndarray]:
    """For each (phi, share): the restricted-likelihood matrix P = R^-1 - R^-1 1 1^T R^-1 / (1^T R^-1 1)
    of the unit-variance correlation R = share T(phi) + (1 - share) I of a chunk of L, and
    log|R| + log(1^T R^-1 1). Shapes (G, L, L) and (G,)."""
    R = share[:, None, None] * phi[:, None, None] ** _lags(L) + (1.0 - share)[:, None, None] * np.eye(L)
    Ri = np.linalg.inv(R)
    a = Ri.sum(axis=2)  # R^-1 1
    s = a.sum(axis=1)  # 1^T R^-1 1
    return Ri - a[:, :, None] * a[:, None, :] / s[:, None, None], np.linalg.slogdet(R)[1] + np.log(s)


@lru_cache(maxsize=4)
def _reml_grid(L: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_restricted` at every grid point (phi major, then share), P flattened: shapes (G, L*L)
    and (G,), G = len(REML_PHI) * len(REML_SHARE)."""
    P, const = _restricted(np.repeat(REML_PHI, len(REML_SHARE)), np.tile(REML_SHARE, len(REML_PHI)), L)
    return P.reshape(len(P), L * L), const


def _chunks(r: np.ndarray, hold: np.ndarray) -> np.ndarray | None:
    """The holds' samples as chunks (H, L, ...) of one length, each hold giving as many whole chunks as it
    holds: L is the longest (at most :data:`REML_CHUNK`, at least :data:`REML_MIN_CHUNK`) whose chunks
    cover :data:`REML_COVER` of the samples in holds of REML_MIN_CHUNK or more.

    Short holds do not set L. A recording sampled on the move has a few samples at a hold's angles before
    or after each move (its settling, under a step label of its own), a hold of its own; a dropped sample
    splits a hold in two. With the tenth percentile of the hold lengths as L, such pieces made the chunks 4
    to 10 samples long, which tell a slow part of the noise from the chunk's free mean poorly: phi 0.8 on 3
    LSB was read as 2.1 LSB of white noise (4 false alarms in 11 of an outside tester's nulls), or phi
    went to its bound and the floor to 1.5 times the residual's own rms."""
    starts = np.flatnonzero(np.r_[True, hold[1:] != hold[:-1]])
    lengths = np.diff(np.r_[starts, len(hold)])
    usable = lengths[lengths >= REML_MIN_CHUNK]
    if not usable.size:
        return None
    L = next((n for n in range(REML_CHUNK, REML_MIN_CHUNK - 1, -1)
              if np.sum(usable // n * n) >= REML_COVER * usable.sum()), REML_MIN_CHUNK)
    idx = [s + k * L + np.arange(L) for s, n in zip(starts, lengths) for k in range(n // L)]
    if len(idx) * (L - 1) < 200:
        return None
    return r[np.array(idx)]


def _parabola(y: np.ndarray, i: np.ndarray, size: int) -> np.ndarray:
    """Offset (in grid steps, within +-0.5) of the maximum of a parabola through y[i-1], y[i], y[i+1]
    (rows of y indexed by i per column); 0 at the grid's ends."""
    inner = (i > 0) & (i < size - 1)
    col = np.arange(y.shape[1])
    lo, mid, hi = (y[np.clip(i + d, 0, size - 1), col] for d in (-1, 0, 1))
    den = lo - 2.0 * mid + hi
    off = np.where(inner & (den < 0), 0.5 * (lo - hi) / np.where(den < 0, den, -1.0), 0.0)
    return np.clip(off, -0.5, 0.5)


def reml_noise(r: np.ndarray, hold: np.ndarray) -> NoiseModel | None:
    """AR(1)-plus-white noise per axis (and per trailing column) by the restricted likelihood of the
    holds: each hold cut into chunks of one length L with their own free mean (so no pose's mean
    enters), the exact Gaussian likelihood of what is left maximised over a grid of (phi, AR share),
    the scale in closed form, then refined between grid points by a parabola in each direction.

    Chunks holding a step (:data:`STEP_TRIM`) are left out. The differences' autocovariance
    (:func:`noise_model`) weighs its lags alike; the likelihood weighs
    the data as they are, and the slow noise a window is judged against, s^2 (1 + phi) / (1 - phi) + q,
    comes out with half the scatter at phi 0.3-0.89 (sd of its log 0.21 -> 0.11 at 0.45, 0.44 -> 0.25 at
    0.89, on 200 simulated series of 28 holds x 60) and without the differences' overstatement of 8-13 %
    at phi 0.3-0.75. The AR part is kept only when it gains :data:`AR_LR` over white noise.
    None when the holds are too short or too few (then the differences' fit)."""
    x = _chunks(r, hold)
    if x is None:
        return None
    H, L = x.shape[:2]
    shape = x.shape[2:]
    X = x.reshape(H, L, -1)
    n = X.shape[2]
    # A departure that starts or ends inside a hold is a step there, which the likelihood would take for
    # slow noise (a window offset of 8 LSB read as phi 0.98): such chunks are left out, per axis.
    steps = _steps(X)
    keep = steps <= STEP_TRIM * np.maximum(np.median(steps, axis=0), 1e-300)
    S = np.einsum("hin,hjn,hn->nij", X, X, keep.astype(float)).reshape(n, L * L)
    P, const = _reml_grid(L)
    used = keep.sum(axis=0)
    m = used * (L - 1)
    quad = np.maximum(P @ S.T, 1e-300)  # (G, n): sum over the kept chunks of x^T P x
    ll = (-0.5 * (m * np.log(quad / m) + used * const[:, None])).reshape(len(REML_PHI), len(REML_SHARE), n)
    best = ll.reshape(-1, n).argmax(axis=0)
    i, j = np.unravel_index(best, ll.shape[:2])
    col = np.arange(n)
    white_ll = ll[0, 0]  # share 0: white noise, whatever phi
    ar = (2.0 * (ll[i, j, col] - white_ll) >= AR_LR) & (quad[0] > 1e-250)  # (noise-free data: white, 0)
    u = np.interp(i + _parabola(ll[:, j, col], i, len(REML_PHI)), np.arange(len(_U)), _U)
    share_i = j + _parabola(ll[i, :, col].T, j, len(REML_SHARE))
    phi = np.where(ar, 1.0 - np.exp(-u), 0.0)
    share = np.where(ar, np.interp(share_i, np.arange(len(REML_SHARE)), REML_SHARE), 0.0)
    # the scale in closed form at the refined point: sum x^T P x over the kept chunks / (their count (L - 1))
    Pn = _restricted(phi, share, L)[0]
    c = np.maximum(np.einsum("nij,nij->n", Pn, S.reshape(n, L, L)) / m, 1e-300)  # noise-free data: not 0
    sig, white = np.sqrt(share * c), np.sqrt((1.0 - share) * c)
    return NoiseModel(sig.reshape(shape), phi.reshape(shape), white.reshape(shape))


def whiten_all(X: np.ndarray, noise: NoiseModel, segment: np.ndarray) -> np.ndarray:
    """Whiten (N, 3, p) columns (or (N, 3) data) into stacked rows (3N, p) (axis-major): the Kalman
    innovations of the AR(1)-plus-white model, nu_t = x_t - phi x_{t-1} + phi (1 - K) nu_{t-1}, each over
    its innovation sigma, restarted (from the marginal sigma) at each segment."""
    flat = X.ndim == 2
    X3 = X[:, :, None] if flat else X
    K, S = noise.kalman()
    first = np.r_[True, segment[1:] != segment[:-1]]
    out = np.empty((3, X3.shape[0], X3.shape[2]))
    for j in range(3):
        if noise.phi[j] == 0.0:  # white noise: the filter is the identity and S the floor
            out[j] = X3[:, j, :] / noise.floor[j]
            continue
        out[j] = _filter_segments([1.0, -noise.phi[j]], [1.0, -noise.phi[j] * (1.0 - K[j])], X3[:, j, :], segment)
        out[j] /= S[j]
        out[j, first] *= S[j] / noise.floor[j]  # a segment's first sample: nothing to predict it from
    out = out.reshape(3 * X3.shape[0], X3.shape[2])
    return out[:, 0] if flat else out


def whiten_adjoint(V: np.ndarray, noise: NoiseModel, segment: np.ndarray) -> np.ndarray:
    """The transpose of :func:`whiten_all` as a linear map: for stacked rows V (3N, q) the (N, 3, q) array U
    with V^T whiten_all(X) = sum over samples t and axes j of U[t, j]^T X[t, j] for every X (N, 3, p).

    So the projections of many whitened columns on a few fixed ones (Q^T W X) need only the raw columns:
    W^T Q once instead of W X for each. Per axis the whitening is a diagonal scaling after a first-order
    filter restarted at each segment, a block-diagonal lower-triangular Toeplitz map; its transpose is the
    same filter run backwards in time over the same segments, after the scaling."""
    flat = V.ndim == 1
    n = len(segment)
    V3 = V.reshape(3, n, -1)
    K, S = noise.kalman()
    first = np.r_[True, segment[1:] != segment[:-1]]
    out = np.empty((n, 3, V3.shape[2]))
    for j in range(3):
        if noise.phi[j] == 0.0:
            out[:, j] = V3[j] / noise.floor[j]
            continue
        scale = np.where(first, 1.0 / noise.floor[j], 1.0 / S[j])
        back = (V3[j] * scale[:, None])[::-1]
        out[:, j] = _filter_segments([1.0, -noise.phi[j]], [1.0, -noise.phi[j] * (1.0 - K[j])], back, segment[::-1])[::-1]
    return out[:, :, 0] if flat else out


def _filter_segments(b: list[float], a: list[float], x: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """``lfilter(b, a)`` (first order) along axis 0 of ``x`` (N, p), restarted from rest at each segment.

    One filter over the whole series, less each segment's carry-over from the one before: at a
    segment's first sample s the continuous output exceeds the restarted one by
    d_s = b1 x_{s-1} - a1 y_{s-1}, which decays by c = -a1 per sample after it. That excess is itself
    a first-order filter's output, driven at each start by d_s less what is left of the previous
    segment's (c^length d_prev). A loop over 50-odd segments per call had cost the analyser most of its
    time."""
    y = signal.lfilter(b, a, x, axis=0)
    starts = np.flatnonzero(np.r_[True, segment[1:] != segment[:-1]])
    if starts.size < 2:
        return y
    c = -a[1]
    d = np.zeros((starts.size,) + x.shape[1:])
    d[1:] = b[1] * x[starts[1:] - 1] - a[1] * y[starts[1:] - 1]
    drive = np.zeros_like(y)
    drive[starts[1:]] = d[1:] - (c ** np.diff(starts).astype(float))[(...,) + (None,) * (x.ndim - 1)] * d[:-1]
    return y - signal.lfilter([1.0], [1.0, -c], drive, axis=0)


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
    for j in range(3):  # the AR recursion restarted at each segment (from its first innovation)
        out[:, j] = _filter_segments([1.0, 0.0], [1.0, -noise.phi[j]], innov[:, j], segment)
    return out + rng.normal(size=(n, 3, k)) * noise.white[None, :, None]

