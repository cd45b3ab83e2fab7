"""One entry point for every calibration method: ``fit(recording, method) -> Calibration``.

It runs the accelerometer step once, the chosen magnetometer method, and fills the uncertainties
and the quality figures (model residuals, staged heading errors) in the same way for every method,
so that methods can be compared on the same recording.

Bad samples (a checksummed but wrong reading, a brown-out's zeros) are rejected before and during
the fit, in two stages, and every dropped row is listed in ``quality["rejected_rows"]``:

1. Model-free screen (every method): a row whose three axes read exactly 0, or whose reading is
   more than :data:`REJECT_SIGMA` robust sigmas from the median of its pose (the consecutive samples
   at one set of encoder angles) and either :data:`GROSS_FRACTION` of the field amplitude or alone
   there (a run of at most :data:`BAD_RUN` rows with good rows of the pose on both sides: a flipped
   bit). Breakdown point: half the samples of each pose (the median and the MAD break down at 50 %);
   sigma is pooled over the recording by the MAD.
2. Model-based rejection (``joint`` and ``error-separation``): iteratively reweighted least squares
   with 0/1 weights on the whitened residuals (a hard-redescending, "skipped" estimator): fit, drop
   every row whose residual on any axis is more than :data:`REJECT_SIGMA` robust sigmas (MAD of the
   kept rows' residuals) and GROSS_FRACTION of that axis's k (or alone in its pose, as above), refit,
   until the kept set no longer
   changes; dropped rows are re-tested each round, so a row wrongly dropped early comes back. When more than :data:`MODEL_BREAKDOWN` of
   the rows look bad the fit is restarted once from its best (1 - MODEL_BREAKDOWN) of rows (a
   least-trimmed-squares concentration step); if that still leaves more than MODEL_BREAKDOWN bad,
   the data as a whole do not follow the model (not a few bad rows) and the usual checks decide.
   Breakdown point: MODEL_BREAKDOWN (20 %) of the rows.

Fewer than :data:`MIN_GOOD_FRACTION` good rows, or good rows that no longer hold the attitudes a
method needs, are refused with that reason.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from itertools import permutations, product
from typing import Any, Callable

import numpy as np
from scipy.ndimage import median_filter

from physics import errorsep as es
from physics import methods as comparison
from physics.calibration import STAGES, Calibration
from physics.frames import field_direction
from physics.heading import circular_mean_deg, error_summary, heading_error, levelled_field, reference_heading, wrap180
from physics.recording import SKIPPED_AT_KEY, SKIPPED_KEY, Recording, RecordingError, file_row
from physics.sensor import LinearSensor
from physics.table import TableGeometry, base_rotation, platform_attitude

#: Methods by name; the first is the default.
METHODS = ("joint", "error-separation", "peak-picking", "ellipsoid", "deviation5", "two-axis", "maxmin", "twelve-position")

#: A calibrated field whose magnitude varies more than this across a level turn means the data
#: are not what the model says (mixed units, angles in radians, a magnet on the table...).
MAX_FIELD_SPREAD = 0.03

#: A row further than this many robust sigmas from its pose's median, or from the fitted model, is
#: rejected, if it is also more than GROSS_FRACTION of the axis's field amplitude (k) off. Garbage is
#: thousands of sigmas off; 8 sigma keeps Gaussian noise in, and the amplitude floor keeps the physics
#: the discrepancy analysis looks for (a settling lag, mains pickup: tens of LSB) in the data.
REJECT_SIGMA = 8.0
GROSS_FRACTION = 0.05
#: ... except a row off by REJECT_SIGMA that comes alone or in a run of at most this many, with rows of
#: its own pose on both sides that are not: physics changes over a hold (a settling lag at its start,
#: mains pickup in every row), while a flipped bit garbles one reading (64 LSB is 20 sigma and under 5 %
#: of most units' k, and one such row in a hold moves the hold's mean by more than its noise). A longer
#: run is something that happened (a magnet brought near for a moment), which the analysis looks at.
BAD_RUN = 3
#: The model-based rejection may drop at most this fraction of the rows: its breakdown point.
MODEL_BREAKDOWN = 0.2
#: Refuse when fewer than this fraction of the rows remain good.
MIN_GOOD_FRACTION = 0.5
#: A magnetometer count at the int16 limit is a clipped reading (the compass sets its saturation bit
#: there): the field was beyond the sensor's range, and the reading says only "at least this".
SATURATED_LSB = 32767.0
#: Rounds of the model-based rejection (fit, reject, refit); it usually settles in two.
MAX_REJECT_ROUNDS = 6
#: Methods that reject rows inconsistent with their own fitted model (stage 2 above).
ROBUST_METHODS = ("joint", "error-separation")
#: Methods that calibrate from the magnetometer alone, without the table's angles (a hand-held recording).
ANGLE_FREE_METHODS = ("ellipsoid", "maxmin")

_COMPARISON: dict[str, Callable[[Recording, es.Accel], Calibration]] = {
    "ellipsoid": comparison.ellipsoid,
    "deviation5": comparison.deviation5,
    "two-axis": comparison.two_axis,
    "maxmin": comparison.maxmin,
    "twelve-position": comparison.twelve_position,
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
    if not rec.has_angles and method not in ANGLE_FREE_METHODS:
        # (the joint fit's least squares on empty angles ended in "SVD did not converge")
        raise RecordingError(f"method {method} needs the table's angles, and this recording has none (psi_t, theta_t "
                             "and phi_t are empty: a hand-held recording); methods " + " and ".join(ANGLE_FREE_METHODS)
                             + " calibrate from the magnetometer alone (without the sensor-to-body misalignment)")
    skipped = int(rec.meta.get(SKIPPED_KEY, 0) or 0)  # malformed rows the reader dropped (--skip-bad-rows)
    if skipped > len(rec):
        # a calibration from a sliver of the file is not the file's (a shuffled file: 1065 of 1080 rows "malformed",
        # time going backwards, and a calibration from the 15 left, 30 times worse, with no trace of it)
        raise RecordingError(f"{skipped} of the file's {skipped + len(rec)} rows were malformed and skipped, more than "
                             "were kept: not a calibration of this recording; look at why (rows out of time order, "
                             "another layout: --mapping) rather than skip them")
    check_angles(rec)
    check_magnetometer(rec)
    rejected = screen_rows(rec)
    _require_good(rec, rejected)
    _require_clustered(rec, rejected)
    work = _kept(rec, rejected)
    if rejected:
        check_magnetometer(work)

    def run(r: Recording) -> Calibration:
        acc = es.accelerometer(r)
        if method in _COMPARISON:
            c = _COMPARISON[method](r, acc)
        elif method == "joint":
            c = _joint(r, acc)
        else:
            c = _stepwise(r, acc, "sinusoid" if method == "error-separation" else "pick", bootstrap, rng)
        c.notes = list(acc.notes) + c.notes
        if acc.sensor is not None and "acc" not in c.sigma and acc.fit is not None:
            c.sigma["acc"] = acc.sigma()
        return c

    too_many: str | None = None
    try:
        if method in ROBUST_METHODS:
            cal, rejected, too_many = _fit_rejecting(rec, rejected, run)
            work = _kept(rec, rejected)
        else:
            cal = run(work)
    except (es.InsufficientData, RecordingError) as e:
        if not rejected or str(e).startswith("too few good samples"):
            raise
        if _same_refusal(run, rec, e):  # the rows dropped are not why (65 of 57,203 were blamed for a missing sweep)
            raise
        raise _too_few(rec, rejected, e) from None
    cal.serial = rec.serial
    cal.method = method
    cal.quality = quality(work, cal)
    skipped_at = [int(x) for x in str(rec.meta.get(SKIPPED_AT_KEY, "")).split(",") if x.strip()]
    cal.quality.update(rejected_rows=rejected_rows(rec, rejected), rejected=len(rejected), samples_total=len(rec),
                       skipped_malformed=skipped, skipped_malformed_rows=skipped_at)
    if skipped:
        where = f" (data rows {index_list(skipped_at)}, 0-based)" if skipped_at else ""
        cal.notes.append(f"{skipped} malformed row(s) of the file were skipped before the fit (--skip-bad-rows){where}; "
                         f"{len(rec)} were read")
    if rec.acc is not None:
        empty = np.flatnonzero(~np.all(np.isfinite(rec.acc), axis=1))
        if 0 < len(empty) < len(rec):  # (all empty: a recording without an accelerometer, which its notes say)
            cal.notes.append(f"{len(empty)} row(s) have no accelerometer reading (empty cells: data rows "
                             f"{index_list(sorted(file_row(rec, int(i)) for i in empty))}, 0-based): the accelerometer "
                             "is calibrated from the others, the magnetometer from every row")
    if np.isfinite(cal.inclination_deg) and abs(cal.inclination_deg) > NEAR_POLE_DEG:
        horizontal = np.cos(np.radians(cal.inclination_deg))
        cal.notes.append(f"the field is {90 - abs(cal.inclination_deg):.1f} deg from vertical: its horizontal part, which "
                         f"heading is measured against, is {100 * horizontal:.1f} % of it, so heading and D are "
                         f"{1 / horizontal:.0f} times as sensitive to every reading's error as on the magnetic equator: "
                         "large heading errors here are the place's, not the calibration's")
    hand = handedness_note(cal.mag.M_o, "magnetometer")
    if hand:
        cal.notes.append(hand)
    if rejected:
        cal.notes.append(f"dropped {len(rejected)} of {len(rec)} rows as bad samples ({_reason_counts(rejected)}): "
                         f"data rows {index_list(sorted(file_row(rec, i) for i in rejected))} (0-based)")
    spread = field_spread(work, cal)
    misfit = misfit_over_noise(work, cal)
    if spread > MAX_FIELD_SPREAD or misfit > MAX_MISFIT:
        message = (f"calibrated field magnitude varies by {100 * spread:.1f} % across the level turn (expected under "
                   f"{100 * MAX_FIELD_SPREAD:.0f} %)") if spread > MAX_FIELD_SPREAD else (
                   f"the fitted model leaves {misfit:.0f} times the noise the poses show (their samples' scatter)")
        if work.has_angles:
            means = pose_means(work)
            found = better_reading(np.column_stack([means.psi_t, means.theta_t, means.phi_t]), means.mag)
            if found is not None:
                here, best, how = found
                raise RecordingError(f"{message}: the table angles fit the nominal model far better read {how} (the "
                                     f"pose means leave {here:.3g} LSB rms as given, {best:.3g} so read). {ANGLE_ADVICE}")
        if spread > MAX_FIELD_SPREAD and method in ROBUST_METHODS:
            # the nominal model fits any linear sensor: a misfit this large is the data's fault
            if too_many:
                message += f"; {too_many}"
            raise RecordingError(message + ": check that mx, my, mz are raw readings in one unit and that the "
                                 "table angles are degrees of the right axes, or whether more samples are garbage than "
                                 f"the fit can drop (up to half of each pose's samples, {100 * MODEL_BREAKDOWN:.0f} % of "
                                 "the rows off the model)")
        if spread > MAX_FIELD_SPREAD:
            why = f": a limitation of the {method} method on this recording"
        elif method not in ROBUST_METHODS:  # a comparison method's simpler model misfits a clean recording too
            why = (f": the {method} method's model leaves out part of what the joint fit models (the sensor's "
                   "alignment to the body, or more), so this residual is the method's, not the recording's; the "
                   "joint fit (--method joint) says whether the recording holds physics its model leaves out")
        else:
            why = (": physics the model leaves out (compasscal analyze names it), or readings and angles that do not "
                   "belong together; the calibration is not to be trusted")
        cal.notes.append(message + why)
    return cal


def handedness_note(M_o: np.ndarray, sensor: str) -> str | None:
    """What to check when the fitted sensor axes are not those of a right-handed triad set along the body
    axes (PHYSICS.md: the right solution has M_o with a positive diagonal), else None. A fit that sees
    the data through a mirror fits as well as the right one: with psi_t and theta_t counted the other way
    it left 3 LSB and said 0.03 deg, and every heading with that calibration was 179 deg off."""
    M_o = np.asarray(M_o, float)
    det = float(np.linalg.det(M_o))
    away = [i for i in range(3) if M_o[i, i] < 0]
    if det > 0 and not away:
        return None
    axes = "xyz"
    said = [f"{axes[i]}_m points {np.degrees(np.arccos(np.clip(M_o[i, i], -1.0, 1.0))):.1f} deg from {axes[i]}_b"
            for i in away]
    return (f"the {sensor}'s fitted axes " + ("form a left-handed set (det M_o = " + f"{det:.3f})" if det < 0 else
                                             "do not lie along the body axes")
            + (" and " + ", ".join(said) if said else "") + ": an axis wired inverted or two axes swapped in the unit, "
            "or two of the table's angles counted the other way (then every heading with this calibration is about "
            "180 deg off, though the fit looks perfect); check the unit's wiring and the recording's angle "
            "convention (PHYSICS.md) before trusting it")


#: A fit whose residual is this many times the noise within the poses is no fit of this recording: the
#: angles read in another convention are looked for, else it is said (swapped psi_t and phi_t columns left
#: 1149 LSB rms against 3 LSB of noise, and the level turn, one pose under that reading, showed no spread).
MAX_MISFIT = 10.0


def pose_noise(rec: Recording) -> np.ndarray | None:
    """Each magnetometer axis's noise: the pooled scatter of the samples of the poses held 3 samples or
    more about their means (LSB); None with fewer than 10 such samples (a recording on the move)."""
    group = pose_groups(rec)
    held = np.bincount(group)[group] >= 3
    if held.sum() < 10:
        return None
    scatter = rec.mag[held] - pose_means(rec).mag[group[held]]
    dof = held.sum() - len(np.unique(group[held]))
    return np.sqrt(np.sum(scatter ** 2, axis=0) / max(dof, 1))


def misfit_over_noise(rec: Recording, cal: Calibration) -> float:
    """The largest axis's model residual RMS over its noise (the pooled scatter of the samples of the
    poses held 3 samples or more about their means); 0 when there are no such poses or no model."""
    noise = pose_noise(rec)
    if noise is None or cal.heading_model is not None:
        return 0.0
    group = pose_groups(rec)
    held = np.bincount(group)[group] >= 3
    resid = np.sqrt(np.nanmean(model_residuals(rec, cal)[held] ** 2, axis=0))
    ratio = resid / np.maximum(noise, 0.5)  # (at least half a count: quantised readings of a quiet sensor)
    return float(np.max(ratio)) if np.all(np.isfinite(ratio)) else 0.0


# --------------------------------------------------------------------------------------------------
# Table angles in another convention
# --------------------------------------------------------------------------------------------------

#: Beyond this inclination (deg) the field's horizontal part is under 17 % of it: a fit says heading is
#: poorly defined there (a simulated unit at I = 88 deg showed 0.97 deg of level error, and one at 90 deg
#: 170 deg with D "250 +- 45", without a word).
NEAR_POLE_DEG = 80.0
#: Another reading of the table angles must leave this many times less residual to be named the likely
#: one: no physics is undone by negating, swapping or rescaling an angle column.
CONVENTION_GAIN = 10.0
#: What to do about it, said with every such refusal.
ANGLE_ADVICE = ("PHYSICS.md's angles are degrees, psi_t about z (outer), theta_t about y (middle), phi_t about x "
                "(inner), right-handed; re-export them so, or read the file through a mapping (--mapping: "
                "[columns], [angles] unit, negate, sequence)")
_ANGLE_NAMES = ("psi_t", "theta_t", "phi_t")
#: better_reading tries each reading on at most this many pose means, spread over the recording: enough to
#: tell conventions apart by a factor of ten (500 and 2,000 name the same readings), where 95 fits of
#: 57,000 (a file of continuous optical angles, every sample its own pose) had taken over ten minutes.
BETTER_READING_POSES = 500


def better_reading(ang: np.ndarray, mag: np.ndarray) -> tuple[float, float, str] | None:
    """(rms residual as given, rms residual so read, the reading) when the table angles ``ang`` (N, 3:
    psi_t, theta_t, phi_t in deg) of readings ``mag`` (N, 3) fit the nominal model ``raw = M R^T v + b``
    :data:`CONVENTION_GAIN` times better read another way: in radians, in another column order, or with
    signs flipped (95 readings, a joint fit each: give it hold means, not every sample). The simplest
    reading is named, or the equally simple ones the attitudes cannot tell apart. None otherwise, or
    when the angles as given cannot determine the fit."""
    if len(mag) > BETTER_READING_POSES:  # a recording of continuous attitudes has a "pose" per sample
        keep = np.linspace(0, len(mag) - 1, BETTER_READING_POSES).round().astype(int)
        ang, mag = ang[keep], mag[keep]
    grid = np.array(es._sphere_starts(400))
    one = np.ones((len(grid), len(mag), 1))

    def misfit(a: np.ndarray) -> float:
        R = platform_attitude(a[:, 0], a[:, 1], a[:, 2])
        try:
            es.check_identifiable(R, grid[0], "magnetometer", "")
            # M and b are linear given the field's direction: every direction of a fine grid at once, then
            # the joint fit from the best of them (one start instead of the fit's twelve: 95 readings to try)
            X = np.concatenate([np.einsum("nji,kj->kni", R, grid), one], axis=2)
            coef = np.linalg.solve(np.einsum("kni,knj->kij", X, X) + 1e-9 * np.eye(4), np.einsum("kni,nc->kic", X, mag))
            sse = np.sum((mag[None] - X @ coef) ** 2, axis=(1, 2))
            f = es.fit_vector_sensor(R, mag, [grid[int(np.argmin(sse))]])
        except (es.InsufficientData, np.linalg.LinAlgError, ValueError):
            return np.inf
        return float(np.sqrt(np.mean((mag - np.einsum("nji,j->ni", R, f.v) @ f.M.T - f.b) ** 2)))

    here = misfit(ang)
    if not np.isfinite(here):
        return None
    tried: list[tuple[float, int, str]] = []  # (residual, how many changes, what they are)
    for scale, unit in ((1.0, ""), (180.0 / np.pi, "in radians")):
        for order in permutations(range(3)):
            for signs in product((1.0, -1.0), repeat=3):
                said = [unit] if unit else []
                if order != (0, 1, 2):
                    said.append("with the columns read as " + ", ".join(_ANGLE_NAMES[i] for i in order))
                flipped = [_ANGLE_NAMES[order[k]] for k in range(3) if signs[k] < 0]
                if flipped:
                    said.append(", ".join(flipped) + " negated")
                if said:
                    changes = int(scale != 1.0) + int(order != (0, 1, 2)) + len(flipped)
                    tried.append((misfit(ang[:, order] * np.array(signs) * scale), changes, "; ".join(said)))
    least = min(m for m, _, _ in tried)
    if not least * CONVENTION_GAIN < here:
        return None
    # the attitudes of a symmetric plan come out alike under several readings: name the simplest of those
    alike = [t for t in tried if t[0] <= 1.1 * least]
    fewest = min(c for _, c, _ in alike)
    simplest = sorted((t for t in alike if t[1] == fewest), key=lambda t: t[0])
    how = simplest[0][2] if len(simplest) == 1 else (
        "in one of these ways, which this recording's attitudes cannot tell apart: "
        + " | ".join(t[2] for t in simplest[:8]) + (f" | {len(simplest) - 8} more" if len(simplest) > 8 else ""))
    return here, simplest[0][0], how


# --------------------------------------------------------------------------------------------------
# Bad samples
# --------------------------------------------------------------------------------------------------

def _robust_sigma(x: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """Per-column noise from the median absolute deviation (50 % breakdown), never below ``floor``."""
    return np.maximum(1.4826 * np.median(np.abs(x), axis=0), floor)


#: A "pose" of fewer samples than this is a reference's sample-and-hold (a few repeats of one reading while
#: the unit moves), whose scatter about its median is not the readings' noise.
SAMPLE_HOLD_MAX = 10


#: The reason of a row that repeats the row before exactly, its time stamp too.
WRITTEN_TWICE = "repeats the row before exactly (same time stamp and readings): a sample written twice"


def screen_rows(rec: Recording) -> dict[int, str]:
    """Model-free screen of the magnetometer and accelerometer rows: {sample index: reason} of the
    ones to drop (a row goes as a whole: its attitude and its field were read together).

    A row is dropped when all three axes of either sensor read exactly 0 (no sensor in a field or under
    gravity does; a brown-out or a dropped frame does), when a magnetometer axis reads the int16 limit
    (:data:`SATURATED_LSB`: a clipped reading, which a whole pose shares), or when one axis is more than REJECT_SIGMA
    robust sigmas and GROSS_FRACTION of its amplitude (half the span of the pose medians, about k)
    from the median of its pose (poses of at least 3 samples; sigma is the recording's MAD about the
    pose medians, at least a count where the readings are whole counts; one pose alone has no amplitude,
    so only lone rows and short runs go there). Rows in no hold are compared with their neighbours
    instead (:func:`_screen_moving`). One corrupted accelerometer row in a hundred moves the levelling, and with it the
    heading, by tenths of a degree.
    """
    out: dict[int, str] = {}
    sensors = [("m", "magnetometer", rec.mag)]
    if rec.acc is not None and np.all(np.isfinite(rec.acc)):
        sensors.append(("a", "accelerometer", rec.acc))
    for _, name, x in sensors:
        for i in np.flatnonzero(np.all(x == 0.0, axis=1)):
            out.setdefault(int(i), f"all three {name} axes read exactly 0 (a brown-out or a dropped reading)")
    for i in np.flatnonzero(np.any(np.abs(rec.mag) >= SATURATED_LSB, axis=1)):
        a = int(np.argmax(np.abs(rec.mag[i])))
        out.setdefault(int(i), f"saturated: m{'xyz'[a]} = {rec.mag[i, a]:g} is at the int16 limit "
                               "(a field beyond the sensor's range: a strong magnet near the unit?)")
    if len(rec) == 0:
        return out
    # a row that repeats the one before exactly, time stamp and readings: a logger that wrote a sample twice
    # (a file of every row twice was fitted with its noise taken for 30 % less, and no word of it)
    same = np.r_[False, (np.diff(rec.t) == 0) & np.all(np.diff(rec.mag, axis=0) == 0, axis=1)]
    if rec.acc is not None:
        acc = np.nan_to_num(rec.acc, nan=np.inf)
        same[1:] &= np.all(acc[1:] == acc[:-1], axis=1)
    for i in np.flatnonzero(same):
        out.setdefault(int(i), WRITTEN_TWICE)
    group = pose_groups(rec)
    _screen_frozen(rec, group, out)
    _screen_stuck(rec, group, out)
    _screen_angle_glitches(rec, out)
    usable = np.ones(len(rec), bool)
    usable[list(out)] = False
    n = np.bincount(group[usable], minlength=group.max() + 1)
    multi = usable & (n[group] >= 3)
    _screen_moving(rec, usable & ~multi, out)
    if not multi.any():
        return out
    for prefix, _, x in sensors:
        med = np.full((group.max() + 1, 3), np.nan)
        for g in np.unique(group[multi]):
            med[g] = np.median(x[multi & (group == g)], axis=0)
        dev = x - med[group]
        amplitude = 0.5 * (np.nanmax(med, axis=0) - np.nanmin(med, axis=0))
        # whole counts resolve nothing under a count: when half of a hold's readings sit on the two
        # counts by its median, their MAD says 0.7 LSB and ordinary noise would look 9 sigma off
        counts = np.all(x[multi] == np.round(x[multi]), axis=0)
        # nor below the noise from one held sample to the next: poses of a few repeats of one reading (an
        # optical reference's sample-and-hold) have a MAD of nothing, and ordinary readings of a hand-held
        # recording were dropped as 3810 sigma off (0.03 LSB against 24 of sample-to-sample noise)
        # (from the short "poses" only, a reference's few repeats: a step is bad when either of its rows is,
        # so over a table recording's holds this floor broke down at 30 % garbage, not 50 %, and 40 % random
        # accelerometer rows were all kept for a 26-deg calibration; a hold of many samples has its own MAD)
        idx = np.flatnonzero(multi & (n[group] < SAMPLE_HOLD_MAX))
        steps = np.diff(x[idx], axis=0)[np.diff(idx) == 1]
        step_sigma = _robust_sigma(steps, np.zeros(3)) / np.sqrt(2.0) if len(steps) >= 10 else np.zeros(3)
        sigma = _robust_sigma(dev[multi], np.maximum.reduce([np.full(3, 2e-4) * amplitude,
                                                             np.where(counts, 1.0, 1e-12), step_sigma]))
        z = np.abs(dev) / sigma
        # gross needs an amplitude, i.e. two poses (a run's first hold alone has none: lone rows only)
        gross = np.any((z > REJECT_SIGMA) & (np.abs(dev) > GROSS_FRACTION * amplitude) & (amplitude > 0), axis=1)
        off = multi & np.any(z > REJECT_SIGMA, axis=1)
        done = np.zeros(len(rec), bool)
        done[list(out)] = True
        lone = off & isolated_runs(off | done, group)
        for i in np.flatnonzero(multi & (gross | lone)):
            a = int(np.argmax(z[i]))
            out.setdefault(int(i), f"{prefix + 'xyz'[a]} = {x[i, a]:g} is {abs(dev[i, a]):.1f} LSB ({z[i, a]:.0f} sigma) "
                                   f"from the median of its pose's samples ({med[group[i], a]:g})")
    return out


#: Readings whose noise from one sample to the next (within a hold) is above this (counts, every
#: magnetometer axis) do not repeat on all six axes by chance (under 1 in 10^4 pairs) ...
FROZEN_NOISE = 1.5
#: ... and a run of at least this many repeats is a frozen sensor, not a reference's sample-and-hold
#: (a reading held over two or three of the reference's samples is honest).
FROZEN_RUN = 4


def _screen_frozen(rec: Recording, group: np.ndarray, out: dict[int, str]) -> None:
    """Rows that repeat the previous row exactly on every magnetometer and accelerometer axis, in runs of
    :data:`FROZEN_RUN` or more (``group``: :func:`pose_groups`) (a frozen sensor, or a logger repeating its last frame), go, the first of each
    run kept, where the readings' noise makes an exact repeat improbable (:data:`FROZEN_NOISE`; a quiet
    quantised sensor, or noise-free readings, repeat honestly). A stretch of them across a move put the old
    attitude's reading at the new one: 40 % of such rows made the heading error 3-4 times the clean fit's."""
    if rec.acc is None or not np.all(np.isfinite(rec.acc)) or len(rec) < 12:
        return
    same = np.r_[False, np.all(rec.mag[1:] == rec.mag[:-1], axis=1) & np.all(rec.acc[1:] == rec.acc[:-1], axis=1)]
    runs = [r for r in consecutive_runs(same) if len(r) >= FROZEN_RUN]
    if not runs:
        return
    steps = np.diff(rec.mag, axis=0)[group[1:] == group[:-1]]
    moved = steps[np.any(steps != 0.0, axis=1)]  # the repeats themselves say nothing of the noise
    if len(moved) < 10 or not np.all(_robust_sigma(moved, np.zeros(3)) / np.sqrt(2.0) > FROZEN_NOISE):
        return
    for i in np.concatenate(runs):
        out.setdefault(int(i), "repeats the previous row exactly on all six axes (mx..az), which this noise does not "
                               "do by chance: a frozen sensor or a repeated frame")


def _screen_angle_glitches(rec: Recording, out: dict[int, str]) -> None:
    """Rows inside a hold whose table angles differ from both neighbours' (which agree) while the reading
    matches theirs (:func:`_bad_angles`): a bad encoder reading, model-free, so that every method drops it.
    The joint and error-separation fits found them off the model; the twelve-position method, which has no
    such step, took 1 % of rows with psi_t 180 deg off for positions of their own (1 deg of level error)."""
    if not rec.has_angles or len(rec) < 3:
        return
    ang = np.column_stack([rec.psi_t, rec.theta_t, rec.phi_t])
    agree = np.all(np.abs(wrap180(ang[2:] - ang[:-2])) <= 1e-3, axis=1)
    own = np.any(np.abs(wrap180(ang[1:-1] - ang[:-2])) > 1e-3, axis=1)
    rows = np.flatnonzero(agree & own) + 1
    if not len(rows):
        return
    noise = pose_noise(rec)
    for i in rows:
        reason = _bad_angles(rec, int(i), noise)
        if reason:
            out.setdefault(int(i), reason)


#: One axis repeating one reading for this many rows in a row or more, where its noise makes a repeat
#: improbable (:data:`FROZEN_NOISE`: each repeat then has a chance of 0.19 at most, twelve rows 1e-8), is stuck.
STUCK_RUN = 12


def _screen_stuck(rec: Recording, group: np.ndarray, out: dict[int, str]) -> None:
    """Rows where one axis of either sensor repeats one reading :data:`STUCK_RUN` times or more in a row
    while the others go on (``group``: :func:`pose_groups`) go, the first of each run kept, where that axis's
    noise (its steps within poses outside such runs) makes the repeats improbable. A magnetometer axis stuck
    for 200 rows across several poses moved the tilted heading by 0.5 deg with nothing dropped, and the
    twelve-position method kept the stuck rows of a pose and dropped its good ones. An axis whose readings
    repeat in most rows is the logger's rate above the sensor's, not a fault, and is left alone."""
    cols = [(f"m{'xyz'[j]}", rec.mag[:, j]) for j in range(3)]
    if rec.acc is not None and np.all(np.isfinite(rec.acc)):
        cols += [(f"a{'xyz'[j]}", rec.acc[:, j]) for j in range(3)]
    # the whole magnetometer still while the table turns is a dead sensor, which the sweeps' own check
    # names ("sweep about z ...: mx, my and mz do not change"), not three stuck axes to fit around
    dead = np.r_[False, np.all(rec.mag[1:] == rec.mag[:-1], axis=1)]
    for name, x in cols:
        same = np.r_[False, x[1:] == x[:-1]] & (~dead if name[0] == "m" else True)
        # rows another screen took (a frozen sensor's, all six axes repeating) do not make a run of one axis
        runs = [r for r in consecutive_runs(same) if sum(int(i) not in out for i in r) >= STUCK_RUN - 1]
        if not runs:
            continue
        in_run = np.zeros(len(x), bool)
        in_run[np.concatenate(runs)] = True
        if in_run.mean() > 0.5:
            continue
        steps = np.diff(x)[(group[1:] == group[:-1]) & ~in_run[1:]]
        sigma = float(_robust_sigma(steps, 0.0)) / np.sqrt(2.0) if len(steps) >= 10 else 0.0
        if sigma <= FROZEN_NOISE:
            continue
        for r in runs:
            for i in r:
                out.setdefault(int(i), f"{name} repeats one reading ({x[i]:g}) for {len(r) + 1} rows in a row, which its "
                                       f"noise ({sigma:.2g} LSB per sample) does not do by chance: a stuck axis")


#: Rows of a hold tried as the centre of its densest cluster (:func:`scattered_rows`), at most about this many.
CLUSTER_CENTRES = 200


def scattered_rows(rec: Recording) -> np.ndarray:
    """Rows of a hold (3 samples or more) outside the densest cluster of its readings (a mask): within
    GROSS_FRACTION of the sensor's scale (its largest amplitude, or its readings' typical size) of the hold's
    row that has the most others that close, on all three axes of both sensors. Where more than half of a
    hold's rows are garbage its median is one of them and :func:`screen_rows` cannot tell (at 70 % random
    rows it dropped none of them, and the comparison methods calibrated the garbage to 180 deg of error); a
    handful of good readings still lie together, while random ones scatter over the sensor's whole range.
    Only counted, to refuse for the right reason: a hold split between two real fields (a magnet brought
    near) would lose its smaller part."""
    out = np.zeros(len(rec), bool)
    if len(rec) == 0:
        return out
    group = pose_groups(rec)  # a pose is a run of consecutive rows
    holds = [r for r in np.split(np.arange(len(rec)), np.flatnonzero(np.diff(group)) + 1) if len(r) >= 3]
    if not holds:
        return out
    sensors = [rec.mag] + ([rec.acc] if rec.acc is not None and np.all(np.isfinite(rec.acc)) else [])
    tol = []
    for x in sensors:
        # one scale for every axis, the sensor's: an axis that hardly turns (no sweep about y) has a span
        # of a few counts, under its noise
        med = np.array([np.median(x[rows], axis=0) for rows in holds])
        scale = max(0.5 * float(np.ptp(med, axis=0).max()), float(np.median(np.linalg.norm(x, axis=1))))
        tol.append(max(GROSS_FRACTION * scale, 1.0))
    for rows in holds:
        centres = rows[::max(1, len(rows) // CLUSTER_CENTRES)]  # a long hold: its cluster from a sample of rows
        close = np.ones((len(centres), len(rows)), bool)
        for x, tl in zip(sensors, tol):
            close &= np.all(np.abs(x[centres][:, None, :] - x[rows][None, :, :]) <= tl, axis=2)
        out[rows] = ~close[int(np.argmax(close.sum(axis=1)))]
    return out


#: Samples taken on the move (a scan, or a recording without table angles) are compared with the median
#: of this many neighbours of their own step: two bad rows in a row cannot move it.
MOVING_WINDOW = 5
#: Neighbouring samples more than this far apart in any table angle (deg) are no neighbours: single-sample
#: holds 45 deg apart are poses of their own, not a turn sampled on the move.
MOVING_STEP_DEG = 5.0
#: ... and go only when that far from it, as a share of the field's amplitude: no turn of a table or a hand
#: moves the field by half its amplitude between neighbouring samples, while a garbage reading (random
#: int16) mostly lies beyond it. Real hand-held files jump by 5-15 % between samples (a fast spin, a
#: filter's steps), which the holds' GROSS_FRACTION would have dropped by the hundred.
MOVING_GROSS_FRACTION = 0.5


def _screen_moving(rec: Recording, moving: np.ndarray, out: dict[int, str]) -> None:
    """The screen of :func:`screen_rows` for magnetometer rows in no hold (``moving``: a scan's, or every
    row of a hand-held recording, whose angles change from sample to sample; runs of them end where the
    table jumps by more than :data:`MOVING_STEP_DEG` between samples): a row goes when one axis is
    more than REJECT_SIGMA robust sigmas and :data:`MOVING_GROSS_FRACTION` of the amplitude from the median
    of its :data:`MOVING_WINDOW` neighbours (in place on ``out``). Without it one garbage reading in a
    hand-held file bent the ellipsoid until its fit refused the file for want of attitudes. (The
    accelerometer is left alone here: on the move it reads the motion's accelerations too.)"""
    left = moving.copy()
    x, angles = rec.mag, es.table_angles(rec)
    for _ in range(3):  # again without the rows that went: two garbage rows side by side pull a median
        idx = np.flatnonzero(left)
        kept = np.ones(len(rec), bool)
        kept[list(out)] = False
        between = np.cumsum(kept)  # rows dropped before are skipped over; anything else in between ends a run
        jump = np.abs(wrap180(np.diff(angles[idx], axis=0))) > MOVING_STEP_DEG  # (NaN: no angles)
        cut = ((rec.step[idx[1:]] != rec.step[idx[:-1]]) | (between[idx[1:] - 1] - between[idx[:-1]] > 0)
               | np.any(jump, axis=1))
        runs = [r for r in np.split(idx, np.flatnonzero(cut) + 1) if len(r) >= MOVING_WINDOW]
        if not runs:
            return
        rows = np.concatenate(runs)
        ref = np.concatenate([median_filter(x[r], size=(MOVING_WINDOW, 1), mode="mirror") for r in runs])  # (at a run's end: not itself twice)
        dev = x[rows] - ref
        # the field's amplitude, the largest axis's (an axis that hardly turns, z in a level spin, has none
        # of its own, and its ordinary jitter would pass for garbage against it), between the 1 % and 99 %
        # points: where three of five neighbours are garbage, the median is garbage too
        lo, hi = np.quantile(ref, [0.01, 0.99], axis=0)
        amplitude = np.full(3, 0.5 * float(np.max(hi - lo)))
        counts = np.all(x[rows] == np.round(x[rows]), axis=0)
        z = np.abs(dev) / _robust_sigma(dev, np.maximum(2e-4 * amplitude, np.where(counts, 1.0, 1e-12)))
        bad = np.flatnonzero(np.any((z > REJECT_SIGMA) & (np.abs(dev) > MOVING_GROSS_FRACTION * amplitude)
                                    & (amplitude > 0), axis=1))
        if not len(bad):
            return
        for k in bad:
            a = int(np.argmax(z[k]))
            out.setdefault(int(rows[k]), f"m{'xyz'[a]} = {x[rows[k], a]:g} is {abs(dev[k, a]):.1f} LSB ({z[k, a]:.0f} "
                                         f"sigma) from the median of its {MOVING_WINDOW} neighbouring samples ({ref[k, a]:g})")
        left[rows[bad]] = False


def consecutive_runs(mask: np.ndarray) -> list[np.ndarray]:
    """The indices of ``mask``'s True rows, split into runs of consecutive rows."""
    idx = np.flatnonzero(mask)
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if len(idx) else []


def isolated_runs(off: np.ndarray, group: np.ndarray, longest: int = BAD_RUN, at_edges: bool = False) -> np.ndarray:
    """The rows of mask ``off`` that come alone or in runs of at most ``longest``, with a row of their own
    group (pose) on both sides that is not off (a mask). ``at_edges``: a run at its group's first or last
    row counts too, with a row of its group that is not off on its other side."""
    out = np.zeros(len(off), bool)
    n = len(off)
    for run in consecutive_runs(off):
        a, b = int(run[0]) - 1, int(run[-1]) + 1
        g = group[run[0]]
        if len(run) > longest or group[run[-1]] != g:
            continue
        good_a = a >= 0 and group[a] == g and not off[a]
        good_b = b < n and group[b] == g and not off[b]
        edge_a = a < 0 or group[a] != g  # the run starts its group
        edge_b = b >= n or group[b] != g  # the run ends its group
        if (good_a and good_b) or (at_edges and ((edge_a and good_b) or (good_a and edge_b))):
            out[run] = True
    return out


def model_residuals(rec: Recording, cal: Calibration) -> np.ndarray:
    """Raw readings minus what the nominal model with ``cal``'s M, b, I, D and base tilt predicts (N, 3), LSB."""
    v_base = base_rotation(cal.base_tilt_deg).T @ field_direction(cal.inclination_deg, cal.declination_deg)
    return rec.mag - cal.mag.measure(np.einsum("nji,j->ni", es.rotations(rec), v_base))


def _fit_rejecting(rec: Recording, screened: dict[int, str], run: Callable[[Recording], Calibration]
                   ) -> tuple[Calibration, dict[int, str], str | None]:
    """Stage 2 of the module docstring: fit, drop rows off the model, refit until the kept set settles.

    Returns the calibration, every rejected row with its reason, and (when the model-based rejection
    was abandoned because too many rows disagree) a sentence saying so for the refusal that follows.
    """
    candidates = _good(rec, screened)
    group = pose_groups(rec)
    noise = pose_noise(rec.select(candidates))

    def settle(keep: np.ndarray, cal: Calibration) -> tuple[np.ndarray, Calibration, np.ndarray, np.ndarray, str | None]:
        trimmed = False
        for _ in range(MAX_REJECT_ROUNDS):
            r = model_residuals(rec, cal)
            sigma = _robust_sigma(r[keep], 1e-4 * np.abs(cal.mag.k))
            z = np.abs(r) / sigma
            # whitened distance, counted only where the error is also gross or the row off alone in its
            # pose (module docstring)
            lone = isolated_runs(~candidates | np.any(z > REJECT_SIGMA, axis=1), group)
            counted = (np.abs(r) > GROSS_FRACTION * np.abs(cal.mag.k)) | lone[:, None]
            d = np.where(counted, z, np.minimum(z, REJECT_SIGMA)).max(axis=1)
            bad = candidates & (d > REJECT_SIGMA)
            if bad.sum() > MODEL_BREAKDOWN * candidates.sum():
                if trimmed:
                    return candidates, run(rec.select(candidates)), r, z, (
                        f"{int(bad.sum())} of {len(rec)} rows disagree with the fitted model by more than "
                        f"{REJECT_SIGMA:g} sigma, more than the {100 * MODEL_BREAKDOWN:.0f} % of bad rows "
                        "the robust fit can drop")
                # a fit pulled by many bad rows: restart from its best rows (a least-trimmed-squares step)
                trimmed = True
                new_keep = candidates & (d <= np.quantile(d[candidates], 1.0 - MODEL_BREAKDOWN))
            else:
                new_keep = candidates & ~bad
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
            try:
                cal = run(rec.select(keep))
            except (es.InsufficientData, RecordingError) as e:  # the dropped rows took attitudes the fit needs
                raise _too_few(rec, {**screened, **{int(i): "off the fitted model" for i in np.flatnonzero(candidates & ~keep)}},
                               e) from None
        return keep, cal, r, z, None

    keep, cal, r, z, too_many = settle(candidates.copy(), run(rec.select(candidates)))
    if too_many is not None:
        return cal, screened, too_many
    for _ in range(MAX_POSE_RESTARTS):
        restart = _without_pulling_pose(rec, keep, cal, group, noise, run)
        if restart is None:
            break
        keep, cal, r, z, too_many = settle(*restart)
        if too_many is not None:
            return cal, screened, too_many
    out = dict(screened)
    for i in np.flatnonzero(candidates & ~keep):
        a = int(np.argmax(z[i]))
        out[int(i)] = _bad_angles(rec, int(i), noise) or (
            f"{'m' + 'xyz'[a]} = {rec.mag[i, a]:g} is {abs(r[i, a]):.1f} LSB ({z[i, a]:.0f} sigma) off the fitted model")
    _require_good(rec, out)
    return cal, out, None


def _bad_angles(rec: Recording, i: int, noise: np.ndarray | None) -> str | None:
    """The reason of a row off the model whose table angles, not its reading, are wrong: inside a hold
    (its two neighbours at one attitude), with angles of its own but a reading within 8 sigma of the
    neighbours' (a corrupted psi_t was blamed on my: "my = -2161.8 is 2030 LSB off the fitted model")."""
    if noise is None or i == 0 or i == len(rec) - 1:
        return None
    before, here, after = np.column_stack([rec.psi_t[i - 1:i + 2], rec.theta_t[i - 1:i + 2], rec.phi_t[i - 1:i + 2]])
    if not (np.allclose(before, after) and rec.step[i - 1] == rec.step[i] == rec.step[i + 1]):
        return None
    off = np.abs(wrap180(here - before)) > 1e-3
    near = np.abs(rec.mag[i] - 0.5 * (rec.mag[i - 1] + rec.mag[i + 1])) <= REJECT_SIGMA * np.maximum(noise, 0.5)
    if not off.any() or not near.all():
        return None
    said = ", ".join(f"{n} = {here[k]:g}" for k, n in enumerate(("psi_t", "theta_t", "phi_t")) if off[k])
    return f"table angle(s) {said} differ from both neighbours' in its hold, whose reading it shares: a bad angle reading"


#: A fit whose residuals' robust sigma is this many times the poses' own noise may be pulled by one
#: pose gone wrong (a magnetised tool beside it, a reading offset for its whole hold) ...
PULLED = 3.0
#: ... and is, when the fit without that pose leaves this many times less: the pose then fits its own
#: noise nowhere, and the rows' rule (REJECT_SIGMA, GROSS_FRACTION) judges its rows against the better fit.
UNBENT = 3.0
#: Poses the fit may be restarted without, one at a time.
MAX_POSE_RESTARTS = 3


def _without_pulling_pose(rec: Recording, keep: np.ndarray, cal: Calibration, group: np.ndarray,
                          noise: np.ndarray | None, run: Callable[[Recording], Calibration]
                          ) -> tuple[np.ndarray, Calibration] | None:
    """A start for the row rejection without the one pose that bends the whole fit, or None.

    The rows' rule measures distance in the residuals' robust sigma, which a fit pulled by a whole pose
    inflates everywhere: an upside-down pose 400 LSB off on x left x's sigma at 40 LSB against 3 LSB of
    noise, and that pose at 7.5 of those sigmas, so it stayed and the heading was 2 deg off. Where the
    residuals are PULLED times the noise the held poses show, the fit is tried without its worst pose
    (largest mean residual in sigmas); it is the start only when that leaves UNBENT times less. Physics
    the model leaves out spreads over the poses, and leaving one out changes little (real recordings:
    no restart)."""
    if noise is None:
        return None
    floor = 1e-4 * np.abs(cal.mag.k)
    r = model_residuals(rec, cal)
    sigma = _robust_sigma(r[keep], floor)
    if not np.any(sigma > PULLED * np.maximum(noise, 0.5)):
        return None
    poses = np.unique(group[keep])
    means = np.array([np.abs(r[keep & (group == p)].mean(axis=0)) / sigma for p in poses])
    worst = poses[int(np.argmax(means.max(axis=1)))]
    trial = keep & (group != worst)
    try:
        fitted = run(rec.select(trial))
    except (es.InsufficientData, RecordingError):  # the pose holds an attitude the fit needs
        return None
    if not np.any(sigma > UNBENT * _robust_sigma(model_residuals(rec, fitted)[trial], floor)):
        return None
    return trial, fitted


def _good(rec: Recording, rejected: dict[int, str]) -> np.ndarray:
    """The rows not rejected (a mask)."""
    keep = np.ones(len(rec), bool)
    keep[list(rejected)] = False
    return keep


def _kept(rec: Recording, rejected: dict[int, str]) -> Recording:
    return rec.select(_good(rec, rejected)) if rejected else rec


def _require_good(rec: Recording, rejected: dict[int, str]) -> None:
    """Refuse when fewer than MIN_GOOD_FRACTION of the rows are good, naming that as the reason."""
    good = len(rec) - len(rejected)
    if rejected and good < MIN_GOOD_FRACTION * len(rec):
        raise _too_few_good(f"{len(rejected)} of {len(rec)} rows are bad ({_reason_counts(rejected)}; first at sample "
                            f"indices {index_list(sorted(rejected))})", good)


def _too_few_good(bad: str, good: int) -> RecordingError:
    """The refusal of a recording with fewer than MIN_GOOD_FRACTION good rows (``bad`` says which are bad)."""
    return RecordingError(f"too few good samples remain: {bad}, leaving {good}; the fit needs at least "
                          f"{100 * MIN_GOOD_FRACTION:.0f} % good rows. Check the compass's connection and supply, "
                          "then record again")


def _require_clustered(rec: Recording, rejected: dict[int, str]) -> None:
    """Refuse, naming too few good samples as the reason, when more than MIN_GOOD_FRACTION of the rows are bad
    counting the ones only :func:`scattered_rows` sees (holds mostly of garbage, whose medians are garbage too)."""
    bad = scattered_rows(rec)
    bad[list(rejected)] = True
    if bad.sum() > (1.0 - MIN_GOOD_FRACTION) * len(rec):
        holds = np.unique(pose_groups(rec)[bad])
        raise _too_few_good(f"{int(bad.sum())} of {len(rec)} rows lie apart from the other readings of their hold (in "
                            f"{len(holds)} holds: more than half of many holds' samples are garbage, so their medians "
                            "are too)", len(rec) - int(bad.sum()))


def _same_refusal(run: Callable[[Recording], Calibration], rec: Recording, e: Exception) -> bool:
    """Whether the fit refuses every row of ``rec`` (the bad ones kept) as it refused the good ones (``e``:
    the same kind of refusal, by its words up to the first number): then the dropped rows are not the reason."""
    try:
        run(rec)
    except (es.InsufficientData, RecordingError) as again:
        words = lambda x: re.split(r"\d", str(x), maxsplit=1)[0]  # noqa: E731
        return type(again) is type(e) and words(again) == words(e)
    except (ValueError, np.linalg.LinAlgError):  # the bad rows broke the fit another way: they are why
        return False
    return False


def _too_few(rec: Recording, rejected: dict[int, str], e: Exception) -> Exception:
    """The refusal of a fit that the remaining good rows no longer support, naming the bad rows as the reason."""
    return type(e)(f"too few good samples remain: after dropping {len(rejected)} bad row(s) of {len(rec)} "
                   f"({_reason_counts(rejected)}): {e}")


def reason_kind(reason: str) -> str:
    """The kind of a dropped row's reason, as the notes count them: all zeros, saturated, written twice,
    frozen, stuck axis, bad table angles, off its pose, off the model."""
    if reason.startswith("all three"):
        return "all zeros"
    if reason.startswith("repeats the previous row"):
        return "frozen"
    if reason == WRITTEN_TWICE:
        return "written twice"
    if reason.endswith("a stuck axis"):
        return "stuck axis"
    if reason.startswith("saturated"):
        return "saturated"
    if reason.startswith("table angle"):
        return "bad table angles"
    return "off their pose's median" if "median of its pose" in reason else "off the fitted model"


def _reason_counts(rejected: dict[int, str]) -> str:
    kinds: dict[str, int] = {}
    for reason in rejected.values():
        kinds[reason_kind(reason)] = kinds.get(reason_kind(reason), 0) + 1
    return ", ".join(f"{n} {k}" for k, n in kinds.items())


def index_list(idx: list[int], limit: int = 20) -> str:
    """Sample indices for a note: the first ``limit``, then how many more."""
    return ", ".join(map(str, idx[:limit])) + (f" and {len(idx) - limit} more" if len(idx) > limit else "")


def rejected_rows(rec: Recording, rejected: dict[int, str]) -> list[dict[str, Any]]:
    """The calibration JSON's list of dropped rows: sample index (into the recording as read), its
    file's 0-based data row ``row`` (which counts malformed rows a reader skipped: `file_row`), t, step
    label, reason."""
    return [{"index": i, "row": file_row(rec, i), "t": float(rec.t[i]), "step": str(rec.step[i]), "reason": rejected[i]}
            for i in sorted(rejected)]


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
    if fit_.scatter > 1.0:
        notes.append(f"the pose means scatter {fit_.scatter:.3g} times as much as the samples' noise predicts (an error "
                     "the same for a whole pose: the table's axes, a reading rounded to whole counts): the "
                     f"uncertainties are widened by {np.sqrt(fit_.scatter):.2g} to cover it")
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

def radian_like(angles: Sequence[np.ndarray]) -> tuple[int, float] | None:
    """The column of ``angles`` (psi, theta, phi in degrees by the format) that says they are radians, and
    its span: every angle within +-2 pi and one turning by more than a radian. None when they may be
    degrees (a table turning by less than a degree and a half in every axis has nothing to fit anyway).
    Empty (NaN) cells are left out. The fit and the importers' mappings judge by this one rule."""
    fin = [np.asarray(a, float)[np.isfinite(a)] for a in angles]
    spans = [float(np.ptp(a)) if a.size else 0.0 for a in fin]
    if max(spans, default=0.0) > 1.0 and all(np.all(np.abs(a) <= 2 * np.pi + 1e-6) for a in fin):
        i = int(np.argmax(spans))
        return i, spans[i]
    return None


def check_angles(rec: Recording) -> None:
    """Refuse table angles that look like radians (the format says degrees)."""
    found = radian_like([rec.psi_t, rec.theta_t, rec.phi_t])
    if found is not None:
        i, span = found
        raise RecordingError(f"column {('psi_t', 'theta_t', 'phi_t')[i]}: every table angle is within +-2 pi and it "
                             f"spans only {span:.3f}: table angles must be in degrees, these look like radians")


def _never_changing(names: Sequence[str], x: np.ndarray) -> list[str]:
    """The columns of ``x`` whose readings (empty cells aside) never change, named with their one value."""
    cols = [col[np.isfinite(col)] for col in x.T]
    return [f"{name} (always {col[0]:g})" for name, col in zip(names, cols) if len(col) > 1 and np.ptp(col) == 0]


def check_magnetometer(rec: Recording) -> None:
    """Refuse a magnetometer axis whose reading never changes: no method can calibrate it (its
    sensitivity would be 0 and every heading 0/0); and an accelerometer axis that never changes while
    the table tilts."""
    if len(rec) < 2:  # (one row "never changes" either: say what is wrong with the file)
        raise RecordingError(f"the recording has {len(rec)} data row(s): a calibration needs readings at many "
                             "attitudes (the calibrate plan records 18 poses of 60 samples)")
    dead = _never_changing(("mx", "my", "mz"), rec.mag)
    if dead:
        raise RecordingError(f"column{'s' if len(dead) > 1 else ''} {', '.join(dead)}: the reading never changes over "
                             "the recording: a dead or disconnected magnetometer axis?")
    if rec.acc is None or not rec.has_angles or np.ptp(rec.theta_t) + np.ptp(rec.phi_t) == 0:
        return  # (a level turn leaves an accelerometer axis nearly still: nothing to judge it by)
    # an accelerometer axis that never changes while the table tilts was calibrated as a sensitivity of
    # 6.5e-14 counts per g, every tilted heading 180 deg off, and no word of it
    dead = _never_changing(("ax", "ay", "az"), rec.acc)
    if dead:
        raise RecordingError(f"column{'s' if len(dead) > 1 else ''} {', '.join(dead)}: the reading never changes while "
                             "the table tilts: a dead or disconnected accelerometer axis? (to calibrate the magnetometer "
                             "alone, leave the accelerometer's columns empty)")


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
    rms = np.sqrt(np.mean(model_residuals(rec, cal) ** 2, axis=0)).tolist()
    if cal.heading_model and cal.heading_model["kind"] == "two_axis":
        rms[2] = None  # the two-axis compass does not use z_m
    # the paper averages the readings at each position (eq. 5): score per-pose means, not single samples
    mean = pose_means(rec)
    mag, f_b = mean.mag, es.specific_force(mean, cal.acc)
    ref = mean.psi_t - cal.declination_deg
    lev = _level(mean)
    # PHYSICS.md: the heading error as its maximum absolute value and as RMS
    staged: dict[str, float | None] = {}
    staged_rms: dict[str, float | None] = {}
    for stage in STAGES:
        if lev.any():
            e = heading_error(cal.heading(mag[lev], f_b[lev], stage), ref[lev])
            staged[stage], staged_rms[stage] = float(np.max(np.abs(e))), float(np.sqrt(np.mean(e * e)))
        else:
            staged[stage] = staged_rms[stage] = None
    tilted = ~lev & (np.abs(wrap180(mean.theta_t)) <= 60.0) & (np.abs(wrap180(mean.phi_t)) <= 60.0)
    if tilted.any():
        e = heading_error(cal.heading(mag[tilted], f_b[tilted]), ref[tilted])
        staged["tilted_full"], staged_rms["tilted_full"] = float(np.max(np.abs(e))), float(np.sqrt(np.mean(e * e)))
    return {"residual_rms_lsb": rms, "heading_error_deg": staged, "heading_error_rms_deg": staged_rms,
            "samples": len(rec), "poses": len(mean)}


def pose_groups(rec: Recording) -> np.ndarray:
    """Pose index of each sample: a pose is a run of consecutive samples with one step and encoder angles."""
    key = np.round(es.table_angles(rec), 3)
    change = np.r_[True, np.any(key[1:] != key[:-1], axis=1) | (rec.step[1:] != rec.step[:-1])]
    return np.cumsum(change) - 1


def pose_means(rec: Recording) -> Recording:
    """One row per pose (a run of consecutive samples with the same step and encoder angles), averaged."""
    group = pose_groups(rec)
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


#: Level samples taken on the move (a scan) are smoothed over this many in a row before their spread is
#: taken: a systematic variation is slow in heading, a sample's noise is not.
SPREAD_SMOOTHING = 9


def field_spread(rec: Recording, cal: Calibration) -> float:
    """Relative spread (max - min) / median of the calibrated field magnitude over the level turn (0 when
    not applicable): over each level pose's median, and samples outside poses (a scan) smoothed over
    :data:`SPREAD_SMOOTHING` in a row. What the check looks for (mixed units, angles in radians, a magnet
    on the table) is systematic; one sample's noise is not: 5 LSB on a unit of 1000 LSB per field is 0.5 %
    of the field per sample, and the 480 level samples of the default plan span six times that, so
    the samples' own spread refused half such units (within PHYSICS.md's ranges) until 2026-11-28."""
    lev = _level(rec)
    if cal.heading_model is not None or lev.sum() < 3:
        return 0.0  # heading-only models do not claim a calibrated vector
    norm = np.linalg.norm(cal.body_field(rec.mag[lev], es.specific_force(rec, cal.acc)[lev]), axis=1)
    group = pose_groups(rec)[lev]
    n = np.bincount(group)
    held = n[group] >= 3
    values = [float(np.median(norm[group == g])) for g in np.unique(group[held])]
    loose = norm[~held]
    if len(loose) >= SPREAD_SMOOTHING:
        loose = median_filter(loose, size=SPREAD_SMOOTHING, mode="nearest")
    values += loose.tolist()
    return float((max(values) - min(values)) / np.median(values))


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
    group = pose_groups(rec)
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
