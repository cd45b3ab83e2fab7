"""Read recordings made elsewhere into a :class:`~physics.recording.Recording` (issue 6, "Real recordings").

``read_recording_file(path)`` understands:

- our own recording CSV (shared/design/RECORDING.md), through :func:`physics.recording.parse_recording`;
- the QMC5883L CSV of tomisuarez2/MagnetometerCalibration (``Fs,50.00`` / ``Initialization time,60`` /
  ``mx,my,mz`` then integer counts): no time column, so ``t = row / Fs``; the first
  ``Initialization time`` seconds were logged while the sensor was held still to warm up, so those rows
  are labelled step ``warmup`` and the rest ``data`` (kept, not dropped: the analyser uses the warm-up as
  a static hold and can see a warm-up drift);
- the GimbalPlatform ``.mat`` files (pabloramesc/GimbalPlatform): ``datasets/ble33sense`` (variable
  ``data``, N x 10: dt ms, acc g, gyro deg/s, mag uT) and ``datasets/platform`` (``data``, N x 14: time s,
  the three gimbal angles, acc, gyro, mag, dt ms), whose angles become table angles (:func:`_read_platform`);
- the BROAD files (``imu_mag`` uT, ``imu_acc`` m/s^2, ``imu_gyr`` rad/s, ``opt_quat`` optical reference
  IMU->ENU, ``movement`` mask), ``.mat`` or ``.hdf5`` (the same variables), whose optical reference becomes
  table angles;
- MATLAB v7.3 ``.mat`` files (HDF5 inside, read with h5py) of any of the layouts above, and the
  ``compassBuffer`` files of sunsided/sensor-fusion (HMC5883L, N x 4 = t s, x, y, z gauss);
- anything else through a mapping file (``read_recording_file(path, mapping="map.toml")``, see
  :func:`load_mapping` and examples/mapping.toml): which column is what, units, axis signs and order,
  angle convention or an attitude quaternion, and the time base.

Units: a Recording holds raw counts (LSB). Recordings that come in physical units are stored at the
nominal scales of PROTOCOLS.md's compass, written into the metadata: magnetometer 0.01 uT per count
(``mag_unit``), accelerometer 1/16384 g per count (``acc_unit``, physics.sensor.ACC_LSB_PER_G), and
gyro rates as extra columns ``gx, gy, gz`` in deg/s (``gyro_unit``).

Every error is a :class:`RecordingFileError` (a RecordingError) whose message starts with the file name.
"""

from __future__ import annotations

import csv
import math
import re
import tomllib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, PrivateAttr, ValidationError, ValidationInfo,
                      create_model, field_validator, model_validator)
from pydantic_core import ErrorDetails
from scipy.spatial.transform import Rotation

from physics.fit import radian_like
from physics.frames import yaw_pitch_roll
from physics.recording import SKIPPED_AT_KEY, SKIPPED_KEY, Recording, RecordingError, parse_recording
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
#: NWU -> NED: north stays, west becomes -east, up becomes -down.
T_NED_NWU = np.diag([1.0, -1.0, -1.0])
#: Lab frames a quaternion may be stated in, as the rotation into our L (z down, x at azimuth zero).
LAB_FRAMES = {"NED": np.eye(3), "ENU": T_NED_ENU, "NWU": T_NED_NWU}
HDF5_SUFFIXES = (".hdf5", ".h5", ".he5")
#: First bytes of an HDF5 file; MATLAB v7.3 puts a 512-byte header in front of them.
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


class RecordingFileError(RecordingError):
    """A recording file that cannot be read; the message names the file and the problem."""


def _fail(path: Path, problem: str) -> RecordingFileError:
    return RecordingFileError(f"{path.name}: {problem}")


def read_recording_file(path: Path | str, *, skip_bad_rows: bool = False,
                        mapping: Path | str | dict[str, Any] | None = None) -> Recording:
    """Read any supported recording file (see module docstring) into a Recording.

    ``skip_bad_rows`` drops malformed rows of a text file (counted in ``meta["skipped_rows"]``) instead
    of rejecting the file. ``mapping`` (a TOML file, or its parsed dict) says how to read a file no
    built-in reader knows; with it the built-in layouts are not tried.
    """
    path = Path(path)
    if mapping is not None:
        spec = load_mapping(mapping)  # mapping errors first: they name the mapping file, not the data
    if not path.exists():
        raise _fail(path, "file not found")
    if not path.is_file():
        raise _fail(path, "not a regular file")
    if mapping is not None:
        return _read_mapped(path, spec, skip_bad_rows)
    suffix = path.suffix.lower()
    if suffix == ".mat":
        return _read_mat(path)
    if suffix in HDF5_SUFFIXES:
        return _dispatch_arrays(path, _load_hdf5(path, matlab=False), "HDF5")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise _fail(path, f"not UTF-8 text and not a .mat or .hdf5 file ({e.reason} at byte {e.start + 1}, counting from 1)") from None
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if first.replace(" ", "").lower().startswith("fs,"):
        return _read_qmc_csv(path, text, skip_bad_rows)
    try:
        rec = parse_recording(text, skip_bad_rows=skip_bad_rows)
    except RecordingError as e:
        raise _fail(path, f"not a readable recording CSV (RECORDING.md): {e}; for another layout give a "
                          "mapping file (--mapping, examples/mapping.toml)") from None
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
    skipped_at: list[int] = []  # 0-based data rows (the non-blank lines after the header)
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
            skipped_at.append(len(rows) + len(skipped_at))
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
        "sensor": "QMC5883L (on a board its source calls GY-63)",
        "sample_rate_hz": f"{fs:g}",
        "warmup_s": f"{t_init:g}",
        "mag_unit": "raw counts (uncalibrated)",
        "time_source": "t = row / Fs (nominal rate; the file has no time stamps)",
        "note": "the first warmup_s seconds were logged with the sensor held still (step warmup), "
                "then it was moved by hand through all orientations (step data)",
    }
    if skip_bad_rows:
        meta[SKIPPED_KEY] = str(len(problems))
        if skipped_at:
            meta[SKIPPED_AT_KEY] = ",".join(map(str, skipped_at))
    return _build(path, t=t, step=step, mag=mag, meta=meta)


# --------------------------------------------------------------------------------------------------
# MATLAB files
# --------------------------------------------------------------------------------------------------

def _read_mat(path: Path) -> Recording:
    import scipy.io  # local: only the .mat readers need it

    try:
        d = scipy.io.loadmat(str(path))
    except NotImplementedError:  # MATLAB v7.3 keeps its variables in an HDF5 file
        return _dispatch_arrays(path, _load_hdf5(path, matlab=True), "MATLAB v7.3")
    except Exception as e:  # scipy raises ValueError/TypeError/... for files that are not MAT-files
        raise _fail(path, f"not a readable MATLAB .mat file ({type(e).__name__}: {e})") from None
    return _dispatch_arrays(path, d, "MATLAB")


def _dispatch_arrays(path: Path, d: dict[str, Any], kind: str) -> Recording:
    """Pick the reader of a .mat/.hdf5 file from the variables it holds."""
    if "imu_mag" in d:
        return _read_broad(path, d)
    if "compassBuffer" in d:
        return _read_compass_buffer(path, d)
    if "data" in d:
        shape = np.shape(d["data"])
        if len(shape) == 2 and shape[1] == 14:
            return _read_platform(path, d)
        return _read_gimbal(path, d)
    keys = sorted(k for k in d if not k.startswith("__"))
    raise _fail(path, f"unknown {kind} layout: expected BROAD variables (imu_mag, imu_acc, imu_gyr, opt_quat, "
                      "movement, sampling_rate), GimbalPlatform's 'data' (N x 10 or N x 14) or sensor-fusion's "
                      f"'compassBuffer' (N x 4); found {keys}; for another layout give a mapping file (--mapping)")


def _is_hdf5(path: Path) -> bool:
    with path.open("rb") as f:
        head = f.read(520)
    return head[:8] == HDF5_SIGNATURE or head[512:520] == HDF5_SIGNATURE


def _load_hdf5(path: Path, *, matlab: bool) -> dict[str, Any]:
    """The top-level numeric datasets (and, for names no dataset has, the root attributes) of an HDF5 file.

    MATLAB v7.3 writes its column-major arrays as they lie in memory, so h5py sees every matrix
    transposed (a MATLAB N x 4 array arrives as 4 x N); ``matlab=True`` transposes them back so the
    readers see MATLAB's shapes, as scipy.io.loadmat gives them for older files.
    """
    try:
        import h5py  # local: only HDF5 files need it
    except ImportError:  # pragma: no cover - h5py is a dependency (pyproject.toml)
        raise _fail(path, "reading HDF5 (and MATLAB v7.3) files needs the h5py package") from None
    if not _is_hdf5(path):
        raise _fail(path, "not an HDF5 file (no HDF5 signature)" if not matlab else
                          "MATLAB v7.3 file without an HDF5 body: cannot read it")
    out: dict[str, Any] = {}
    try:
        with h5py.File(path, "r") as f:
            for name, item in f.items():
                # MATLAB's own bookkeeping groups (#refs#, #subsystem#) and any group are not variables
                if not isinstance(item, h5py.Dataset) or item.dtype.kind not in "fiub":
                    continue
                a = np.asarray(item[()], dtype=float)
                out[name] = a.T if matlab and a.ndim >= 2 else a
            for name, value in f.attrs.items():
                if name not in out and np.asarray(value).dtype.kind in "fiub":
                    out[name] = np.asarray(value, dtype=float)
    except OSError as e:
        raise _fail(path, f"not a readable HDF5 file ({e})") from None
    return out


def _array(path: Path, d: dict[str, Any], name: str, cols: int | None) -> np.ndarray:
    if name not in d:
        raise _fail(path, f"variable {name!r} is missing")
    a = np.asarray(d[name], dtype=float)
    if cols is None:
        return a.reshape(-1)
    if a.ndim != 2 or a.shape[1] != cols:
        raise _fail(path, f"variable {name!r} has shape {a.shape}, expected (N, {cols})")
    return a


def _extra(values: np.ndarray, names: tuple[str, ...] = ("gx", "gy", "gz")) -> dict[str, list[str]]:
    return {name: [f"{v:.6f}" for v in values[:, k]] for k, name in enumerate(names)}


def _finite_rows(path: Path, data: np.ndarray, name: str = "data") -> None:
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if bad.size:
        raise _fail(path, f"{name} has non-finite values in row(s) {(bad[:10] + 1).tolist()}")


#: How the LSM9DS1's readings as the Arduino library gives them become one right-handed frame (the source's
#: NED frame, compute_attitude.m): its accelerometer/gyro axes as read form a left-handed set, and its
#: magnetometer's x axis points against theirs.
LSM9DS1_AXES = "ax, ay, az = file ax, ay, -az; mx, my, mz = file -mx, my, -mz; gx, gy, gz = file gx, gy, -gz"


def _lsm9ds1_axes(acc: np.ndarray, gyro: np.ndarray, mag: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The LSM9DS1's accelerometer, gyro and magnetometer columns in one right-handed frame
    (:data:`LSM9DS1_AXES`)."""
    sign = np.array([1.0, 1.0, -1.0])
    return acc * sign, gyro * sign, mag * np.array([-1.0, 1.0, -1.0])


def _read_gimbal(path: Path, d: dict[str, Any]) -> Recording:
    """GimbalPlatform (pabloramesc), ``matlab/datasets/ble33sense``: ``data`` N x 10 = dt [ms], ax ay az [g],
    gx gy gz [deg/s], mx my mz [uT]; the unit turned by hand or held still, no angles."""
    shape = np.shape(d["data"])
    if len(shape) != 2 or shape[1] != 10:
        raise _fail(path, f"variable 'data' has shape {shape}, expected (N, 10) (datasets/ble33sense) or "
                          "(N, 14) (datasets/platform)")
    data = _array(path, d, "data", 10)
    _finite_rows(path, data)
    dt_ms = data[:, 0]
    nonpos = np.flatnonzero(dt_ms[1:] <= 0)
    if nonpos.size:
        raise _fail(path, f"column 1 (dt, ms) is not positive in row(s) {(nonpos[:10] + 2).tolist()}")
    # dt is the time since the previous sample; the run starts at the first sample (t = 0).
    t = np.concatenate([[0.0], np.cumsum(dt_ms[1:])]) / 1000.0
    spin_z = "spin_z" in path.name.lower()
    # in one right-handed frame, as the same chip's platform files are read (the raw axes, a left-handed
    # accelerometer and a magnetometer x against it, gave a level unit az = +1 g, and a dip through a mirror)
    acc, gyro, mag = _lsm9ds1_axes(data[:, 1:4], data[:, 4:7], data[:, 7:10])
    meta = {
        "source_file": path.name,
        "source": "pabloramesc/GimbalPlatform, matlab/datasets/ble33sense/"
                  + ("spin_Z.mat" if spin_z else "*.mat") + " (MIT)",
        "sensor": "LSM9DS1 (Arduino Nano 33 BLE Sense)",
        "mag_unit": MAG_UNIT, "acc_unit": ACC_UNIT, "gyro_unit": GYRO_UNIT,
        "sample_rate_hz": f"{1000.0 / float(np.median(dt_ms[1:])):.3f}",
        "time_source": "t = cumulative sum of the dt column (ms), first sample at t = 0",
        "note": ("rotation about the sensor z axis while level; " if spin_z else "motion as the file name says; ")
                + "how it was driven is not documented; no heading reference",
        "axes": LSM9DS1_AXES,
    }
    return _build(path, t=t, step=np.full(len(t), "spin_z" if spin_z else "data"),
                  mag=mag * MAG_COUNTS_PER_UT, acc=acc * ACC_LSB_PER_G, meta=meta, extra=_extra(gyro))


#: AS5600 magnetic encoder: 4096 counts per turn. The platform firmware (TFG_platformController.ino,
#: ``as5600_read``) converts with 0.087 deg per count instead of 360/4096 = 0.08789, so its angles are
#: 1.02 % short; multiplying the file's angle by this factor gives the angle from the same zero.
AS5600_SCALE = (360.0 / 4096.0) / 0.087
#: The firmware's angle wraps after 4096 counts of 0.087 deg.
AS5600_WRAP_DEG = 4096 * 0.087


def _read_platform(path: Path, d: dict[str, Any]) -> Recording:
    """GimbalPlatform (pabloramesc), ``matlab/datasets/platform/*.mat``: ``data`` N x 14 from the servo gimbal.

    Layout, from the repository (TFG_platformController.ino ``send_data_serial``, which prints t, angx,
    angy, angz and then the IMU line of arduino/ArduinoBLE33_controller.ino ``send_sample``; the column
    names of matlab/data_grapher.m and matlab/compute_attitude.m), 0-based columns:

    0 ``t`` [s] Arduino UNO ``millis()/1000`` when the line was sent;
    1 ``tx`` [deg] inner (x) stage, AS5600 encoder reading - 187 (measured);
    2 ``ty`` [deg] middle (y) stage, AS5600 encoder reading - 169 (measured);
    3 ``tz`` [deg] outer (z) stage: the servo *command* - 90 (the firmware does not read the z encoder);
    4-6 ``ax ay az`` [g], 7-9 ``gx gy gz`` [deg/s], 10-12 ``mx my mz`` [uT] (LSM9DS1 raw axes, Arduino_LSM9DS1);
    13 ``dt`` [ms] the BLE33's time between its own samples.

    Frames. The source's scripts compare ``[tx ty -tz]`` with the ZYX (roll, pitch, yaw) of the IMU in
    its "NED frame" ``acc = [ax ay -az]``, ``gyr = [gx gy -gz]``, ``mag = [-mx my -mz]``
    (compute_attitude.m). That frame is right-handed: the LSM9DS1's accelerometer/gyro axes as read form
    a left-handed set and its magnetometer's x axis points against theirs (the chip's known quirk, and
    what these transforms undo). So we take the body frame b = the source's NED frame (z down when
    level), store acc, mag and gyro in it, and set phi_t = tx, theta_t = ty, psi_t = -tz (outer z, middle
    y, inner x, right-handed about z down: PHYSICS.md), which is how the gimbal is nested (z servo on the
    base, then y, then x carrying the IMU: the source compares its angles with ZYX Euler angles).
    The measured x and y angles are rescaled by :data:`AS5600_SCALE`; the raw angles are kept as extra
    columns ``enc_x, enc_y, enc_z``. The firmware sends its first samples (at least 100) before it moves
    the servos, with all angles set to 0 rather than read; the leading rows whose three angles are
    exactly 0 are labelled step ``origin_hold`` (the servos held at their origin), the rest ``platform``.
    """
    data = _array(path, d, "data", 14)
    _finite_rows(path, data)
    t_s = data[:, 0]
    back = np.flatnonzero(np.diff(t_s) < 0)
    if back.size:
        raise _fail(path, f"column 0 (t, s) decreases at row {int(back[0]) + 2} "
                          f"({t_s[back[0] + 1]:g} < {t_s[back[0]]:g})")
    enc = data[:, 1:4]
    # the firmware angle jumps by one encoder turn when the reading wraps; an encoder does not
    tx = np.unwrap(enc[:, 0], period=AS5600_WRAP_DEG) * AS5600_SCALE
    ty = np.unwrap(enc[:, 1], period=AS5600_WRAP_DEG) * AS5600_SCALE
    tz = enc[:, 2]
    zero = np.all(enc == 0.0, axis=1)
    n_hold = int(np.argmin(zero)) if not zero.all() else len(zero)
    step = np.where(np.arange(len(t_s)) < n_hold, "origin_hold", "platform")
    acc_b, gyr_b, mag_b = _lsm9ds1_axes(data[:, 4:7], data[:, 7:10], data[:, 10:13])
    dt = np.diff(t_s)
    meta = {
        "source_file": path.name,
        "source": "pabloramesc/GimbalPlatform, matlab/datasets/platform/*.mat (MIT)",
        "sensor": "LSM9DS1 (Arduino Nano 33 BLE Sense) on a three-axis servo gimbal with AS5600 encoders",
        "mag_unit": MAG_UNIT, "acc_unit": ACC_UNIT, "gyro_unit": GYRO_UNIT,
        "sample_rate_hz": f"{1.0 / float(np.median(dt[dt > 0])):.3f}" if (dt > 0).any() else "unknown",
        "time_source": "t = column 0 (Arduino UNO millis()/1000) - its first value",
        # "turntable": the gimbal is a nested three-axis mechanism like ours and these are its own stage
        # angles, so what the analyser tests only on a table exists here and is worth testing: iron
        # riding on a stage (the servo motors and the encoder magnets move with the stages), axis
        # non-perpendicularity, encoder zeros. (BROAD's optical reference tracks a hand-held unit: no
        # stages.) The z angle is the servo command, not a measurement: servo lag and dead band show as
        # angle error about z, which the metadata says.
        "attitude_source": "turntable",
        "angle_sources": "phi_t, theta_t: AS5600 magnetic encoders on the x and y stages (measured); psi_t: "
                         "the z servo command (not measured, lags the stage)",
        "angles": "phi_t = tx * 1.0102, theta_t = ty * 1.0102, psi_t = -tz (file columns 1, 2, 3); outer z, "
                  "middle y, inner x; body frame b = the source's NED frame (acc [ax ay -az], mag [-mx my -mz], "
                  "gyro [gx gy -gz] of the LSM9DS1 as read); 1.0102 = (360/4096)/0.087 undoes the firmware's "
                  "encoder scale",
        "axes": LSM9DS1_AXES,
        "origin_hold_rows": str(n_hold),
        "steps": "origin_hold: leading rows whose angles the firmware set to 0 before moving the servos "
                 "(not read); platform: the rest",
    }
    extra = {**_extra(gyr_b), **_extra(enc, ("enc_x", "enc_y", "enc_z")),
             "dt_imu_ms": [f"{v:g}" for v in data[:, 13]]}
    return _build(path, t=t_s - t_s[0], step=step, mag=mag_b * MAG_COUNTS_PER_UT, acc=acc_b * ACC_LSB_PER_G,
                  angles=(-tz, ty, tx), meta=meta, extra=extra)


def _read_compass_buffer(path: Path, d: dict[str, Any]) -> Recording:
    """sunsided/sensor-fusion ``hmc5883l_compass.mat``: ``compassBuffer`` N x 4 = t [s], x, y, z [gauss]
    (data/export_data.m names the columns sec, compass_x, compass_y, compass_z). MATLAB v7.3 files."""
    buf = np.asarray(d["compassBuffer"], dtype=float)
    if buf.ndim == 2 and buf.shape[1] != 4 and buf.shape[0] == 4:
        buf = buf.T  # written 4 x N: one row per quantity
    if buf.ndim != 2 or buf.shape[1] != 4:
        raise _fail(path, f"variable 'compassBuffer' has shape {buf.shape}, expected (N, 4) = t, x, y, z")
    _finite_rows(path, buf, "compassBuffer")
    t = buf[:, 0]
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        raise _fail(path, f"compassBuffer column 0 (t, s) decreases at row {int(back[0]) + 2}")
    dt = np.diff(t)
    meta = {
        "source_file": path.name,
        "source": "sunsided/sensor-fusion, data/set-*/*/hmc5883l_compass.mat (EUPL-1.2)",
        "sensor": "Honeywell HMC5883L",
        "mag_unit": MAG_UNIT,
        "mag_file_unit": "gauss (1 G = 100 uT = 10000 counts here)",
        "sample_rate_hz": f"{1.0 / float(np.median(dt[dt > 0])):.3f}" if (dt > 0).any() else "unknown",
        "time_source": "t = compassBuffer column 0 (s) - its first value",
        "t0_file_s": f"{t[0]:.6f}",
        "note": "hand-turned (the set's folder name says which axis); no heading reference",
    }
    return _build(path, t=t - t[0], step=np.full(len(t), "data"), mag=buf[:, 1:4] * 100.0 * MAG_COUNTS_PER_UT,
                  meta=meta)


def quaternion_matrix(q: np.ndarray, order: str = "wxyz") -> np.ndarray:
    """(N, 3, 3) active rotation matrices of unit quaternions (Hamilton), components in ``order``
    ("wxyz" or "xyzw"); the quaternions are normalised first."""
    q = np.asarray(q, dtype=float)
    if order == "xyzw":
        q = q[:, [3, 0, 1, 2]]
    elif order != "wxyz":
        raise ValueError(f"quaternion order must be 'wxyz' or 'xyzw', got {order!r}")
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def table_angles(C_Lb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(psi_t, theta_t, phi_t) in degrees of attitudes C_Lb: their ZYX Euler angles (an ideal table's
    encoder angles), psi_t and phi_t unwrapped so they move continuously as encoder readings do."""
    psi, theta, phi = yaw_pitch_roll(C_Lb)
    return (np.degrees(np.unwrap(np.radians(psi))), theta, np.degrees(np.unwrap(np.radians(phi))))


def _from_sequence(angles: tuple[np.ndarray, np.ndarray, np.ndarray], sequence: str) -> tuple[tuple[np.ndarray, ...], str]:
    """Table angles (psi_t, theta_t, phi_t, deg) of attitudes given as angles about z, y and x (deg)
    composed in ``sequence`` (scipy's convention: upper case intrinsic, lower case extrinsic), and a
    note of the conversion for the metadata."""
    about = dict(zip("zyx", angles))
    C = Rotation.from_euler(sequence, np.column_stack([about[a] for a in sequence.lower()]), degrees=True).as_matrix()
    kind = "intrinsic: C_Lb = " if sequence.isupper() else "extrinsic, about the lab's axes: C_Lb = "
    product = " ".join(f"R{a}" for a in (sequence.lower() if sequence.isupper() else sequence.lower()[::-1]))
    return table_angles(C), (f"the file's angles compose C_Lb in the sequence {sequence} ({kind}{product}); "
                             "psi_t, theta_t, phi_t are its ZYX Euler angles, psi_t and phi_t unwrapped")


def broad_attitude(quat_wxyz: np.ndarray) -> np.ndarray:
    """C_Lb (N, 3, 3) in our lab frame L = NED from BROAD's ``opt_quat`` ([w, x, y, z], IMU -> ENU).

    BROAD's quaternion maps IMU coordinates to ENU: ``v_ENU = R(q) v_IMU``. Checked on the data: at rest
    ``R(q) acc`` is (0.00, 0.03, 9.89) m/s^2 (up, as a specific force at rest must be) in file 01 and
    (0.02, -0.02, 9.82) in file 05, while the transpose gives (0.02, 0.17, 5.2) with a spread of 3-6
    m/s^2; and ``R(q) mag`` is a constant field pointing north (azimuth -2.6 and -0.2 deg from +y_ENU)
    and down with dip 70.2 and 69.3 deg (Berlin: about 68 deg). So ``C_Lb = T_NED<-ENU R(q)``, and the
    accelerometer at rest reads ``C_Lb^T [0, 0, -1] g`` (PHYSICS.md's f_b) to within its calibration.
    """
    R = quaternion_matrix(quat_wxyz, "wxyz")  # the active rotation of the unit quaternion (Hamilton)
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
    # unwrapped so the angles move continuously (a table encoder does not jump from +180 to -180)
    psi, theta, phi = table_angles(broad_attitude(quat[keep]))

    mag_counts = mag * MAG_COUNTS_PER_UT
    repeats = float(np.mean(np.all(np.diff(mag, axis=0) == 0, axis=1)))
    meta = {
        "source_file": path.name,
        "source": f"dlaidig/broad, {'data_hdf5' if path.suffix.lower() in HDF5_SUFFIXES else 'data_mat'} "
                  "(CC-BY-4.0; Laidig, Caruso, Cereatti, Seel, Data 6(7) 2021)",
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


# --------------------------------------------------------------------------------------------------
# Mapping files: anything else
# --------------------------------------------------------------------------------------------------

#: Microtesla per file unit of the magnetometer.
MAG_UNITS = {"uT": 1.0, "nT": 1e-3, "mT": 1e3, "T": 1e6, "gauss": 100.0, "G": 100.0, "mgauss": 0.1, "mG": 0.1}
#: g per file unit of the accelerometer.
ACC_UNITS = {"g": 1.0, "mg": 1e-3, "m/s^2": 1.0 / STANDARD_G, "m/s2": 1.0 / STANDARD_G}
#: deg/s per file unit of the gyro.
GYRO_UNITS = {"deg/s": 1.0, "dps": 1.0, "rad/s": 180.0 / math.pi}
#: Seconds per file unit of the time (or interval) column.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
#: A unit a time column's name may end in, and the TIME_UNITS key it means.
TIME_NAMES = {"ms": "ms", "msec": "ms", "millis": "ms", "milliseconds": "ms", "us": "us", "usec": "us",
              "micros": "us", "microseconds": "us", "ns": "ns", "nanos": "ns", "sec": "s", "seconds": "s"}
_TIME_UNIT_IN_NAME = re.compile(r"(" + "|".join(sorted(TIME_NAMES, key=len, reverse=True)) + r")\W*$")
ANGLE_UNITS = {"deg": 1.0, "rad": 180.0 / math.pi}
#: deg C = file value + offset.
TEMP_UNITS = {"C": 0.0, "K": -273.15}
FORMATS = ("csv", "mat", "hdf5")
#: At most this many problems are listed in one error message.
MAX_PROBLEMS = 20

_GROUP_COLUMNS = {"mag": ("mx", "my", "mz"), "acc": ("ax", "ay", "az"), "gyro": ("gx", "gy", "gz"),
                  "angles": ("psi_t", "theta_t", "phi_t")}
_COLUMN_GROUP = {c: g for g, cols in _GROUP_COLUMNS.items() for c in cols} | {
    "t": "time", "dt": "time", "temp_c": "temperature", "step": "step"}
ColumnSpec = str | int


def _check(ok: Callable[[Any], Any], problem: str) -> BeforeValidator:
    """Refuse a mapping value as given unless ``ok(v)``: ``problem``, formatted with the value as ``v``."""
    def check(v: Any) -> Any:
        if not ok(v):
            raise ValueError(problem.format(v=v))
        return v
    return BeforeValidator(check)


def _one_of(choices: Iterable[str], more: str = "") -> BeforeValidator:
    accepted = tuple(choices)
    return _check(lambda v: isinstance(v, str) and v in accepted,
                  "{v!r} is not known; accepted: " + ", ".join(accepted) + more)


def _unit_or_factor(units: dict[str, float]) -> BeforeValidator:
    """One of ``units``, "counts" (kept as they are) or a number: counts per file unit."""
    known = _one_of([*units, "counts"], ", or a number (counts per file unit)").func
    def check(v: Any) -> str | float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return known(v)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"as a factor (counts per file unit) must be positive, got {v!r}")
        return float(v)
    return BeforeValidator(check)


def _column(value: Any) -> ColumnSpec:
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise ValueError(f"must be a column name (text) or a 0-based index, got {value!r}")
    if isinstance(value, int) and value < 0:
        raise ValueError(f"must be a 0-based index (>= 0), got {value}")
    if isinstance(value, str) and not value.strip():
        raise ValueError("is empty")
    return value


def _axes(value: Any) -> list[tuple[int, float]]:
    """``["y", "-x", "z"]``: our x is the file's y, our y minus the file's x, our z the file's z."""
    if not isinstance(value, list) or len(value) != 3:
        raise ValueError(f"must list 3 axes such as [\"y\", \"-x\", \"z\"], got {value!r}")
    out = []
    for a in value:
        s = a.strip().lower() if isinstance(a, str) else ""
        if s.lstrip("+-") not in ("x", "y", "z"):
            raise ValueError(f"{a!r} is not an axis (x, y, z with an optional sign)")
        out.append(("xyz".index(s.lstrip("+-")), -1.0 if s.startswith("-") else 1.0))
    if len({i for i, _ in out}) != 3:
        raise ValueError(f"must use each of x, y, z once, got {value!r}")
    return out


Column = Annotated[ColumnSpec | None, BeforeValidator(_column)]  # None: not given (refused as a value)
Text = Annotated[str, _check(lambda v: isinstance(v, str) and v.strip(), "must be text, got {v!r}")]
_GIVEN = _check(lambda v: v is not None, "must be given a value, got None")  # (TOML cannot write None)


class _Strict(BaseModel):
    # strict: a value of the wrong TOML type is refused, never converted (true is not 1, "3" is not 3)
    model_config = ConfigDict(extra="forbid", strict=True)


class FileTable(_Strict):
    format: Annotated[str | None, _one_of(FORMATS)] = None
    delimiter: Annotated[str, _check(lambda d: isinstance(d, str) and (d == "whitespace" or len(d) == 1),
                                     'must be one character or "whitespace", got {v!r}')] = ","
    skip_rows: Annotated[int, Field(ge=0)] = 0
    header: bool = True
    comment: str = "#"
    variable: Annotated[str | None, _GIVEN] = None
    step: Annotated[str, _check(lambda v: isinstance(v, str) and v.strip() and "\n" not in v,
                                "must be a non-empty label on one line, got {v!r}")] = "data"


#: [columns]: key -> the file's column (header name or 0-based index).
Columns = create_model("Columns", __base__=_Strict, **{  # type: ignore[call-overload]
    k: (Column, None) for k in ("t", "dt", "step", *(c for cols in _GROUP_COLUMNS.values() for c in cols), "temp_c")})


class TimeTable(_Strict):
    unit: Annotated[str, _one_of(TIME_UNITS)] = "s"
    rate_hz: Annotated[float | None, _GIVEN, Field(gt=0, allow_inf_nan=False)] = None
    start_at_zero: bool = True


class _Sensor(_Strict):
    """[mag], [acc], [gyro]: the file's unit and the order and signs of its axes."""

    unit: Any
    axes: Annotated[list[str], _check(_axes, "")] = ["x", "y", "z"]  # _axes names the problem itself


class MagTable(_Sensor):
    unit: Annotated[str | float, _unit_or_factor(MAG_UNITS)] = "uT"


class AccTable(_Sensor):
    unit: Annotated[str | float, _unit_or_factor(ACC_UNITS)] = "g"


class GyroTable(_Sensor):
    unit: Annotated[str, _one_of(GYRO_UNITS)] = "deg/s"


def _tait_bryan(v: Any) -> bool:
    return isinstance(v, str) and (v.isupper() or v.islower()) and sorted(v.lower()) == ["x", "y", "z"]


class AnglesTable(_Strict):
    unit: Annotated[str, _one_of(ANGLE_UNITS)] = "deg"
    negate: list[Annotated[str, _one_of(_GROUP_COLUMNS["angles"])]] = []
    # the order the angles compose the attitude in, as scipy's Rotation.from_euler: upper case intrinsic
    # (C_Lb = R_1 R_2 R_3), lower case extrinsic (about the lab's axes, first letter first)
    sequence: Annotated[str, _check(_tait_bryan, "{v!r} is not a rotation sequence of three different axes; e.g. "
                                                 "ZYX (ours, the default), XYZ, ZXY, or in lower case about the "
                                                 "lab's fixed axes (xyz = ZYX)")] = "ZYX"
    source: Text = "turntable"


class AttitudeTable(_Strict):
    columns: Annotated[list[Column], _check(lambda v: isinstance(v, list) and len(v) == 4,
                                            "must list the 4 quaternion columns, got {v!r}")]
    order: Annotated[str, _one_of(("wxyz", "xyzw"))] = "wxyz"
    rotation: Annotated[str, _one_of(("body_to_lab", "lab_to_body"))] = "body_to_lab"  # v_lab = R(q) v_body
    frame: Annotated[str, _one_of(LAB_FRAMES)] = "NED"
    source: Text = "attitude reference (quaternion)"


class TempTable(_Strict):
    unit: Annotated[str, _one_of(TEMP_UNITS)] = "C"


class Mapping(_Strict):
    """A parsed, checked mapping file (see examples/mapping.toml); :func:`load_mapping` builds it."""

    file: FileTable = FileTable()
    columns: Columns = Columns()  # type: ignore[valid-type]
    time: TimeTable = TimeTable()
    mag: MagTable = MagTable()
    acc: AccTable = AccTable()
    gyro: GyroTable = GyroTable()
    angles: AnglesTable = AnglesTable()
    attitude: Annotated[AttitudeTable | None, _GIVEN] = None
    temp: TempTable = TempTable()
    meta: dict[str, Any] = {}  # any key
    _name: str = PrivateAttr("mapping")  # the mapping file's name

    @property
    def given(self) -> dict[str, ColumnSpec]:
        """The columns the mapping names: key -> header name or 0-based index."""
        return {k: v for k, v in self.columns if v is not None}

    @field_validator("mag", "acc", "gyro", "angles", mode="before")
    @classmethod
    def _needs_its_columns(cls, value: Any, info: ValidationInfo) -> Any:
        # before the table's own keys: a table for columns that are not there is the problem, whatever it says
        keys, columns = _GROUP_COLUMNS[str(info.field_name)], info.data.get("columns")  # absent if refused
        # (only when none is given: one missing of three is the whole check's "columns.mx not given")
        if isinstance(value, dict) and value and columns is not None and all(getattr(columns, k) is None for k in keys):
            raise ValueError(f"is given but columns.{', columns.'.join(keys)} are not")
        return value

    @field_validator("meta")
    @classmethod
    def _single_lines(cls, meta: dict[str, Any]) -> dict[str, str]:
        for key, value in meta.items():
            if isinstance(value, (dict, list)) or ":" in key or "\n" in f"{key}{value}":
                raise ValueError(f"{key!r}: keys and values must be single-line text without ':' in the key")
        return {key: str(value) for key, value in meta.items()}

    @model_validator(mode="after")
    def _whole(self) -> Mapping:
        given = self.given
        for group, keys in _GROUP_COLUMNS.items():
            if 0 < len(missing := [k for k in keys if k not in given]) < 3:
                raise ValueError(f"columns.{', columns.'.join(missing)} not given: {group} needs all three columns "
                                 f"({', '.join(keys)}) or none")
        if "mx" not in given:
            raise ValueError("columns.mx, columns.my and columns.mz (the magnetometer) are required")
        bases = [b for b, present in (("columns.t", "t" in given), ("columns.dt", "dt" in given),
                                      ("time.rate_hz", self.time.rate_hz is not None)) if present]
        if len(bases) != 1:
            raise ValueError("give exactly one time base: columns.t (a time column), columns.dt (the interval "
                             "since the previous sample) or time.rate_hz (a constant rate); "
                             + (f"got {', '.join(bases)}" if bases else "got none"))
        if self.attitude is not None and "psi_t" in given:
            raise ValueError("give either angle columns (columns.psi_t, theta_t, phi_t) or [attitude], not both")
        for key, spec in given.items():  # one file column read as two kinds of quantity is a slip in the mapping
            first = next(k for k, v in given.items() if v == spec and type(v) is type(spec))
            if _COLUMN_GROUP[first] != _COLUMN_GROUP[key]:
                raise ValueError(f"columns.{first} and columns.{key} both name column {spec!r}: each quantity needs "
                                 "a column of its own")
        return self


#: The keys a mapping accepts, per table ("" is the top level; [meta] takes any key).
MAPPING_KEYS: dict[str, tuple[str, ...]] = {"": tuple(Mapping.model_fields)} | {
    table: tuple(model.model_fields) for table, model in (
        ("file", FileTable), ("columns", Columns), ("time", TimeTable), ("mag", MagTable), ("acc", AccTable),
        ("gyro", GyroTable), ("angles", AnglesTable), ("attitude", AttitudeTable), ("temp", TempTable))}
#: How pydantic's own refusals read in a mapping error (then ", got <the value>", but for a missing key).
_PROBLEMS = {"string_type": "must be text", "bool_type": "must be true or false", "int_type": "must be a whole number",
             "float_type": "must be a number", "finite_number": "must be a finite number",
             "greater_than": "must be a number > {gt:g}", "greater_than_equal": "must be >= {ge:g}",
             "list_type": "must be a list", "model_type": "must be a table", "dict_type": "must be a table",
             "missing": "is required"}


def _problem(err: ErrorDetails) -> str:
    """One refusal as ``key.path problem``: ``file.delimiter must be ...``, ``[mag] is given but ...``."""
    loc, kind = err["loc"], err["type"]
    if kind == "extra_forbidden":
        table = ".".join(map(str, loc[:-1]))
        return (f"unknown key {loc[-1]!r} in {f'[{table}]' if table else 'the top level'}; "
                f"accepted keys: {', '.join(MAPPING_KEYS[table])}")
    path = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")
    if kind in _PROBLEMS:
        problem = _PROBLEMS[kind].format(**err.get("ctx", {})) + ("" if kind == "missing" else f", got {err['input']!r}")
    else:  # ValueError: a check of ours
        problem = str(err["ctx"]["error"]) if kind == "value_error" else err["msg"]
    return f"{f'[{path}]' if len(loc) == 1 else path} {problem}".strip()


def load_mapping(mapping: Path | str | dict[str, Any]) -> Mapping:
    """Read and check a mapping (a TOML file's path, or its parsed content); see examples/mapping.toml.

    Every problem is a RecordingFileError naming the mapping file and the key (all of them at once, ';'
    between): unknown keys are refused with the accepted ones listed, so a misspelt key never passes silently.
    """
    if isinstance(mapping, dict):
        name, raw = "mapping", mapping
    else:
        mpath = Path(mapping)
        name = mpath.name
        try:
            raw = tomllib.loads(mpath.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise RecordingFileError(f"{name}: mapping file not found") from None
        except (OSError, UnicodeDecodeError) as e:
            raise RecordingFileError(f"{name}: cannot read the mapping file ({e})") from None
        except tomllib.TOMLDecodeError as e:
            raise RecordingFileError(f"{name}: not valid TOML: {e}") from None
    try:
        m = Mapping.model_validate(raw)
    except ValidationError as e:
        where = f"{name}: mapping" if name != "mapping" else "mapping"  # a dict has no file name to show
        raise RecordingFileError(f"{where}: " + "; ".join(_problem(err) for err in e.errors())) from None
    m._name = name
    return m


class _Table:
    """The mapped file's rows: one float array per column key, labels for messages."""

    def __init__(self, n: int, where: list[str], labels: dict[str, str], rows: list[int] | np.ndarray) -> None:
        self.n = n
        self.where = where  # "line 17" / "row 5" for each kept row
        self.rows = np.asarray(rows, dtype=int)  # the 0-based data row of the file of each kept row
        self.labels = labels  # column key -> how the message names the column ("'Bx'", "3 ('Bx')")
        self.values: dict[str, np.ndarray] = {}
        self.skipped = 0


def _label(spec: ColumnSpec, header: list[str] | None) -> str:
    if isinstance(spec, int):
        return f"{spec} ({header[spec]!r})" if header is not None and spec < len(header) else str(spec)
    return repr(spec)


def _needed(m: Mapping) -> list[tuple[str, ColumnSpec, str]]:
    """(key, the file's column, the key's group) of every column to read."""
    need = m.given | ({f"q{i}": c for i, c in enumerate(m.attitude.columns)} if m.attitude is not None else {})
    return [(key, spec, _COLUMN_GROUP.get(key, "attitude")) for key, spec in need.items()]


#: Columns that may hold empty or NaN cells (RECORDING.md: acc and temp_c may be empty); the quaternion
#: may be missing where the reference lost track (those rows are dropped and counted).
_OPTIONAL = ("ax", "ay", "az", "gx", "gy", "gz", "temp_c", "q0", "q1", "q2", "q3")


def _split(m: Mapping, line: str) -> list[str]:
    if m.file.delimiter == "whitespace":
        return line.split()
    return next(csv.reader([line], delimiter=m.file.delimiter))


def _csv_table(path: Path, m: Mapping, skip_bad_rows: bool) -> _Table:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise _fail(path, f"not UTF-8 text ({e.reason} at byte {e.start + 1}, counting from 1); for a .mat/.hdf5 file set "
                          "file.format in the mapping") from None
    lines = text.splitlines()
    if m.file.skip_rows >= len(lines):
        raise _fail(path, f"mapping: file.skip_rows = {m.file.skip_rows} but the file has {len(lines)} line(s)")
    header: list[str] | None = None
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in enumerate(lines[m.file.skip_rows:], start=m.file.skip_rows + 1):
        if not line.strip() or (m.file.comment and line.lstrip().startswith(m.file.comment)):
            continue
        cells = [c.strip() for c in _split(m, line)]
        if m.file.header and header is None:
            header = cells
            continue
        rows.append((lineno, cells))
    if m.file.header and header is None:
        raise _fail(path, f"mapping: file.header = true but no header line after the first {m.file.skip_rows} line(s)")
    index: dict[str, int] = {}
    labels: dict[str, str] = {}
    for key, spec, group in _needed(m):
        if isinstance(spec, str):
            if header is None:
                raise _fail(path, f"mapping: {group} column {spec!r} ({key}) is given by name but file.header = "
                                  "false: give its 0-based index")
            if spec not in header:
                raise _fail(path, f"mapping: {group} column {spec!r} ({key}) not found in header "
                                  f"[{', '.join(header)}]")
            if header.count(spec) > 1:  # which one is meant cannot be guessed
                at = [str(i) for i, h in enumerate(header) if h == spec]
                raise _fail(path, f"mapping: {group} column {spec!r} ({key}) appears {len(at)} times in the header "
                                  f"(0-based columns {', '.join(at)}): give the 0-based index of the one meant")
            index[key] = header.index(spec)
        else:
            if header is not None and spec >= len(header):
                raise _fail(path, f"mapping: {group} column {spec} ({key}) is beyond the header's {len(header)} "
                                  f"columns [{', '.join(header)}]")
            index[key] = spec
        labels[key] = _label(spec, header)
    for key, i in index.items():  # one file column read as two kinds of quantity is a slip in the mapping
        first = next(k for k, j in index.items() if j == i)
        if _COLUMN_GROUP.get(first, "attitude") != _COLUMN_GROUP.get(key, "attitude"):
            raise _fail(path, f"mapping: columns.{first} and columns.{key} both name column {labels[key]}: "
                              "each quantity needs a column of its own")

    problems: list[str] = []
    bad_rows = 0
    where: list[str] = []
    kept: list[int] = []
    cells_out: dict[str, list[Any]] = {k: [] for k in index}
    for data_row, (lineno, cells) in enumerate(rows):
        row_problems = []
        if header is not None and len(cells) > len(header):  # a shifted or merged line: its cells cannot be trusted
            row_problems.append(f"line {lineno}: {len(cells)} fields, the header has {len(header)}")
        parsed: dict[str, Any] = {}
        for key, i in index.items():
            if i >= len(cells):
                row_problems.append(f"column {labels[key]} line {lineno}: missing (the row has {len(cells)} fields)")
                continue
            cell = cells[i]
            if key == "step":
                if not cell:
                    row_problems.append(f"column {labels[key]} line {lineno}: empty step label")
                parsed[key] = cell
                continue
            if cell == "" and key in _OPTIONAL:
                parsed[key] = math.nan
                continue
            try:
                v = float(cell)
            except ValueError:
                row_problems.append(f"column {labels[key]} line {lineno}: not a number ({cell!r})")
                continue
            if math.isinf(v) or (math.isnan(v) and key not in _OPTIONAL):
                row_problems.append(f"column {labels[key]} line {lineno}: not finite ({cell!r})")
                continue
            parsed[key] = v
        if row_problems:
            problems.extend(row_problems)
            bad_rows += 1
            continue
        where.append(f"line {lineno}")
        kept.append(data_row)
        for key, v in parsed.items():
            cells_out[key].append(v)
    if problems and not skip_bad_rows:
        more = f"\n... and {len(problems) - MAX_PROBLEMS} more" if len(problems) > MAX_PROBLEMS else ""
        raise _fail(path, f"{len(problems)} problem(s) in {bad_rows} row(s) of the mapped columns:\n"
                          + "\n".join(problems[:MAX_PROBLEMS]) + more)
    table = _Table(len(where), where, labels, kept)
    table.skipped = bad_rows
    for key, values in cells_out.items():
        table.values[key] = np.array(values, dtype=object if key == "step" else float)
    return table


def _array_table(path: Path, m: Mapping, fmt: str, skip_bad_rows: bool) -> _Table:
    if fmt == "mat":
        import scipy.io

        try:
            d: dict[str, Any] = scipy.io.loadmat(str(path))
        except NotImplementedError:
            d = _load_hdf5(path, matlab=True)
        except Exception as e:
            raise _fail(path, f"not a readable MATLAB .mat file ({type(e).__name__}: {e})") from None
    else:
        d = _load_hdf5(path, matlab=False)
    names = sorted(k for k in d if not k.startswith("__"))
    table_var = None
    if m.file.variable is not None:
        if m.file.variable not in d:
            raise _fail(path, f"mapping: file.variable {m.file.variable!r} not found; the file holds [{', '.join(names)}]")
        table_var = np.asarray(d[m.file.variable], dtype=float)
        if table_var.ndim == 1:
            table_var = table_var[:, None]
        if table_var.ndim != 2:
            raise _fail(path, f"mapping: variable {m.file.variable!r} has shape {table_var.shape}, expected 2-D (rows, columns)")
    cols: dict[str, np.ndarray] = {}
    labels: dict[str, str] = {}
    for key, spec, group in _needed(m):
        if isinstance(spec, int):
            if table_var is None:
                raise _fail(path, f"mapping: {group} column {spec} ({key}) is an index but file.variable is not set; "
                                  f"the file holds [{', '.join(names)}]")
            if spec >= table_var.shape[1]:
                raise _fail(path, f"mapping: {group} column {spec} ({key}) is beyond variable {m.file.variable!r} with "
                                  f"{table_var.shape[1]} columns")
            col = table_var[:, spec]
            labels[key] = f"{m.file.variable}[{spec}]"
        else:
            var, _, rest = spec.partition("[")
            if var not in d:
                raise _fail(path, f"mapping: {group} column {spec!r} ({key}) not found; the file holds "
                                  f"[{', '.join(names)}]")
            a = np.asarray(d[var], dtype=float)
            if a.ndim == 2 and a.shape[1] == 1:
                a = a[:, 0]
            if rest:
                try:
                    k = int(rest.rstrip("]"))
                except ValueError:
                    raise _fail(path, f"mapping: {group} column {spec!r} ({key}): write 'name[k]' with a 0-based "
                                      "column number k") from None
                if a.ndim != 2 or not 0 <= k < a.shape[1]:
                    raise _fail(path, f"mapping: {group} column {spec!r} ({key}): variable {var!r} has shape "
                                      f"{a.shape}, no column {k}")
                col = a[:, k]
            elif a.ndim != 1:
                raise _fail(path, f"mapping: {group} column {spec!r} ({key}): variable {var!r} has shape {a.shape}; "
                                  f"name one column as '{var}[k]'")
            else:
                col = a
            labels[key] = repr(spec)
        cols[key] = col
    lengths = {len(v) for v in cols.values()}
    if len(lengths) > 1:
        desc = ", ".join(f"{labels[k]} {len(v)}" for k, v in cols.items())
        raise _fail(path, f"mapping: the mapped columns differ in length (rows: {desc})")
    n = lengths.pop() if lengths else 0
    bad = np.zeros(n, dtype=bool)
    problems = []
    for key, col in cols.items():
        if key == "step":
            continue
        wrong = np.isinf(col) | (np.isnan(col) if key not in _OPTIONAL else False)
        for i in np.flatnonzero(wrong)[:MAX_PROBLEMS]:
            problems.append(f"column {labels[key]} row {i + 1}: not finite ({col[i]})")
        bad |= wrong
    if problems and not skip_bad_rows:
        raise _fail(path, f"{int(bad.sum())} row(s) with non-finite values in the mapped columns:\n"
                          + "\n".join(problems[:MAX_PROBLEMS]))
    keep = np.flatnonzero(~bad)
    table = _Table(len(keep), [f"row {i + 1}" for i in keep], labels, keep)
    table.skipped = int(bad.sum())
    for key, col in cols.items():
        if key == "step":
            table.values[key] = np.array([f"{v:g}" for v in col[keep]], dtype=object)
        else:
            table.values[key] = col[keep]
    return table


def _to_counts(values: np.ndarray, unit: str | float, physical: dict[str, float], counts_per: float) -> np.ndarray:
    if unit == "counts":
        return values
    if isinstance(unit, float):
        return values * unit
    return values * physical[unit] * counts_per


def _unit_text(unit: str | float, nominal: str) -> str:
    if unit == "counts":
        return "raw counts (as in the file)"
    if isinstance(unit, float):
        return f"file value x {unit:g} (counts per file unit, from the mapping)"
    return nominal


def _oriented(values: np.ndarray, axes: list[tuple[int, float]]) -> np.ndarray:
    return np.column_stack([sign * values[:, i] for i, sign in axes])


def _one_column_per_quantity(path: Path, tab: _Table) -> None:
    """Refuse one column read as two quantities of a kind (two angles, two axes) unless it is constant:
    a column of zeros may stand for the axes a table lacks, a changing one is a slip in the mapping."""
    keys = [k for k in tab.values if k != "step"]
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            if tab.labels[a] == tab.labels[b] and np.nanmax(tab.values[a]) > np.nanmin(tab.values[a]):
                raise _fail(path, f"mapping: columns.{a} and columns.{b} both name column {tab.labels[a]}, whose "
                                  "values change: each needs a column of its own (one column may stand for two "
                                  "only when it is constant, e.g. zeros for the axes a table lacks)")


def _read_mapped(path: Path, m: Mapping, skip_bad_rows: bool) -> Recording:
    """Read ``path`` as ``m`` says; see :func:`load_mapping`."""
    fmt = m.file.format or ("mat" if path.suffix.lower() == ".mat" else
                       "hdf5" if path.suffix.lower() in HDF5_SUFFIXES else "csv")
    tab = _csv_table(path, m, skip_bad_rows) if fmt == "csv" else _array_table(path, m, fmt, skip_bad_rows)
    if tab.n == 0:
        raise _fail(path, "mapping: no data rows" + (f" ({tab.skipped} bad row(s) skipped)" if tab.skipped else ""))
    v = tab.values
    _one_column_per_quantity(path, tab)
    keep = np.ones(tab.n, dtype=bool)
    meta: dict[str, str] = {"source_file": path.name, "mapping": m._name}

    # time base
    scale = TIME_UNITS[m.time.unit]
    for key in ("t", "dt"):
        named = _TIME_UNIT_IN_NAME.search(tab.labels.get(key, "").lower()) if key in v else None
        if named and "unit" not in m.time.model_fields_set and TIME_NAMES[named.group(1)] != "s":
            # (a column "tms" read as seconds made a 106,050-s recording of a two-minute one, unsaid)
            unit = TIME_NAMES[named.group(1)]
            words = {"ms": "milliseconds", "us": "microseconds", "ns": "nanoseconds"}[unit]
            raise _fail(path, f"mapping: column {tab.labels[key]} is named like a time in {words}, and [time] gives no "
                              f'unit (seconds by default): say unit = "{unit}" in [time] (or unit = "s" if it is seconds)')
    if "t" in v:
        t = v["t"] * scale
        back = np.flatnonzero(np.diff(t) < 0)
        if back.size:
            i = int(back[0]) + 1
            raise _fail(path, f"column {tab.labels['t']} {tab.where[i]}: time goes backwards "
                              f"({v['t'][i]:g} after {v['t'][i - 1]:g} {m.time.unit})")
        meta["time_source"] = f"t = column {tab.labels['t']} in {m.time.unit}" + (
            " - its first value" if m.time.start_at_zero else "")
        if m.time.start_at_zero:
            meta["t0_file_s"] = f"{t[0]:.6f}"
            t = t - t[0]
    elif "dt" in v:
        dt = v["dt"] * scale
        neg = np.flatnonzero(dt[1:] < 0)
        if neg.size:
            i = int(neg[0]) + 1
            raise _fail(path, f"column {tab.labels['dt']} {tab.where[i]}: negative interval ({v['dt'][i]:g} {m.time.unit})")
        # dt is the time since the previous sample: the first row's dt reaches before the recording
        t = np.concatenate([[0.0], np.cumsum(dt[1:])])
        meta["time_source"] = (f"t = cumulative sum of column {tab.labels['dt']} ({m.time.unit}, the interval "
                               "since the previous sample), first sample at t = 0")
    else:
        assert m.time.rate_hz is not None
        t = np.arange(tab.n) / m.time.rate_hz
        meta["time_source"] = f"t = row / {m.time.rate_hz:g} Hz (constant rate from the mapping; no time column)"
        meta["sample_rate_hz"] = f"{m.time.rate_hz:g}"
    # to the nanosecond: sums and differences of decimal times carry float residue into the converted
    # file ("0.0500000000000007", "106.049999999998") that no clock had
    t = np.round(t, 9)

    def group(name: str) -> np.ndarray:
        return _oriented(np.column_stack([v[c] for c in _GROUP_COLUMNS[name]]), _axes(getattr(m, name).axes))

    mag = _to_counts(group("mag"), m.mag.unit, MAG_UNITS, MAG_COUNTS_PER_UT)
    meta["mag_unit"] = _unit_text(m.mag.unit, MAG_UNIT)
    meta["mag_axes"] = f"mx, my, mz = file {', '.join(m.mag.axes)} (from columns {', '.join(tab.labels[c] for c in _GROUP_COLUMNS['mag'])})"
    acc = None
    if "ax" in v:
        acc = _to_counts(group("acc"), m.acc.unit, ACC_UNITS, ACC_LSB_PER_G)
        meta["acc_unit"] = _unit_text(m.acc.unit, ACC_UNIT)
        meta["acc_axes"] = f"ax, ay, az = file {', '.join(m.acc.axes)}"
    extra: dict[str, list[str]] = {}
    gyro = None
    if "gx" in v:
        gyro = group("gyro") * GYRO_UNITS[str(m.gyro.unit)]
        meta["gyro_unit"] = GYRO_UNIT
        meta["gyro_axes"] = f"gx, gy, gz = file {', '.join(m.gyro.axes)}"
    temp = v["temp_c"] + TEMP_UNITS[m.temp.unit] if "temp_c" in v else None

    angles = None
    if "psi_t" in v:
        f = ANGLE_UNITS[m.angles.unit]
        psi, theta, phi = (v[c] * f * (-1.0 if c in m.angles.negate else 1.0) for c in _GROUP_COLUMNS["angles"])
        angles = (psi, theta, phi)
        # refused here, when the file is read, by the fit's own rule (it would refuse the recording later)
        found = radian_like(angles) if m.angles.unit == "deg" and tab.n >= 20 else None
        if found is not None:
            c = _GROUP_COLUMNS["angles"][found[0]]
            raise _fail(path, f"mapping: angles.unit is \"deg\", but every angle is within +-2 pi and column "
                              f"{tab.labels[c]} ({c}) spans {found[1]:.3f}: these look like radians (angles.unit = \"rad\")")
        meta["attitude_source"] = m.angles.source
        meta["angles"] = (f"psi_t (outer, z) = {'-' if 'psi_t' in m.angles.negate else ''}column {tab.labels['psi_t']}, "
                          f"theta_t (middle, y) = {'-' if 'theta_t' in m.angles.negate else ''}column {tab.labels['theta_t']}, "
                          f"phi_t (inner, x) = {'-' if 'phi_t' in m.angles.negate else ''}column {tab.labels['phi_t']}, "
                          f"file unit {m.angles.unit}")
        if m.angles.sequence not in ("ZYX", "xyz"):
            angles, note = _from_sequence(angles, m.angles.sequence)
            meta["angles"] += "; " + note
            if m.angles.source == "turntable":
                # ZYX angles computed from another nesting are no table's stages: the tests of iron or
                # errors on a stage would be made in frames that do not exist
                meta["attitude_source"] = f"turntable with its stages nested {m.angles.sequence}, not z, y, x"
    elif m.attitude is not None:
        q = np.column_stack([v[f"q{i}"] for i in range(4)])
        norm = np.linalg.norm(np.nan_to_num(q), axis=1)
        keep = np.isfinite(q).all(axis=1) & (norm > 0.5)
        if not keep.any():
            raise _fail(path, "mapping: the attitude quaternion has no valid row (columns "
                              f"{', '.join(tab.labels[f'q{i}'] for i in range(4))})")
        if not 0.9 <= float(np.median(norm[keep])) <= 1.1:  # (a temperature column as q3 was taken, normalised)
            raise _fail(path, f"mapping: the attitude quaternion's norm is {float(np.median(norm[keep])):.4g} (median "
                              "over its rows), not 1: are attitude.columns "
                              f"({', '.join(tab.labels[f'q{i}'] for i in range(4))}) the four components of a unit quaternion?")
        R = quaternion_matrix(q[keep], m.attitude.order)
        if m.attitude.rotation == "lab_to_body":
            R = np.transpose(R, (0, 2, 1))
        angles_kept = table_angles(LAB_FRAMES[m.attitude.frame] @ R)
        angles = tuple(np.full(tab.n, np.nan) for _ in range(3))  # type: ignore[assignment]
        for full, part in zip(angles, angles_kept):
            full[keep] = part
        meta["attitude_source"] = m.attitude.source
        meta["angles"] = (f"psi_t, theta_t, phi_t = ZYX Euler angles of C_Lb = T_L<-{m.attitude.frame} R(q), "
                          f"q = columns {', '.join(tab.labels[f'q{i}'] for i in range(4))} ({m.attitude.order}), "
                          f"R(q) maps {'body to lab' if m.attitude.rotation == 'body_to_lab' else 'lab to body (transposed)'}; "
                          "lab frame L = NED (x at azimuth zero, z down); psi_t and phi_t unwrapped")
        meta["dropped_rows_no_reference"] = str(int(tab.n - keep.sum()))

    step = v["step"] if "step" in v else np.full(tab.n, m.file.step, dtype=object)
    if skip_bad_rows:
        meta[SKIPPED_KEY] = str(tab.skipped)
    # the file's data rows not in the recording (malformed, or with no reference): what a message about
    # a sample counts to name its row of the file (physics.recording.file_row)
    left_out = np.ones(tab.n + tab.skipped, dtype=bool)
    left_out[tab.rows[keep]] = False
    if left_out.any():
        meta[SKIPPED_AT_KEY] = ",".join(map(str, np.flatnonzero(left_out)))
    if gyro is not None:
        extra = _extra(gyro[keep])
    meta.update(m.meta)
    return _build(path, t=t[keep], step=step[keep], mag=mag[keep], acc=None if acc is None else acc[keep],
                  angles=None if angles is None else tuple(a[keep] for a in angles),  # type: ignore[arg-type]
                  temp_c=None if temp is None else temp[keep], meta=meta, extra=extra)


#: Significant digits an imported value keeps: a unit's factor leaves noise in a double's last bits
#: (350 ms x 0.001 = 0.35000000000000003 s, 38.48 uT x 100 = 3847.9999999999995 counts), which an
#: export would print; 15 digits are far below any sensor's resolution and print as the file had them.
IMPORT_DIGITS = 15


def _tidy(values: np.ndarray | None) -> np.ndarray | None:
    """``values`` rounded to :data:`IMPORT_DIGITS` significant digits (NaN, 0 and values below 1e-8
    left alone: the powers of ten that scale them would not be exact)."""
    if values is None:
        return None
    x = np.asarray(values, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        digits = IMPORT_DIGITS - 1 - np.floor(np.log10(np.abs(x)))
    ok = np.isfinite(x) & (x != 0) & np.isfinite(digits) & (digits <= 22)  # 10**22: the last exact power of ten
    f = 10.0 ** np.where(ok, digits, 0.0)
    return np.where(ok, np.round(x * f) / f, x)


def _build(path: Path, *, t: np.ndarray, step: np.ndarray, mag: np.ndarray, meta: dict[str, str],
           acc: np.ndarray | None = None, angles: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
           temp_c: np.ndarray | None = None, extra: dict[str, list[str]] | None = None) -> Recording:
    n = len(t)
    psi, theta, phi = angles if angles is not None else (np.full(n, np.nan),) * 3
    try:
        return Recording.from_arrays(t=_tidy(t), step=step, psi_t=_tidy(psi), theta_t=_tidy(theta), phi_t=_tidy(phi),
                                     mag=_tidy(mag), acc=_tidy(acc), temp_c=_tidy(temp_c), meta=meta, extra=extra)
    except RecordingError as e:
        raise _fail(path, str(e)) from None
