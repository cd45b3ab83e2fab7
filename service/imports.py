"""Read recordings made elsewhere into a :class:`~physics.recording.Recording` (issue 6, "Real recordings").

``read_recording_file(path)`` understands:

- our own recording CSV (shared/design/RECORDING.md), through :func:`physics.recording.parse_recording`;
- the QMC5883L CSV of tomisuarez2/MagnetometerCalibration (``Fs,50.00`` / ``Initialization time,60`` /
  ``mx,my,mz`` then integer counts): no time column, so ``t = row / Fs``; the first
  ``Initialization time`` seconds were logged while the sensor was held still to warm up, so those rows
  are labelled step ``warmup`` and the rest ``data`` (kept, not dropped: the analyser uses the warm-up as
  a static hold and can see a warm-up drift);
- the GimbalPlatform ``.mat`` (variable ``data``, N x 10: dt ms, acc g, gyro deg/s, mag uT);
- the BROAD ``.mat`` files (``imu_mag`` uT, ``imu_acc`` m/s^2, ``imu_gyr`` rad/s, ``opt_quat`` optical
  reference IMU->ENU, ``movement`` mask), whose optical reference becomes table angles.

Units: a Recording holds raw counts (LSB). Recordings that come in physical units are stored at the
nominal scales of PROTOCOLS.md's compass, written into the metadata: magnetometer 0.01 uT per count
(``mag_unit``), accelerometer 1/16384 g per count (``acc_unit``, physics.sensor.ACC_LSB_PER_G), and
gyro rates as extra columns ``gx, gy, gz`` in deg/s (``gyro_unit``).

Every error is a :class:`RecordingFileError` (a RecordingError) whose message starts with the file name.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from physics.frames import yaw_pitch_roll
from physics.recording import SKIPPED_KEY, Recording, RecordingError, parse_recording
from physics.sensor import ACC_LSB_PER_G

#: Nominal magnetometer scale of PROTOCOLS.md's compass: counts per microtesla (0.01 uT per count).
MAG_COUNTS_PER_UT = 100.0
#: Standard gravity used to express m/s^2 in g.
STANDARD_G = 9.80665
MAG_UNIT = "0.01 uT per count"
ACC_UNIT = f"1/{ACC_LSB_PER_G:.0f} g per count (g = {STANDARD_G} m/s^2)"
GYRO_UNIT = "deg/s"

#: ENU -> NED: x_NED = y_ENU (north), y_NED = x_ENU (east), z_NED = -z_ENU (down). Our lab frame L is z
#: down with x at azimuth zero (PHYSICS.md); for BROAD we take L = NED, so azimuth zero is the optical
#: frame's north (which the BROAD authors aligned with the ENU reference).
T_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


class RecordingFileError(RecordingError):
    """A recording file that cannot be read; the message names the file and the problem."""


def _fail(path: Path, problem: str) -> RecordingFileError:
    return RecordingFileError(f"{path.name}: {problem}")


def read_recording_file(path: Path | str, *, skip_bad_rows: bool = False) -> Recording:
    """Read any supported recording file (see module docstring) into a Recording.

    ``skip_bad_rows`` drops malformed rows of a text file (counted in ``meta["skipped_rows"]``) instead
    of rejecting the file.
    """
    path = Path(path)
    if not path.exists():
        raise _fail(path, "file not found")
    if not path.is_file():
        raise _fail(path, "not a regular file")
    suffix = path.suffix.lower()
    if suffix == ".mat":
        return _read_mat(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise _fail(path, f"not UTF-8 text and not a .mat file ({e.reason} at byte {e.start})") from None
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if first.replace(" ", "").lower().startswith("fs,"):
        return _read_qmc_csv(path, text, skip_bad_rows)
    try:
        rec = parse_recording(text, skip_bad_rows=skip_bad_rows)
    except RecordingError as e:
        raise _fail(path, f"not a readable recording CSV (RECORDING.md): {e}") from None
    rec.meta.setdefault("source_file", path.name)
    return rec


# --------------------------------------------------------------------------------------------------
# QMC5883L CSV (tomisuarez2/MagnetometerCalibration)
# --------------------------------------------------------------------------------------------------

def _header_value(path: Path, line: str, lineno: int, key: str) -> float:
    cells = [c.strip() for c in line.split(",")]
    if len(cells) != 2 or cells[0].lower() != key.lower():
        raise _fail(path, f"line {lineno}: expected '{key},<number>', got {line.strip()!r}")
    try:
        value = float(cells[1])
    except ValueError:
        raise _fail(path, f"line {lineno}: {key} is not a number ({cells[1]!r})") from None
    if not math.isfinite(value):
        raise _fail(path, f"line {lineno}: {key} is not finite ({cells[1]!r})")
    return value


def _read_qmc_csv(path: Path, text: str, skip_bad_rows: bool) -> Recording:
    """The QMC5883L logger's CSV: three header lines, then ``mx,my,mz`` integers at Fs."""
    lines = text.splitlines()
    if len(lines) < 4:
        raise _fail(path, f"QMC CSV needs 3 header lines and data rows, got {len(lines)} line(s)")
    fs = _header_value(path, lines[0], 1, "Fs")
    if fs <= 0:
        raise _fail(path, f"line 1: sampling frequency Fs must be positive, got {fs:g}")
    t_init = _header_value(path, lines[1], 2, "Initialization time")
    if t_init < 0:
        raise _fail(path, f"line 2: Initialization time must not be negative, got {t_init:g}")
    names = [c.strip().lower() for c in lines[2].split(",")]
    if names != ["mx", "my", "mz"]:
        raise _fail(path, f"line 3: expected the column line 'mx,my,mz', got {lines[2].strip()!r}")

    rows: list[list[float]] = []
    problems: list[str] = []
    for lineno, line in enumerate(lines[3:], start=4):
        if not line.strip():
            continue
        cells = [c.strip() for c in line.split(",")]
        try:
            if len(cells) != 3:
                raise ValueError(f"expected 3 fields, got {len(cells)}")
            values = [float(c) for c in cells]
            if not all(math.isfinite(v) for v in values):
                raise ValueError("non-finite value")
        except ValueError as e:
            problems.append(f"line {lineno}: {e} ({line.strip()[:60]!r})")
            continue
        rows.append(values)
    if problems and not skip_bad_rows:
        more = f"\n... and {len(problems) - 20} more" if len(problems) > 20 else ""
        raise _fail(path, f"{len(problems)} malformed row(s):\n" + "\n".join(problems[:20]) + more)
    if not rows:
        raise _fail(path, "no data rows")

    mag = np.array(rows)
    # t from the nominal rate: the logger writes every line it receives and records no time stamps
    # (it timed the warm-up by the PC clock, so the warm-up boundary is as exact as the nominal rate).
    t = np.arange(len(mag)) / fs
    step = np.where(t < t_init, "warmup", "data")
    meta = {
        "source_file": path.name,
        "source": "tomisuarez2/MagnetometerCalibration, calibration data/filtered_raw_data.csv "
                  "(MIT, (c) 2025 Tomas Suarez)",
        "sensor": "QMC5883L (GY-273 board)",
        "sample_rate_hz": f"{fs:g}",
        "warmup_s": f"{t_init:g}",
        "mag_unit": "raw counts (uncalibrated)",
        "time_source": "t = row / Fs (nominal rate; the file has no time stamps)",
        "note": "the first warmup_s seconds were logged with the sensor held still (step warmup), "
                "then it was moved by hand through all orientations (step data)",
    }
    if skip_bad_rows:
        meta[SKIPPED_KEY] = str(len(problems))
    return _build(path, t=t, step=step, mag=mag, meta=meta)


# --------------------------------------------------------------------------------------------------
# MATLAB files
# --------------------------------------------------------------------------------------------------

def _read_mat(path: Path) -> Recording:
    import scipy.io  # local: only the .mat readers need it

    try:
        d = scipy.io.loadmat(str(path))
    except NotImplementedError:  # MATLAB v7.3 is HDF5
        raise _fail(path, "MATLAB v7.3 (HDF5) files are not supported; save as v7 or earlier") from None
    except Exception as e:  # scipy raises ValueError/TypeError/... for files that are not MAT-files
        raise _fail(path, f"not a readable MATLAB .mat file ({type(e).__name__}: {e})") from None
    if "imu_mag" in d:
        return _read_broad(path, d)
    if "data" in d:
        return _read_gimbal(path, d)
    keys = sorted(k for k in d if not k.startswith("__"))
    raise _fail(path, "unknown .mat layout: expected BROAD variables (imu_mag, imu_acc, imu_gyr, opt_quat, "
                      f"movement, sampling_rate) or GimbalPlatform's 'data' (N x 10); found {keys}")


def _array(path: Path, d: dict[str, Any], name: str, cols: int | None) -> np.ndarray:
    if name not in d:
        raise _fail(path, f"variable {name!r} is missing")
    a = np.asarray(d[name], dtype=float)
    if cols is None:
        return a.reshape(-1)
    if a.ndim != 2 or a.shape[1] != cols:
        raise _fail(path, f"variable {name!r} has shape {a.shape}, expected (N, {cols})")
    return a


def _extra(values: np.ndarray) -> dict[str, list[str]]:
    return {name: [f"{v:.6f}" for v in values[:, k]] for k, name in enumerate(("gx", "gy", "gz"))}


def _read_gimbal(path: Path, d: dict[str, Any]) -> Recording:
    """GimbalPlatform (pabloramesc): ``data`` N x 10 = dt [ms], ax ay az [g], gx gy gz [deg/s], mx my mz [uT]."""
    data = _array(path, d, "data", 10)
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if bad.size:
        raise _fail(path, f"data has non-finite values in row(s) {(bad[:10] + 1).tolist()}")
    dt_ms = data[:, 0]
    nonpos = np.flatnonzero(dt_ms[1:] <= 0)
    if nonpos.size:
        raise _fail(path, f"column 1 (dt, ms) is not positive in row(s) {(nonpos[:10] + 2).tolist()}")
    # dt is the time since the previous sample; the run starts at the first sample (t = 0).
    t = np.concatenate([[0.0], np.cumsum(dt_ms[1:])]) / 1000.0
    meta = {
        "source_file": path.name,
        "source": "pabloramesc/GimbalPlatform, matlab/datasets/ble33sense/spin_Z.mat (MIT)",
        "sensor": "LSM9DS1 (Arduino Nano 33 BLE Sense)",
        "mag_unit": MAG_UNIT, "acc_unit": ACC_UNIT, "gyro_unit": GYRO_UNIT,
        "sample_rate_hz": f"{1000.0 / float(np.median(dt_ms[1:])):.3f}",
        "time_source": "t = cumulative sum of the dt column (ms), first sample at t = 0",
        "note": "rotation about the sensor z axis while level; how it was driven is not documented; "
                "no heading reference",
    }
    return _build(path, t=t, step=np.full(len(t), "spin_z"), mag=data[:, 7:10] * MAG_COUNTS_PER_UT,
                  acc=data[:, 1:4] * ACC_LSB_PER_G, meta=meta, extra=_extra(data[:, 4:7]))


def broad_attitude(quat_wxyz: np.ndarray) -> np.ndarray:
    """C_Lb (N, 3, 3) in our lab frame L = NED from BROAD's ``opt_quat`` ([w, x, y, z], IMU -> ENU).

    BROAD's quaternion maps IMU coordinates to ENU: ``v_ENU = R(q) v_IMU``. Checked on the data: at rest
    ``R(q) acc`` is (0.00, 0.03, 9.89) m/s^2 (up, as a specific force at rest must be) in file 01 and
    (0.02, -0.02, 9.82) in file 05, while the transpose gives (0.02, 0.17, 5.2) with a spread of 3-6
    m/s^2; and ``R(q) mag`` is a constant field pointing north (azimuth -2.6 and -0.2 deg from +y_ENU)
    and down with dip 70.2 and 69.3 deg (Berlin: about 68 deg). So ``C_Lb = T_NED<-ENU R(q)``, and the
    accelerometer at rest reads ``C_Lb^T [0, 0, -1] g`` (PHYSICS.md's f_b) to within its calibration.
    """
    q = np.asarray(quat_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.empty((len(q), 3, 3))  # the active rotation of the unit quaternion (Hamilton convention)
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return T_NED_ENU @ R


def _block_labels(moving: np.ndarray) -> np.ndarray:
    """``rest_<k>`` / ``move_<k>`` for each run of the movement mask, k counted from 1 per kind."""
    labels = np.empty(len(moving), dtype=object)
    starts = np.flatnonzero(np.r_[True, moving[1:] != moving[:-1]])
    ends = np.r_[starts[1:], len(moving)]
    count = {True: 0, False: 0}
    for a, b in zip(starts, ends):
        kind = bool(moving[a])
        count[kind] += 1
        labels[a:b] = f"{'move' if kind else 'rest'}_{count[kind]}"
    return labels


def _read_broad(path: Path, d: dict[str, Any]) -> Recording:
    """BROAD (Laidig et al. 2021): IMU data with an optical reference, turned into table angles.

    The reference attitude C_Lb (see :func:`broad_attitude`) gives ``(psi_t, theta_t, phi_t)`` = its ZYX
    Euler angles (physics.frames.yaw_pitch_roll): an ideal table's encoder angles are exactly the
    platform's ZYX heading, pitch and roll. psi_t and phi_t are unwrapped (continuous, like encoder
    readings) rather than folded into one turn. Rows without an optical reference (NaN quaternion) are
    dropped and counted in ``meta["dropped_rows_no_reference"]``.
    """
    mag = _array(path, d, "imu_mag", 3)
    n = len(mag)
    acc = _array(path, d, "imu_acc", 3)
    gyr = _array(path, d, "imu_gyr", 3)
    quat = _array(path, d, "opt_quat", 4)
    moving = _array(path, d, "movement", None)
    for name, a in (("imu_acc", acc), ("imu_gyr", gyr), ("opt_quat", quat), ("movement", moving)):
        if len(a) != n:
            raise _fail(path, f"variable {name!r} has {len(a)} rows, imu_mag has {n}")
    rate = _array(path, d, "sampling_rate", None)
    if rate.size != 1 or not np.isfinite(rate[0]) or rate[0] <= 0:
        raise _fail(path, f"sampling_rate must be one positive number, got {rate.tolist()}")
    fs = float(rate[0])
    labels = _block_labels(moving.astype(bool))  # before dropping rows, so a gap does not split a block

    bad_imu = ~(np.isfinite(mag).all(axis=1) & np.isfinite(acc).all(axis=1) & np.isfinite(gyr).all(axis=1))
    if bad_imu.any():
        raise _fail(path, f"IMU data has non-finite values in {int(bad_imu.sum())} row(s), first row "
                          f"{int(np.flatnonzero(bad_imu)[0]) + 1}")
    has_ref = np.isfinite(quat).all(axis=1) & (np.linalg.norm(np.nan_to_num(quat), axis=1) > 0.5)
    if not has_ref.any():
        raise _fail(path, "opt_quat has no valid row: no optical reference to turn into table angles")
    keep = np.flatnonzero(has_ref)
    C = broad_attitude(quat[keep])
    psi, theta, phi = yaw_pitch_roll(C)
    # unwrap so the angles move continuously (a table encoder does not jump from +180 to -180)
    psi = np.degrees(np.unwrap(np.radians(psi)))
    phi = np.degrees(np.unwrap(np.radians(phi)))

    mag_counts = mag * MAG_COUNTS_PER_UT
    repeats = float(np.mean(np.all(np.diff(mag, axis=0) == 0, axis=1)))
    meta = {
        "source_file": path.name,
        "source": "dlaidig/broad, data_mat (CC-BY-4.0; Laidig, Caruso, Cereatti, Seel, Data 6(7) 2021)",
        "sensor": "myon aktos-t IMU; reference: Optitrack optical motion capture",
        "sample_rate_hz": f"{fs:.6g}",
        "mag_unit": MAG_UNIT, "acc_unit": ACC_UNIT, "gyro_unit": GYRO_UNIT,
        # the analyser reads this key: no turntable, so no stages, table axes or rotation centre
        "attitude_source": "optical reference",
        "angles": "psi_t, theta_t, phi_t = ZYX Euler angles of the optical reference C_Lb, lab frame L = NED "
                  "(x north of the optical ENU frame, z down), psi_t and phi_t unwrapped",
        "dropped_rows_no_reference": str(int(n - keep.size)),
        "mag_repeated_rows": f"{repeats:.3f} (fraction of rows repeating the previous magnetometer reading: "
                             "the magnetometer updates slower than the IMU rate)",
        "time_source": "t = row / sampling_rate (row index before dropping rows without reference)",
        "steps": "rest_<k> / move_<k> from BROAD's movement mask (0 = rest)",
    }
    return _build(path, t=keep / fs, step=labels[keep], mag=mag_counts[keep],
                  acc=acc[keep] / STANDARD_G * ACC_LSB_PER_G, angles=(psi, theta, phi), meta=meta,
                  extra=_extra(np.degrees(gyr[keep])))


def _build(path: Path, *, t: np.ndarray, step: np.ndarray, mag: np.ndarray, meta: dict[str, str],
           acc: np.ndarray | None = None, angles: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
           extra: dict[str, list[str]] | None = None) -> Recording:
    n = len(t)
    psi, theta, phi = angles if angles is not None else (np.full(n, np.nan),) * 3
    try:
        return Recording.from_arrays(t=t, step=step, psi_t=psi, theta_t=theta, phi_t=phi, mag=mag, acc=acc,
                                     meta=meta, extra=extra)
    except RecordingError as e:
        raise _fail(path, str(e)) from None
