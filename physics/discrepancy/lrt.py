"""Nested likelihood-ratio tests on the whitened linear twin, calibrated on simulated nulls, and the
spectral line search."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy import special, stats

from physics.discrepancy.noise import NoiseModel, _whiten_each, estimate_noise, simulate_noise
from physics.discrepancy.twin import Context



# --------------------------------------------------------------------------------------------------
# Tests on the whitened linear twin
# --------------------------------------------------------------------------------------------------

def _orth(A: np.ndarray, rcond: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the column space of A (rank-revealing)."""
    if A.shape[1] == 0:
        return A
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > rcond * max(s[0], 1e-300)] if s.size else U[:, :0]


def _extend(Q: np.ndarray, *blocks: np.ndarray, rcond: float = 1e-9) -> np.ndarray:
    """:func:`_orth` of ``[Q, *blocks]`` for orthonormal Q: Q and the orthonormal basis of what the blocks'
    columns X add beyond span(Q). Only X's projected part is decomposed (a tall SVD of a few columns, not
    of the whole model's: on a long recording these SVDs had cost the analysis a sixth of its time)."""
    X = np.column_stack(blocks) if blocks else Q[:, :0]
    if X.shape[1] == 0:
        return Q
    Xp = X - Q @ (Q.T @ X)
    Xp -= Q @ (Q.T @ Xp)  # once more: one pass leaves ~eps |X| of span(Q), which a kept direction would carry
    U, s, _ = np.linalg.svd(Xp, full_matrices=False)
    top = max(1.0 if Q.shape[1] else 0.0, float(np.max(np.linalg.norm(X, axis=0))), 1e-300)
    return np.column_stack([Q, U[:, s > rcond * top]])


def _complement(X: np.ndarray, Q: np.ndarray, rcond: float = 1e-6) -> np.ndarray:
    """Orthonormal basis of what X adds beyond span(Q) (Q orthonormal). Directions that are mostly in
    span(Q) (kept fraction below sqrt(rcond)) count as absorbed."""
    return _complement_map(X, Q, rcond)[0]


def _complement_map(X: np.ndarray, Q: np.ndarray,
                    rcond: float = 1e-6) -> tuple[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]]:
    """:func:`_complement` B of X beyond span(Q), and the map from any linear image of X and Q to that
    of B: ``image(L @ X, L @ Q) == L @ B`` (B is X's columns less their part in Q, times a small matrix).
    So the nulls' projections on B come from their projections on X, computed once, and on Q."""
    if X.shape[1] == 0:
        return X, lambda LX, LQ: LX
    norm = np.linalg.norm(X, axis=0)
    nz = norm > 0
    Xn = X[:, nz] / norm[nz]
    A = Q.T @ Xn
    Xp = Xn - Q @ A
    # the basis from Xp's small Gram matrix, not a tall SVD: the same directions, since the kept ones
    # have s^2 = lam above rcond, far above the Gram matrix's rounding
    lam, V = np.linalg.eigh(Xp.T @ Xp)
    keep = lam > rcond
    R = V[:, keep] / np.sqrt(lam[keep])
    return Xp @ R, lambda LX, LQ: (LX[:, nz] / norm[nz] - LQ @ A) @ R


def complement_statistic(X: np.ndarray, Q: np.ndarray, y: np.ndarray) -> float:
    """``|B^T y|^2`` for B = :func:`_complement` (X, Q), from the columns' 3x3-sized Gram matrix instead of
    a tall SVD (the window refinement computes it thousands of times per analysis): with the projected
    columns Xp = U S V^T, B^T y = S^-1 V^T Xp^T y over the kept directions (s > 1e-3, i.e. s^2 > 1e-6)."""
    if X.shape[1] == 0:
        return 0.0
    norm = np.linalg.norm(X, axis=0)
    Xn = X[:, norm > 0] / norm[norm > 0]
    A = Q.T @ Xn  # Xp = Xn - Q A: its Gram matrix and Xp^T y without forming Xp
    lam, V = np.linalg.eigh(Xn.T @ Xn - A.T @ A)
    keep = lam > 1e-6
    u = V[:, keep].T @ (Xn.T @ y - A.T @ (Q.T @ y))
    return float(np.sum(u * u / lam[keep]))


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
    search: float = 0.0  # log of what searching (a window's edges) multiplied its single p by

    @property
    def df(self) -> int:
        return int(self.basis.shape[1])

    @property
    def evidence(self) -> float:
        """How well the columns explain the residual, for choosing between explanations once something
        is known to be there: the statistic (twice the log-likelihood gain) less 2 per parameter and
        twice the log of the search's multiplicity (a window's fitted edges), an information criterion.

        Which family a test belongs to and how large that family is decide whether anything is there
        (the corrected p); they say nothing about which of two significant explanations the data
        prefer, and at large statistics each test's null-calibrated scale moves p by orders of
        magnitude, so p cannot rank them either."""
        return self.statistic - 2.0 * self.df - 2.0 * self.search


def _score(tests: list[Test], y: np.ndarray, null: np.ndarray | None, extra: float = 0,
           m: Sequence[float] | None = None, null_proj: Sequence[np.ndarray] | None = None) -> None:
    """Statistic, null-calibrated chi-square p and Bonferroni p of every test on whitened residual y.

    ``null`` holds whitened null residuals (K, 3N) from simulations; the statistic's null distribution
    is taken as c chi2(nu) with the mean and variance of the simulated statistics (Satterthwaite): the
    scale c is the Bartlett factor, and a smaller nu carries the heavier tail that an uncertain noise
    estimate gives. nu is never above the test's df: a variance estimated from a few hundred nulls is
    itself uncertain (+-10 %), and a low draw's lighter tail made p several times too small far out (at
    1e-4, where the tests decide), while a high draw's heavier tail only cost a little power.
    ``extra`` counts other tests of the same round (the mains line search) in the correction; ``m``
    gives each test its own count instead (the dictionary's blocks, each by its prior weight).
    ``null_proj``: each test's ``null @ basis`` where the caller has it (:func:`_complement_map`)."""
    live = [t for t in tests if t.df > 0]
    counts = [len(live) + extra] * len(tests) if m is None else list(m)
    calibrated = null is not None and len(null) >= 20
    if calibrated and null_proj is None and live:
        # the nulls against every test's basis in one product: the nulls are the large operand, read once
        sims_all = null @ np.column_stack([t.basis for t in live])
        ends = np.cumsum([t.df for t in live])
        proj = iter(np.split(sims_all, ends[:-1], axis=1))
        null_proj = [next(proj) if t.df > 0 else None for t in tests]
    for k, (t, mt) in enumerate(zip(tests, counts)):
        if t.df == 0:
            continue
        t.statistic = float(np.sum((t.basis.T @ y) ** 2))
        c, nu = 1.0, float(t.df)
        if calibrated and null_proj is not None:
            sims = np.sum(null_proj[k] ** 2, axis=1)
            mean = float(np.mean(sims))
            t.bartlett = mean / t.df
            c = max(t.bartlett, 0.5)
            if len(null) >= 100:  # enough nulls to measure the spread as well as the scale
                c = max(float(np.var(sims, ddof=1)) / (2.0 * mean), 0.5)
                nu = float(np.clip(mean / c, 0.5, t.df))
                c = mean / nu
        t.p_value = float(stats.chi2.sf(t.statistic / c, nu))
        t.p_adjusted = float(min(1.0, t.p_value * mt))
        t.log_p = float(min(0.0, chi2_logsf(t.statistic / c, nu) + np.log(mt)))


def chi2_logsf(x: Any, df: Any) -> Any:
    """log of the chi-square tail, finite far beyond where scipy's underflows. There it is the asymptotic
    series of the upper incomplete gamma function, log Gamma(a, y) ~ (a - 1) log y - y + log(1 + (a - 1) / y
    + (a - 1)(a - 2) / y^2), a = df / 2, y = x / 2: exact in its leading terms, so tests with different
    degrees of freedom still rank correctly (a normal approximation compresses the far tail, and far
    more for few degrees of freedom than for many). Scalars give a float, arrays an array (elementwise;
    scipy.special directly: the window search evaluates thousands at once)."""
    xa, da = np.broadcast_arrays(np.asarray(x, float), np.asarray(df, float))
    with np.errstate(divide="ignore"):
        v = np.log(special.chdtrc(da, xa))
    far = ~np.isfinite(v)
    if np.any(far):
        a, y = da[far] / 2.0, xa[far] / 2.0
        series = 1.0 + (a - 1.0) / y + (a - 1.0) * (a - 2.0) / (y * y)
        v = np.array(v, float)
        v[far] = (a - 1.0) * np.log(y) - y + np.log(np.maximum(series, 1e-300)) - special.gammaln(a)
    return float(v) if v.ndim == 0 else v


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
    # a line shows inside the runs (their means are removed): below one cycle per typical run it is a
    # slow wander of the noise, not a line
    lengths = np.array([np.ptp(ctx.t[ctx.segment == k]) for k in np.unique(ctx.segment)])
    typical = float(np.median(lengths[lengths > 0])) if np.any(lengths > 0) else span
    lo = max(3.0 / max(span, 1e-9), 1.0 / max(typical, 1e-9))
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

