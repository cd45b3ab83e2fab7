"""One entry point for every calibration method: ``fit(recording, method) -> Calibration``.

It runs the accelerometer step once, the chosen magnetometer method, and fills the uncertainties
and the quality figures (model residuals, staged heading errors) in the same way for every method,
so that methods can be compared on the same recording.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from physics import errorsep as es
from physics import methods as comparison
from physics.calibration import STAGES, Calibration
from physics.frames import field_direction
from physics.heading import circular_mean_deg, error_summary, heading_error, levelled_field, reference_heading, wrap180
from physics.recording import Recording, RecordingError
from physics.sensor import LinearSensor
from physics.table import TableGeometry, base_rotation, platform_attitude

#: Methods by name; the first is the default.
METHODS = ("joint", "error-separation", "peak-picking", "ellipsoid", "deviation5", "two-axis", "maxmin")

#: A calibrated field whose magnitude varies more than this across a level turn means the data
#: are not what the model says (mixed units, angles in radians, a magnet on the table...).
MAX_FIELD_SPREAD = 0.03

_COMPARISON: dict[str, Callable[[Recording, es.Accel], Calibration]] = {
    "ellipsoid": comparison.ellipsoid,
    "deviation5": comparison.deviation5,
    "two-axis": comparison.two_axis,
    "maxmin": comparison.maxmin,
}


def fit(rec: Recording, method: str = "joint", bootstrap: int = 20, rng: np.random.Generator | None = None) -> Calibration:
    """Calibrate the unit of ``rec`` with ``method`` (one of :data:`METHODS`).

    ``bootstrap`` is the number of simulated repetitions used to give the stepwise methods their
    uncertainties (0 skips it); the joint method's come from its covariance.
    Raises :class:`RecordingError` for unusable data and ``InsufficientData`` when the recording's
    attitudes cannot determine a parameter the method needs.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    check_angles(rec)
    check_magnetometer(rec)
    acc = es.accelerometer(rec)
    if method in _COMPARISON:
        cal = _COMPARISON[method](rec, acc)
    elif method == "joint":
        cal = _joint(rec, acc)
    else:
        cal = _stepwise(rec, acc, "sinusoid" if method == "error-separation" else "pick", bootstrap, rng)
    cal.serial = rec.serial
    cal.method = method
    cal.notes = list(acc.notes) + cal.notes
    if acc.sensor is not None and "acc" not in cal.sigma and acc.fit is not None:
        cal.sigma["acc"] = acc.sigma()
    cal.quality = quality(rec, cal)
    spread = field_spread(rec, cal)
    if spread > MAX_FIELD_SPREAD:
        message = (f"calibrated field magnitude varies by {100 * spread:.1f} % across the level turn (expected under "
                   f"{100 * MAX_FIELD_SPREAD:.0f} %)")
        if method in ("joint", "error-separation"):
            # the nominal model fits any linear sensor: a misfit this large is the data's fault
            raise RecordingError(message + ": check that mx, my, mz are raw readings in one unit and that the "
                                 "table angles are degrees of the right axes")
        cal.notes.append(message + f": a limitation of the {method} method on this recording")
    return cal


def _stepwise(rec: Recording, acc: es.Accel, peak: str, bootstrap: int, rng: np.random.Generator | None) -> Calibration:
    mag, v, diag = es.error_separation(rec, acc, peak)
    inc, dec = es.field_in_lab(v, acc.tilt_deg)
    cal = Calibration(method="", mag=mag, acc=acc.sensor, inclination_deg=inc, declination_deg=dec,
                      base_tilt_deg=(float(acc.tilt_deg[0]), float(acc.tilt_deg[1])))
    cal.notes.append("sweeps used: " + "; ".join(diag["sweeps"]))  # type: ignore[arg-type]
    if bootstrap > 0:
        cal.sigma = _bootstrap_sigma(rec, acc, mag, v, peak, bootstrap, rng or np.random.default_rng(0))
    return cal


def _bootstrap_sigma(rec: Recording, acc: es.Accel, mag: LinearSensor, v: np.ndarray, peak: str, n: int,
                     rng: np.random.Generator) -> dict[str, object]:
    """Spread of the stepwise estimates over ``n`` recordings simulated from the fitted model and its residual noise."""
    R = es.rotations(rec)
    clean = mag.measure(np.einsum("nji,j->ni", R, v))
    noise = np.sqrt(np.mean((rec.mag - clean) ** 2, axis=0))
    draws = []
    for _ in range(n):
        fake = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t,
                                     clean + rng.normal(0.0, 1.0, clean.shape) * noise, rec.acc, rec.temp_c, rec.meta)
        m, vv, _ = es.error_separation(fake, acc, peak)
        inc, dec = es.field_in_lab(vv, acc.tilt_deg)
        draws.append(np.r_[m.angles_deg.ravel(), m.k, m.bias, inc, wrap180(dec - 180.0)])
    s = np.std(np.array(draws), axis=0, ddof=1)
    return {"angles_deg": s[:9].reshape(3, 3), "k": s[9:12], "bias": s[12:15],
            "inclination_deg": s[15], "declination_deg": s[16], "bootstrap": n}


def _joint(rec: Recording, acc: es.Accel) -> Calibration:
    """Joint least squares over every sample, started from the stepwise solution when there are sweeps."""
    notes = []
    try:
        _, v_start, _ = es.error_separation(rec, acc)
    except es.InsufficientData:
        v_start = None
        notes.append("no complete set of sweeps: joint fit started from a search over field directions")
    fit_ = es.joint_magnetometer(es.rotations(rec), rec.mag, v_start)
    ft = es.field_and_tilt(fit_, acc.fit)
    sigma: dict[str, object] = es.sensor_sigmas(fit_)
    sigma.update({"inclination_deg": ft["field_sigma"][0], "declination_deg": ft["field_sigma"][1],
                  "base_tilt_deg": ft["tilt_sigma"], "noise_lsb": fit_.noise})
    return Calibration(method="", mag=LinearSensor.from_matrix(fit_.M, fit_.b), acc=acc.sensor,
                       inclination_deg=float(ft["field"][0]), declination_deg=float(ft["field"][1]),
                       base_tilt_deg=(float(ft["tilt"][0]), float(ft["tilt"][1])), sigma=sigma, notes=notes)


# --------------------------------------------------------------------------------------------------
# Checks and quality figures
# --------------------------------------------------------------------------------------------------

def check_angles(rec: Recording) -> None:
    """Refuse table angles that look like radians (the format says degrees)."""
    for name in ("psi_t", "theta_t", "phi_t"):
        a = getattr(rec, name)
        span = float(np.ptp(a))
        if 1.0 < span <= 2 * np.pi + 1e-6 and np.all(np.abs(a) <= 2 * np.pi + 1e-6):
            raise RecordingError(f"column {name}: spans only {span:.3f}: table angles must be in degrees, "
                                 "these look like radians")


def check_magnetometer(rec: Recording) -> None:
    """Refuse a magnetometer axis whose reading never changes: no method can calibrate it (its
    sensitivity would be 0 and every heading 0/0)."""
    dead = [f"{name} (always {col[0]:g})" for name, col in zip(("mx", "my", "mz"), rec.mag.T) if len(col) and np.ptp(col) == 0]
    if dead:
        raise RecordingError(f"column{'s' if len(dead) > 1 else ''} {', '.join(dead)}: the reading never changes over "
                             "the recording: a dead or disconnected magnetometer axis?")


def _level(rec: Recording) -> np.ndarray:
    return (np.abs(rec.theta_t) < 0.01) & (np.abs(rec.phi_t) < 0.01)


def _fill_field(rec: Recording, cal: Calibration, f_b: np.ndarray) -> None:
    """Give a method that does not estimate the field an I and D from its own corrected readings."""
    if np.isfinite(cal.declination_deg) and np.isfinite(cal.inclination_deg):
        return
    lev = _level(rec)
    use = lev if lev.any() else np.ones(len(rec), bool)
    psi = cal.heading(rec.mag[use], f_b[use])
    if not np.isfinite(cal.declination_deg):
        cal.declination_deg = circular_mean_deg(rec.psi_t[use] - psi)
    if not np.isfinite(cal.inclination_deg):
        h = levelled_field(cal.body_field(rec.mag[use], f_b[use]), f_b[use])
        cal.inclination_deg = float(np.degrees(np.median(np.arctan2(h[:, 2], np.hypot(h[:, 0], h[:, 1])))))


def quality(rec: Recording, cal: Calibration) -> dict[str, object]:
    """Model residuals (LSB) and in-sample heading errors (deg) of a calibration on its recording.

    Residuals: raw readings minus what the nominal model with this calibration's M, b, I, D and
    tilt predicts. Heading errors: max over the level samples at each stage of the paper's Fig. 5,
    and over the tilted samples (pitch and roll within 60 deg), against ``psi_t - D``.
    """
    f_b = es.specific_force(rec, cal.acc)
    _fill_field(rec, cal, f_b)
    v_base = base_rotation(cal.base_tilt_deg).T @ field_direction(cal.inclination_deg, cal.declination_deg)
    pred = cal.mag.measure(np.einsum("nji,j->ni", es.rotations(rec), v_base))
    rms = np.sqrt(np.mean((rec.mag - pred) ** 2, axis=0)).tolist()
    if cal.heading_model and cal.heading_model["kind"] == "two_axis":
        rms[2] = None  # the two-axis compass does not use z_m
    # the paper averages the readings at each position (eq. 5): score per-pose means, not single samples
    mean = pose_means(rec)
    mag, f_b = mean.mag, es.specific_force(mean, cal.acc)
    ref = mean.psi_t - cal.declination_deg
    lev = _level(mean)
    staged: dict[str, float | None] = {}
    for stage in STAGES:
        if lev.any():
            e = heading_error(cal.heading(mag[lev], f_b[lev], stage), ref[lev])
            staged[stage] = float(np.max(np.abs(e)))
        else:
            staged[stage] = None
    tilted = ~lev & (np.abs(wrap180(mean.theta_t)) <= 60.0) & (np.abs(wrap180(mean.phi_t)) <= 60.0)
    if tilted.any():
        e = heading_error(cal.heading(mag[tilted], f_b[tilted]), ref[tilted])
        staged["tilted_full"] = float(np.max(np.abs(e)))
    return {"residual_rms_lsb": rms, "heading_error_deg": staged, "samples": len(rec), "poses": len(mean)}


def _pose_groups(rec: Recording) -> np.ndarray:
    """Pose index of each sample: a pose is a run of consecutive samples with one step and encoder angles."""
    key = np.round(es.table_angles(rec), 3)
    change = np.r_[True, np.any(key[1:] != key[:-1], axis=1) | (rec.step[1:] != rec.step[:-1])]
    return np.cumsum(change) - 1


def pose_means(rec: Recording) -> Recording:
    """One row per pose (a run of consecutive samples with the same step and encoder angles), averaged."""
    group = _pose_groups(rec)
    change = np.r_[True, group[1:] != group[:-1]]
    n = np.bincount(group)

    def avg(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return np.bincount(group, x) / n
        return np.column_stack([np.bincount(group, x[:, j]) / n for j in range(x.shape[1])])

    first = np.flatnonzero(change)
    return Recording.from_arrays(avg(rec.t), rec.step[first], avg(rec.psi_t), avg(rec.theta_t), avg(rec.phi_t),
                                 avg(rec.mag), None if rec.acc is None else avg(rec.acc),
                                 None if rec.temp_c is None else avg(rec.temp_c), rec.meta)


def field_spread(rec: Recording, cal: Calibration) -> float:
    """Relative spread (max - min) / median of the calibrated field magnitude over the level samples (0 when not applicable)."""
    lev = _level(rec)
    if cal.heading_model is not None or lev.sum() < 3:
        return 0.0  # heading-only models do not claim a calibrated vector
    norm = np.linalg.norm(cal.body_field(rec.mag[lev], es.specific_force(rec, cal.acc)[lev]), axis=1)
    return float((norm.max() - norm.min()) / np.median(norm))


def evaluate(rec: Recording, cal: Calibration, max_tilt_deg: float = 60.0) -> dict[str, object]:
    """Heading error of ``cal`` on a recording made for checking it (the ``evaluate`` procedure).

    Per pose (readings averaged), the compass heading from the calibrated magnetometer and
    accelerometer against the platform's true magnetic heading from the encoder angles, the
    calibration's base tilt and its D. Returns the per-pose errors with each pose's own noise (the
    standard error of its mean heading) and max/RMS level and tilted; ``*_noise_deg`` is the typical
    pose noise, below which an error cannot be resolved by this recording.
    """
    mean = pose_means(rec)
    f_b = es.specific_force(mean, cal.acc)
    geometry = TableGeometry(base_tilt_deg=tuple(cal.base_tilt_deg))  # type: ignore[arg-type]
    C = platform_attitude(mean.psi_t, mean.theta_t, mean.phi_t, geometry)
    h_mean = cal.heading(mean.mag, f_b)
    err = heading_error(h_mean, reference_heading(C, cal.declination_deg))
    # each sample's heading about its pose's mean, for the pose's standard error
    group = _pose_groups(rec)
    h = cal.heading(rec.mag, es.specific_force(rec, cal.acc))
    dev = wrap180(h - h_mean[group])
    n = np.bincount(group)
    sigma = np.sqrt(np.bincount(group, dev * dev) / np.maximum(n - 1, 1) / n)
    lev = _level(mean)
    tilted = ~lev & (np.abs(wrap180(mean.theta_t)) <= max_tilt_deg) & (np.abs(wrap180(mean.phi_t)) <= max_tilt_deg)
    out: dict[str, object] = {"poses": np.column_stack([mean.psi_t, mean.theta_t, mean.phi_t]).tolist(),
                              "error_deg": err.tolist(), "sigma_deg": sigma.tolist()}
    for name, mask in (("level", lev), ("tilted", tilted)):
        s = error_summary(err[mask]) if mask.any() else {"max": None, "rms": None}
        out[f"{name}_max_deg"], out[f"{name}_rms_deg"] = s["max"], s["rms"]
        out[f"{name}_noise_deg"] = float(np.median(sigma[mask])) if mask.any() else None
    return out
