"""The calibration methods we compare error separation against (PHYSICS.md, seeds 001, 003, 004).

Every method has the signature ``NAME(rec, acc) -> Calibration``: ``rec`` is the unit's recording and
``acc`` the accelerometer calibration the caller computed once (shared by every method). Each returns
a :class:`~physics.calibration.Calibration` whose magnetometer model follows the nominal model
``m = diag(k) M_o h_b + b``; the two methods that are not purely linear add a ``heading_model``.
The caller fills ``quality`` and ``sigma``; a method sets I and D only when it estimates them.

- :func:`ellipsoid`   seed 001: algebraic quadric fit, ``h_b = E (m - B)`` with E symmetric.
- :func:`deviation5`  seed 004: ellipsoid, then ``A + B sin + C cos + D sin 2 + E cos 2`` at level.
- :func:`two_axis`    seed 003 (Cho and Park): x-y max/min over a level turn, h_z from the extended dip.
- :func:`maxmin`      per-axis max/min over all poses: hard iron and scale only.
- :func:`twelve_position` seed 002: each body axis down and up, each at two headings 180 deg apart.

A recording that cannot support a method raises :class:`~physics.errorsep.InsufficientData` naming
what is missing and which parameters it leaves undetermined.
"""

from __future__ import annotations

import numpy as np

from physics.calibration import Calibration
from physics.errorsep import Accel, InsufficientData, coverage_deg, specific_force, table_angles
from physics.frames import rot_x, rot_y
from physics.heading import circular_mean_deg, magnetic_heading, pitch_roll, reference_heading, wrap180
from physics.recording import Recording
from physics.sensor import LinearSensor
from physics.table import platform_attitude

AXES = "xyz"

#: Table angles within this of zero count as level (deg); the encoders resolve 0.001 deg.
LEVEL_TOL_DEG = 0.01
#: Poses are told apart by their table angles rounded to this many decimals (as errorsep.find_sweeps).
POSE_DECIMALS = 2
#: The readings' smallest principal spread must be at least this fraction of their largest (not planar).
QUADRIC_MIN_THICKNESS = 0.05
#: The quadric is refused when its second-smallest singular value is within this factor of the
#: smallest (the minimiser is not unique: several quadrics fit the readings equally well) ...
QUADRIC_SEPARATION = 10.0
#: ... or is this small relative to the largest (noise-free data on too few curves).
QUADRIC_RCOND = 1e-9
#: deviation5 needs at least this many distinct level headings covering at least this much of the turn.
DEV5_MIN_HEADINGS = 5
DEV5_MIN_COVERAGE_DEG = 180.0
#: two_axis: a level turn has at least this many headings covering at least this much of the circle.
TWO_AXIS_MIN_HEADINGS = 4
TWO_AXIS_MIN_COVERAGE_DEG = 270.0
#: two_axis: tilted poses used for the extended dip (Theorem 1 divides by cos(pitch) cos(roll)).
TWO_AXIS_TILT_RANGE_DEG = (10.0, 70.0)
#: maxmin: each body axis must come within this angle of the field and of its opposite. The extreme
#: reading is then at least k cos(tol), so k is at most 1 - cos(tol) (1.5 % at 10 deg) too small.
MAXMIN_TOL_DEG = 10.0
#: maxmin without table angles (a hand-held recording): the same check judged from the readings alone, the
#: field's direction at each axis's largest and smallest reading; looser, as single readings and a scale taken
#: from the same extremes are noisier (the public hand-held logs come within 15 deg, a level spin's z axis 45).
MAXMIN_FREE_TOL_DEG = 20.0
#: twelve_position: a face counts when one body axis is within this of the vertical (deg).
TWELVE_FACE_TOL_DEG = 2.0


# --------------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------------

def _poses(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct poses (table angles rounded as find_sweeps does) and each sample's pose index."""
    keys, inverse = np.unique(np.round(angles, POSE_DECIMALS), axis=0, return_inverse=True)
    return keys, inverse.ravel()


def _pose_means(inverse: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (N, ...) over the samples of each pose; per-pose means keep noise out of max/min."""
    n = int(inverse.max()) + 1
    sums = np.zeros((n,) + values.shape[1:])
    np.add.at(sums, inverse, values)
    counts = np.bincount(inverse, minlength=n).reshape((n,) + (1,) * (values.ndim - 1))
    return sums / counts


def _level_poses(rec: Recording) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Level samples (theta_t, phi_t ~ 0) grouped by heading.

    Returns (indices of the level samples, their distinct psi_t in [0, 360), each level sample's
    index into those headings).
    """
    ang = table_angles(rec)
    level = (np.abs(wrap180(ang[:, 1])) < LEVEL_TOL_DEG) & (np.abs(wrap180(ang[:, 2])) < LEVEL_TOL_DEG)
    idx = np.flatnonzero(level)
    psi = np.round(ang[idx, 0] % 360.0, POSE_DECIMALS) % 360.0
    headings, inverse = np.unique(psi, return_inverse=True)
    return idx, headings, inverse.ravel()


def _base(method: str, rec: Recording, acc: Accel, mag: LinearSensor, notes: list[str]) -> Calibration:
    return Calibration(method=method, mag=mag, acc=acc.sensor, base_tilt_deg=tuple(float(t) for t in acc.tilt_deg),
                       serial=rec.serial, notes=notes)


# --------------------------------------------------------------------------------------------------
# Ellipsoid fitting (seed 001)
# --------------------------------------------------------------------------------------------------

def fit_ellipsoid(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre B and symmetric E with ``|E (m - B)| = 1`` for readings ``mag`` (N, 3), by algebraic fit.

    The general quadric ``[x^2, y^2, z^2, 2xy, 2xz, 2yz, 2x, 2y, 2z, 1] . p = 0`` is fitted as the
    right singular vector of the design matrix with the smallest singular value (readings centred and
    scaled first, so the ten columns are comparable). Raises InsufficientData when the minimiser is not
    unique (readings on a plane, e.g. only a level turn) or the quadric is not an ellipsoid.
    """
    m = np.asarray(mag, dtype=float)
    c0 = m.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((m - c0) ** 2, axis=1))))
    if not s > 0:
        raise InsufficientData("ellipsoid: the readings do not change at all; centre (bias) and shape "
                               "matrix are undetermined")
    # Readings in a plane (a level turn, or any single sweep) fit a flat quadric (the plane squared) to
    # second order in the noise, better than the true ellipsoid: refuse them before the singular values.
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov((m - c0).T)), 0.0))
    if spread[0] < QUADRIC_MIN_THICKNESS * spread[2]:
        raise InsufficientData(
            "ellipsoid: the readings lie in a plane (thickness "
            f"{spread[0] / spread[2]:.2g} of their extent; e.g. only a level turn or a single sweep), so the "
            "10 quadric coefficients, and with them the centre (bias) and the shape matrix (sensitivities, "
            "soft iron), are undetermined. Add attitudes that tilt the unit: sweeps about the table's x and y axes.")
    x, y, z = ((m - c0) / s).T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z, np.ones_like(x)])
    _, sv, vt = np.linalg.svd(design, full_matrices=False)
    if sv.size < 10 or sv[-2] < QUADRIC_RCOND * sv[0] or sv[-2] < QUADRIC_SEPARATION * sv[-1]:
        raise InsufficientData(
            "ellipsoid: the readings do not determine the field ellipsoid (they lie on too few curves, e.g. "
            "a level turn and one sweep), so the 10 quadric coefficients, and with "
            "them the centre (bias) and the shape matrix (sensitivities, soft iron), are undetermined "
            f"(singular values: smallest {sv[-1]:.3g}, next {sv[-2]:.3g}, largest {sv[0]:.3g}). "
            "Add attitudes that tilt the unit: sweeps about the table's x and y axes.")
    p = vt[-1]
    A = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    centre = -np.linalg.solve(A, p[6:9])
    Q = A / (centre @ A @ centre - p[9])  # (m - B)^T Q (m - B) = 1 in the scaled coordinates
    w, V = np.linalg.eigh(Q)
    if not np.all(w > 0):
        raise InsufficientData(
            "ellipsoid: the best-fitting quadric is not an ellipsoid (eigenvalues "
            f"{np.array2string(w, precision=3)}), so the bias and shape matrix are undetermined. "
            "Add attitudes that tilt the unit: sweeps about the table's x and y axes.")
    E = (V * np.sqrt(w)) @ V.T / s  # symmetric square root, back in raw counts
    return c0 + s * centre, E


def ellipsoid(rec: Recording, acc: Accel) -> Calibration:
    """Ellipsoid fitting (seed 001, Sun, Yang, Wang): ``h_b = E (m - B)`` with E symmetric.

    Assumes the readings of every sample lie on one ellipsoid (constant field magnitude), and nothing
    about the attitudes: the table angles are not used. Fits the general quadric to all samples, takes
    its centre as the bias B and the symmetric square root of its normalised matrix as E, so that the
    corrected field has unit length; the magnetometer model is ``M = E^-1``, ``bias = B``.

    Limitation: a symmetric E cannot represent a rotation of the sensor triad relative to the body
    (the antisymmetric part of the misalignment), so that rotation stays in the heading.
    """
    B, E = fit_ellipsoid(rec.mag)
    M = np.linalg.inv(E)
    if np.trace(M / np.linalg.norm(M, axis=1)[:, None]) < 0:  # readings cannot tell the field's sign
        M = -M
    notes = [
        "ellipsoid (seed 001): E is the symmetric square root of the fitted quadric, so a rotation of "
        "the sensor triad relative to the body (the antisymmetric part of the misalignment) is not "
        "seen and stays in the heading; the table angles are not used.",
    ]
    return _base("ellipsoid", rec, acc, LinearSensor.from_matrix(M, B), notes)


# --------------------------------------------------------------------------------------------------
# Five-coefficient heading deviation (seed 004)
# --------------------------------------------------------------------------------------------------

def deviation5(rec: Recording, acc: Accel) -> Calibration:
    """Five-coefficient heading deviation (seed 004, Zhang, Cui, Zhang 2024) on top of the ellipsoid.

    The paper corrects the readings by ellipsoid fitting, then at level headings (24, 15 deg apart)
    fits ``dpsi = A + B sin psi + C cos psi + D sin 2psi + E cos 2psi`` by least squares, with psi the
    compass's heading and ``dpsi = psi - psi_ref``; the compass then reports ``psi - dpsi(psi)``.
    Here the level samples are those with theta_t and phi_t within 0.01 deg of zero (per-pose means);
    at least 5 distinct headings covering 180 deg are needed. The reference heading is ``psi_t - D``
    with D, unknown, estimated as the circular mean of ``psi_t - psi``; A is then the part of the
    mean offset the harmonics leave over, and the returned ``declination_deg`` is that D.

    Assumes the deviation is a function of heading alone, as at level; it is not fitted at tilt.
    When the ellipsoid cannot be fitted (only level data) the raw readings are used instead.
    """
    notes: list[str] = []
    try:
        base_cal = ellipsoid(rec, acc)
        mag, base = base_cal.mag, "ellipsoid"
        notes += base_cal.notes
    except InsufficientData as e:
        mag, base = LinearSensor(np.eye(3), np.ones(3), np.zeros(3)), "raw"
        notes.append(f"deviation5: ellipsoid not fitted ({e}); the deviation is fitted to the raw readings "
                     "(bias 0, k 1, M_o I), which is only meaningful at level")

    idx, headings, inverse = _level_poses(rec)
    cover = coverage_deg(headings)
    if headings.size < DEV5_MIN_HEADINGS or cover < DEV5_MIN_COVERAGE_DEG:
        raise InsufficientData(
            f"deviation5: needs level poses (theta_t = phi_t = 0 within {LEVEL_TOL_DEG} deg) at "
            f"{DEV5_MIN_HEADINGS} or more distinct headings covering {DEV5_MIN_COVERAGE_DEG:.0f} deg or more "
            f"of the turn; found {headings.size} heading(s) covering {cover:.0f} deg. Without them the five "
            "deviation coefficients A..E and the declination D are undetermined. Add a level turn about z "
            "(the paper uses 24 headings 15 deg apart).")

    f_b = specific_force(rec, acc.sensor)
    mag_mean = _pose_means(inverse, rec.mag[idx])
    f_mean = _pose_means(inverse, f_b[idx])
    psi = magnetic_heading(mag.correct(mag_mean), f_mean)
    D = circular_mean_deg(headings - psi)
    dpsi = wrap180(psi - (headings - D))
    p = np.radians(psi)
    X = np.column_stack([np.ones_like(p), np.sin(p), np.cos(p), np.sin(2 * p), np.cos(2 * p)])
    coef, *_ = np.linalg.lstsq(X, dpsi, rcond=None)
    resid = dpsi - X @ coef

    notes.append(f"deviation5 (seed 004): fitted at {headings.size} level headings covering {cover:.0f} deg; "
                 f"D = {D:.3f} deg from the circular mean of psi_t - psi; fit residual max "
                 f"{np.max(np.abs(resid)):.3f} deg. The curve is a function of heading only and is not "
                 "fitted at tilt.")
    if headings.size < 8:
        notes.append(f"deviation5: only {headings.size} headings for 5 coefficients: the curve interpolates "
                     "rather than averages; the paper uses 24")
    cal = _base("deviation5", rec, acc, mag, notes)
    cal.declination_deg = D
    cal.heading_model = {"kind": "deviation5", "coefficients_deg": [float(c) for c in coef], "base": base}
    return cal


# --------------------------------------------------------------------------------------------------
# Two-axis compass with the extended dip angle (seed 003, Cho and Park)
# --------------------------------------------------------------------------------------------------

def two_axis(rec: Recording, acc: Accel) -> Calibration:
    """Two-axis compass with an extended dip angle (seed 003, Cho and Park; Theorems 1-3).

    Assumes an orthogonal x-y sensor pair along the body axes (M_o = I) and no soft iron. Over a
    level turn (per-pose means of the level samples) each of x and y is normalised by its max/min:
    ``bias = (max + min) / 2``, ``SF = (max - min) / 2``, so a normalised reading is ``h / cos I``.
    The z sensor is not used: the vertical component is rebuilt from the pitch, roll and the extended
    dip ``lambda_e`` (Theorem 1), which absorbs the field distortions the normalisation leaves.

    D is the circular mean of ``psi_t - psi`` over the level turn. lambda_e is fitted on the poses tilted
    by 10 to 70 deg, whose reference heading ``psi_t - D`` (the ZYX yaw of the table minus D) is
    known: the normalised x, y predicted from pitch, roll, heading and lambda are linear in
    ``tan lambda`` (``C^T [cos psi, -sin psi, tan lambda]`` with ``C = Ry(pitch) Rx(roll)``), so the
    1-D least squares over lambda is solved in closed form (Theorem 3 in least-squares form).

    Model: M_o = I, ``k = [SF_x / cos lambda_e, SF_y / cos lambda_e, 1]``, ``bias = [b_x, b_y, 0]``,
    and ``heading_model = {"kind": "two_axis", "extended_dip_deg": lambda_e}``.
    """
    ang = table_angles(rec)
    idx, headings, inverse = _level_poses(rec)
    cover = coverage_deg(headings)
    if headings.size < TWO_AXIS_MIN_HEADINGS or cover < TWO_AXIS_MIN_COVERAGE_DEG:
        raise InsufficientData(
            f"two_axis: needs a level turn (theta_t = phi_t = 0 within {LEVEL_TOL_DEG} deg) with "
            f"{TWO_AXIS_MIN_HEADINGS} or more headings covering {TWO_AXIS_MIN_COVERAGE_DEG:.0f} deg or more; "
            f"found {headings.size} level heading(s) covering {cover:.0f} deg. Without it the x and y bias "
            "and scale (max/min normalisation) and the declination D are undetermined. Add a level turn "
            "about z.")
    psi_t = headings
    level_mag = _pose_means(inverse, rec.mag[idx])[:, :2]
    mx, mn = level_mag.max(axis=0), level_mag.min(axis=0)
    bias_xy, sf = (mx + mn) / 2.0, (mx - mn) / 2.0
    if np.any(sf <= 0):
        raise InsufficientData("two_axis: an x or y reading does not change over the level turn; its scale is "
                               "undetermined")
    norm = (level_mag - bias_xy) / sf
    psi_meas = np.degrees(np.arctan2(-norm[:, 1], norm[:, 0])) % 360.0
    D = circular_mean_deg(psi_t - psi_meas)

    # Tilted poses with known heading: Theorem 3 as a linear least squares in t = tan(lambda).
    f_b = specific_force(rec, acc.sensor)
    all_keys, all_inv = _poses(ang)
    f_mean = _pose_means(all_inv, f_b)
    m_mean = _pose_means(all_inv, rec.mag)
    tilt = np.degrees(np.arccos(np.clip(-f_mean[:, 2] / np.linalg.norm(f_mean, axis=1), -1.0, 1.0)))
    lo, hi = TWO_AXIS_TILT_RANGE_DEG
    use = (tilt >= lo) & (tilt <= hi)
    if not use.any():
        raise InsufficientData(
            f"two_axis: needs poses tilted by {lo:.0f} to {hi:.0f} deg (pitch or roll) at known headings to "
            f"estimate the extended dip angle; found none (tilts present: "
            f"{np.array2string(np.unique(np.round(tilt)), max_line_width=200)} deg). Without them the "
            "extended dip, hence the rebuilt vertical component and the tilt compensation, is "
            "undetermined. Add poses pitched or rolled by about 30 deg.")
    R = platform_attitude(all_keys[use, 0], all_keys[use, 1], all_keys[use, 2])
    psi_ref = np.radians(reference_heading(R, D))
    pitch, roll = pitch_roll(f_mean[use])
    C = rot_y(pitch) @ rot_x(roll)  # levelled = C h_b, so h_b / cos(lambda) = C^T [cos psi, -sin psi, tan lambda]
    a = C[:, 0, :2] * np.cos(psi_ref)[:, None] - C[:, 1, :2] * np.sin(psi_ref)[:, None]
    c = C[:, 2, :2]
    measured = (m_mean[use, :2] - bias_xy) / sf
    t = float(np.sum(c * (measured - a)) / np.sum(c * c))
    dip = float(np.degrees(np.arctan(t)))
    resid = measured - a - c * t

    mag = LinearSensor(np.eye(3), np.array([sf[0] / np.cos(np.radians(dip)), sf[1] / np.cos(np.radians(dip)), 1.0]),
                       np.array([bias_xy[0], bias_xy[1], 0.0]))
    gap = 360.0 - cover
    notes = [
        "two_axis (seed 003): the z sensor is not used; the vertical component is rebuilt from pitch, roll "
        f"and the extended dip {dip:.3f} deg (Theorem 1). M_o = I: misalignment and soft iron are not modelled.",
        f"two_axis: x, y normalised by max/min over {headings.size} level headings (largest gap {gap:.0f} deg: "
        f"the sampled extreme may miss the peak by up to {gap / 2:.0f} deg, a scale error up to "
        f"{100 * (1 - np.cos(np.radians(gap / 2))):.2g} %); D = {D:.3f} deg from the level turn.",
        f"two_axis: extended dip from {int(use.sum())} tilted pose(s); normalised-reading residual rms "
        f"{np.sqrt(np.mean(resid ** 2)):.2g} (field units / cos I).",
    ]
    cal = _base("two_axis", rec, acc, mag, notes)
    cal.inclination_deg, cal.declination_deg = dip, D
    cal.heading_model = {"kind": "two_axis", "extended_dip_deg": dip}
    return cal


# --------------------------------------------------------------------------------------------------
# Max/min per axis
# --------------------------------------------------------------------------------------------------

def maxmin(rec: Recording, acc: Accel) -> Calibration:
    """Hard- and soft-iron scaling by max/min per axis: ``bias = (max + min) / 2``, ``k = (max - min) / 2``.

    The common field-swing calibration: per-pose means over all samples (so noise does not widen the
    span), M_o = I. Assumes orthogonal sensor axes along the body axes and that every axis has been
    pointed along and against the field. The last is checked: the field direction is estimated from
    the normalised readings and the table angles, and every body axis must come within
    MAXMIN_TOL_DEG of the field and of its opposite at some pose, else InsufficientData.
    """
    ang = table_angles(rec)
    keys, inverse = _poses(ang)
    means = _pose_means(inverse, np.asarray(rec.mag, dtype=float))
    mx, mn = means.max(axis=0), means.min(axis=0)
    bias, k = (mx + mn) / 2.0, (mx - mn) / 2.0
    if not rec.has_angles:
        return _maxmin_free(rec, acc, means, bias, k)
    R = platform_attitude(keys[:, 0], keys[:, 1], keys[:, 2])  # nominal table: body axes in the base frame
    flat = k <= 0
    if flat.any():
        dirs = np.zeros(3)
    else:
        v = np.einsum("nij,nj->i", R, (means - bias) / k)  # the field in the base frame, averaged over poses
        dirs = v / np.linalg.norm(v) if np.linalg.norm(v) > 0 else v
    along = np.einsum("nji,j->ni", R, dirs)  # cos(angle between body axis i and the field) at each pose
    off_along = np.degrees(np.arccos(np.clip(along.max(axis=0), -1.0, 1.0)))
    off_against = np.degrees(np.arccos(np.clip(-along.min(axis=0), -1.0, 1.0)))
    bad = [i for i in range(3) if flat[i] or max(off_along[i], off_against[i]) > MAXMIN_TOL_DEG]
    if bad:
        dec = float(np.degrees(np.arctan2(dirs[1], dirs[0])) % 360.0) if not flat.any() else float("nan")
        d = f"{dec:.0f}" if np.isfinite(dec) else "D"
        d90 = f"{(dec - 90.0) % 360.0:.0f}" if np.isfinite(dec) else "D - 90"
        # A y sweep turns x_b and z_b in the vertical plane at azimuth psi_t, an x sweep turns y_b and z_b
        # in the vertical plane at psi_t + 90: the plane must hold the field for the axis to reach it.
        hint = {0: f"a full sweep about the table's y axis (pitch) at psi_t = {d} deg",
                1: f"a full sweep about the table's x axis (roll) at psi_t = {d90} deg",
                2: f"a full sweep about the y axis at psi_t = {d} deg or about the x axis at psi_t = {d90} deg"}
        lines = [f"{AXES[i]} axis: comes within {off_along[i]:.0f} deg of the field and {off_against[i]:.0f} deg "
                 f"of its opposite: add {hint[i]}" for i in bad]
        raise InsufficientData(
            f"maxmin: every sensor axis must point along and against the field (within {MAXMIN_TOL_DEG:.0f} deg) "
            "at some pose, or its bias and scale (max + min) / 2, (max - min) / 2 are wrong. "
            f"Estimated field azimuth D ~ {d} deg (steps of a few degrees near the dip let the axis reach "
            "the field). Run the calibration with method maxmin (it finds D on a level turn and sweeps there)."
            "\n  " + "\n  ".join(lines))
    notes = [
        "maxmin: bias and scale from the per-pose max/min of each axis; M_o = I, so misalignment and "
        "non-orthogonality stay in the heading; the table angles are used only to check the span.",
        "maxmin: closest approach of each axis to the field / its opposite (deg): "
        + ", ".join(f"{AXES[i]} {off_along[i]:.1f}/{off_against[i]:.1f}" for i in range(3)),
    ]
    return _base("maxmin", rec, acc, LinearSensor(np.eye(3), k, bias), notes)


def _maxmin_free(rec: Recording, acc: Accel, means: np.ndarray, bias: np.ndarray, k: np.ndarray) -> Calibration:
    """maxmin on a recording without table angles: each axis's span is checked by the field's direction at
    its own largest and smallest reading (scaled by the estimate itself), which must lie within
    MAXMIN_FREE_TOL_DEG of the axis (a level spin's z axis, which never saw the field, was given k = 270
    where x and y had 1500, and a calibration was written)."""
    off = np.full((3, 2), 90.0)
    if np.all(k > 0):
        h = (means - bias) / k
        for i in range(3):
            for j, at in enumerate((np.argmax(means[:, i]), np.argmin(means[:, i]))):
                off[i, j] = np.degrees(np.arccos(min(1.0, abs(h[at, i]) / max(np.linalg.norm(h[at]), 1e-300))))
    bad = [i for i in range(3) if off[i].max() > MAXMIN_FREE_TOL_DEG]
    if bad:
        raise InsufficientData(
            f"maxmin: every sensor axis must point along and against the field (within {MAXMIN_FREE_TOL_DEG:.0f} deg, "
            "judged from the readings: the recording has no table angles), or its bias and scale (max + min) / 2, "
            "(max - min) / 2 are wrong.\n  " + "\n  ".join(
                f"{AXES[i]} axis: at its largest and smallest readings the field is {off[i, 0]:.0f} and {off[i, 1]:.0f} deg "
                "off it: turn the unit so that this axis points along and against the field" for i in bad))
    notes = ["maxmin: bias and scale from the max/min of each axis; M_o = I, so misalignment and non-orthogonality "
             "stay in the heading; no table angles: the span checked from the readings alone.",
             "maxmin: the field's angle off each axis at its largest/smallest reading (deg): "
             + ", ".join(f"{AXES[i]} {off[i, 0]:.1f}/{off[i, 1]:.1f}" for i in range(3))]
    return _base("maxmin", rec, acc, LinearSensor(np.eye(3), k, bias), notes)


# --------------------------------------------------------------------------------------------------
# Twelve positions (seed 002)
# --------------------------------------------------------------------------------------------------

#: The twelve positions as table angles (psi_t, theta_t, phi_t): each body axis down and up, each at
#: two headings 180 deg apart (z down and up by roll 0/180, x by pitch -+90, y by roll +-90).
TWELVE_POSITIONS = [(psi, th, ph) for th, ph in ((0.0, 0.0), (0.0, 180.0), (-90.0, 0.0), (90.0, 0.0), (0.0, 90.0), (0.0, -90.0))
                    for psi in (0.0, 180.0)]


def twelve_position(rec: Recording, acc: Accel) -> Calibration:
    """Twelve-position calibration (seed 002: a tilt-compensated three-axis AMR compass calibrated at
    twelve positions; the paper gives only the name, so these are the textbook equations).

    The positions are the six faces (each body axis pointing down, then up) at two headings 180 deg
    apart. With the model ``m = A h_b + b`` (``A = diag(k) M_o``) and a unit lab field
    ``(cos I cos D, cos I sin D, sin I)``, turning a face through 180 deg about the vertical reverses
    the field's horizontal part and keeps its vertical part ``Z = sin I``. So for each face, with
    ``u`` the body's down direction and ``C`` its attitude at the first heading:

    - the pair's mean is ``b + Z A u``: over the six faces, a linear least squares in ``b`` and
      ``G = Z A`` (every column of A, so misalignment too, from the vertical field alone);
    - the pair's half difference is ``A C^T (cos I cos D, cos I sin D, 0)``: ``C G^-1`` of it is
      ``cot I (cos D, sin D)``, averaged over the faces, which gives I and D;
    - then ``A = G / sin I``, ``k`` its row norms and ``M_o`` its normalised rows.

    The table is taken as level (the base tilt is not in the equations) and the poses as exact.
    """
    ang = table_angles(rec)
    keys, inverse = _poses(ang)
    means = _pose_means(inverse, np.asarray(rec.mag, dtype=float))
    C = platform_attitude(keys[:, 0], keys[:, 1], keys[:, 2])
    down = C[:, 2, :]  # the lab's down direction in body axes (row 2 of C_Lb)
    axis = np.argmax(np.abs(down), axis=1)
    vertical = np.abs(down[np.arange(len(keys)), axis]) >= np.cos(np.radians(TWELVE_FACE_TOL_DEG))
    faces: dict[tuple[int, int], tuple[int, int]] = {}
    for i in np.flatnonzero(vertical):
        face = (int(axis[i]), int(np.sign(down[i, axis[i]])))
        if face in faces:
            continue
        # its partner: the same tilt, the heading 180 deg on
        partner = [j for j in np.flatnonzero(vertical) if np.allclose(keys[j, 1:], keys[i, 1:], atol=0.01)
                   and abs(wrap180(keys[j, 0] - keys[i, 0] - 180.0)) < 0.01]
        if partner:
            faces[face] = (int(i), int(partner[0]))
    missing = [f"{AXES[a]} {'down' if s > 0 else 'up'}" for a in range(3) for s in (1, -1) if (a, s) not in faces]
    if missing:
        raise InsufficientData(
            "twelve_position: needs each body axis pointing down and up (within "
            f"{TWELVE_FACE_TOL_DEG:g} deg of the vertical), each at two headings 180 deg apart; missing: "
            f"{', '.join(missing)}. Without a face its column of the sensor matrix and the bias are "
            "undetermined. Run the calibration with method twelve-position (it visits the twelve positions).")
    pairs = list(faces.values())
    avg = np.array([(means[i] + means[j]) / 2.0 for i, j in pairs])
    half = np.array([(means[i] - means[j]) / 2.0 for i, j in pairs])
    u = np.array([down[i] for i, _ in pairs])
    X = np.hstack([np.ones((len(pairs), 1)), u])  # avg = b + G u
    sol, *_ = np.linalg.lstsq(X, avg, rcond=None)
    bias, G = sol[0], sol[1:].T
    hor = np.array([C[i] @ np.linalg.solve(G, h) for (i, _), h in zip(pairs, half)])  # cot I (cos D, sin D, 0)
    xy = hor[:, :2].mean(axis=0)
    cot = float(np.hypot(*xy))
    inc = float(np.degrees(np.arctan2(1.0, cot)))
    dec = float(np.degrees(np.arctan2(xy[1], xy[0])))
    A = G / np.sin(np.radians(inc))
    k = np.linalg.norm(A, axis=1)
    spread = np.degrees(np.arctan(np.linalg.norm(hor[:, :2] - xy, axis=1) / max(cot, 1e-12)))
    notes = [
        "twelve_position (seed 002): bias and the full sensor matrix from the six faces' vertical field, "
        "I and D from their 180-deg differences; the base is taken as level.",
        f"twelve_position: the faces' horizontal fields agree within {spread.max():.3f} deg; "
        f"off-vertical residual {np.abs(hor[:, 2]).max() / max(cot, 1e-12):.2g} of the horizontal field.",
    ]
    cal = _base("twelve_position", rec, acc, LinearSensor(A / k[:, None], k, bias), notes)
    cal.inclination_deg, cal.declination_deg = inc, dec % 360.0
    return cal


METHODS = {"ellipsoid": ellipsoid, "deviation5": deviation5, "two_axis": two_axis, "maxmin": maxmin,
           "twelve_position": twelve_position}

__all__ = ["METHODS", "TWELVE_POSITIONS", "deviation5", "ellipsoid", "fit_ellipsoid", "maxmin", "twelve_position", "two_axis"]
