"""Reading third-party recordings (service/imports.py): the files in data/real/ and bad inputs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from physics.frames import rot_x, rot_y, rot_z
from physics.recording import RecordingError, file_row, format_recording, parse_recording
from service.imports import RecordingFileError, broad_attitude, read_recording_file

REAL = Path(__file__).resolve().parent.parent / "data" / "real"
BROAD = ["broad_01_undisturbed_slow_rotation_A.mat", "broad_05_undisturbed_slow_rotation_with_breaks_B.mat"]


def test_data_files_carry_their_licences():
    readme = (REAL / "README.md").read_text()
    for name in ["qmc5883l_filtered_raw_data.csv", "gimbalplatform_ble33sense_spin_Z.mat", *BROAD]:
        assert (REAL / name).is_file() and name in readme
    assert "CC-BY-4.0" in readme and "MIT" in readme


def test_qmc_csv():
    rec = read_recording_file(REAL / "qmc5883l_filtered_raw_data.csv")
    assert len(rec) == 22745 and rec.mag.shape == (22745, 3)
    assert not rec.has_angles and rec.acc is None and rec.temp_c is None
    assert rec.t[1] == pytest.approx(0.02) and rec.t[-1] == pytest.approx(22744 / 50.0)
    assert rec.mag[0].tolist() == [6202.0, 682.0, 4812.0]  # raw counts, unchanged
    # the first 60 s (Initialization time) are the warm-up, kept and labelled
    assert (rec.step[rec.t < 60.0] == "warmup").all() and (rec.step[rec.t >= 60.0] == "data").all()
    assert np.sum(rec.step == "warmup") == 3000
    assert rec.meta["sample_rate_hz"] == "50" and rec.meta["warmup_s"] == "60"
    assert "MIT" in rec.meta["source"]


def test_gimbal_mat_units():
    rec = read_recording_file(REAL / "gimbalplatform_ble33sense_spin_Z.mat")
    raw = scipy.io.loadmat(str(REAL / "gimbalplatform_ble33sense_spin_Z.mat"))["data"]
    assert len(rec) == 3000 and not rec.has_angles
    # t from the dt column (ms), first sample at 0
    assert rec.t[0] == 0.0 and rec.t[-1] == pytest.approx(raw[1:, 0].sum() / 1000.0)
    assert np.all(np.diff(rec.t) > 0)
    # uT -> 0.01 uT counts, g -> 1/16384 g counts, gyro deg/s as extra columns; in one right-handed frame, as the
    # same chip's platform files (the LSM9DS1's accelerometer/gyro read left-handed, its magnetometer x reversed)
    assert np.allclose(rec.mag, raw[:, 7:10] * 100.0 * [-1, 1, -1])
    assert np.allclose(rec.acc, raw[:, 1:4] * 16384.0 * [1, 1, -1])
    assert np.allclose(np.asarray(rec.extra["gz"], float), -raw[:, 6], atol=1e-6)
    assert rec.meta["mag_unit"] == "0.01 uT per count" and rec.meta["gyro_unit"] == "deg/s"
    assert rec.meta["acc_unit"].startswith("1/16384 g") and rec.meta["axes"].startswith("ax, ay, az = file ax, ay, -az")
    # level: the specific force points up, -z of a z-down body frame (PHYSICS.md: at rest f = -g), about 1 g
    assert np.median(rec.acc[:, 2]) == pytest.approx(-16384 * 0.98, rel=0.01)


@pytest.mark.parametrize("name", BROAD)
def test_broad_shapes_units_and_steps(name):
    rec = read_recording_file(REAL / name)
    raw = scipy.io.loadmat(str(REAL / name))
    n_raw = len(raw["imu_mag"])
    dropped = int(rec.meta["dropped_rows_no_reference"])
    assert dropped == int(np.isnan(raw["opt_quat"]).any(axis=1).sum()) and len(rec) == n_raw - dropped
    assert rec.has_angles and np.isfinite(rec.psi_t).all() and np.isfinite(rec.theta_t).all()
    keep = ~np.isnan(raw["opt_quat"]).any(axis=1)
    assert np.allclose(rec.mag, raw["imu_mag"][keep] * 100.0)
    assert np.allclose(rec.acc, raw["imu_acc"][keep] / 9.80665 * 16384.0)
    assert np.allclose(np.asarray(rec.extra["gx"], float), np.degrees(raw["imu_gyr"][keep, 0]), atol=1e-5)
    assert np.allclose(rec.t, np.flatnonzero(keep) / raw["sampling_rate"][0, 0])
    # steps from the movement mask: rest_<k> where the mask is 0, move_<k> where it is 1
    moving = raw["movement"].ravel()[keep].astype(bool)
    assert all(s.startswith("move_") == m for s, m in zip(rec.step[::50], moving[::50]))
    assert "rest_1" in set(rec.step) and "move_1" in set(rec.step)
    # encoder-like angles: continuous (unwrapped); consecutive rows jump only near gimbal lock (pitch
    # beyond 85 deg, where ZYX heading and roll are ill-defined, as on a real three-axis table)
    near = np.diff(rec.t) < 0.01
    calm = near & (np.abs(rec.theta_t[1:]) < 85.0) & (np.abs(rec.theta_t[:-1]) < 85.0)
    for a in (rec.psi_t, rec.theta_t, rec.phi_t):
        assert np.max(np.abs(np.diff(a)[calm])) < 5.0
    assert np.max(np.abs(np.diff(rec.theta_t)[near])) < 5.0


@pytest.mark.parametrize("name", BROAD)
def test_broad_angles_agree_with_the_accelerometer_at_rest(name):
    """The table angles from the optical reference, through PHYSICS.md's platform attitude, give the
    specific force f_b = C_Lb^T [0, 0, -1]; at rest the accelerometer must point the same way, up to its
    own calibration: median within 1 deg and 95 % of rest samples within 2 deg (measured 0.35 and 0.75)."""
    rec = read_recording_file(REAL / name)
    C = rot_z(rec.psi_t) @ rot_y(rec.theta_t) @ rot_x(rec.phi_t)
    f_b = np.einsum("nji,j->ni", C, [0.0, 0.0, -1.0])
    a = rec.acc / np.linalg.norm(rec.acc, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(a * f_b, axis=1), -1, 1)))
    rest = np.array([s.startswith("rest_") for s in rec.step])
    assert rest.sum() > 10000
    assert np.median(angle[rest]) < 1.0 and np.percentile(angle[rest], 95) < 2.0
    # while moving (linear accelerations add a few deg) the right convention stays close, the transposed
    # one (quaternion read as ENU -> IMU) is far off: the check can fail. At rest the pose is near level,
    # where both conventions put gravity along z.
    q = scipy.io.loadmat(str(REAL / name))["opt_quat"]
    q = q[~np.isnan(q).any(axis=1)]
    Ct = np.transpose(broad_attitude(q), (0, 2, 1))
    f_wrong = np.einsum("nji,j->ni", Ct, [0.0, 0.0, -1.0])
    wrong = np.degrees(np.arccos(np.clip(np.sum(a * f_wrong, axis=1), -1, 1)))
    assert np.median(angle[~rest]) < 5.0 and np.median(wrong[~rest]) > 10.0


def test_broad_field_is_constant_in_the_lab_frame():
    """The magnetometer rotated into L = NED by the reference points north and down (Berlin: dip ~68 deg)."""
    rec = read_recording_file(REAL / BROAD[1])
    C = rot_z(rec.psi_t) @ rot_y(rec.theta_t) @ rot_x(rec.phi_t)
    h_L = np.einsum("nij,nj->ni", C, rec.mag)
    mean = h_L.mean(axis=0)
    dip = np.degrees(np.arctan2(mean[2], np.hypot(mean[0], mean[1])))
    azimuth = np.degrees(np.arctan2(mean[1], mean[0]))
    assert 60 < dip < 75 and abs(azimuth) < 10
    assert np.all(h_L.std(axis=0) < 0.05 * np.linalg.norm(mean))


def test_recording_csv_round_trip(tmp_path):
    rec = read_recording_file(REAL / "gimbalplatform_ble33sense_spin_Z.mat").select(slice(0, 50))
    p = tmp_path / "rec.csv"
    p.write_text(format_recording(rec))
    back = read_recording_file(p)
    assert len(back) == 50 and np.allclose(back.mag, rec.mag, atol=0.01) and not back.has_angles
    assert back.extra["gx"][:3] == rec.extra["gx"][:3] and back.meta["mag_unit"] == rec.meta["mag_unit"]


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_bad_files_give_named_errors(tmp_path):
    cases = {
        "missing.csv": None,
        "bad_fs.csv": "Fs,fast\nInitialization time,60\nmx,my,mz\n1,2,3\n",
        "bad_cols.csv": "Fs,50\nInitialization time,60\nmx,my\n1,2\n",
        "bad_row.csv": "Fs,50\nInitialization time,0\nmx,my,mz\n1,2,3\n4,x,6\n7,8,9\n",
        "empty.csv": "Fs,50\nInitialization time,0\nmx,my,mz\n",
        "ours.csv": "# compasscal-recording: 1\nt,step,psi_t\n0,a,0\n",
        "junk.mat": "this is not a MAT-file",
    }
    expect = {"missing.csv": "file not found", "bad_fs.csv": "line 1: Fs is not a number",
              "bad_cols.csv": "line 3: expected the column line", "bad_row.csv": "line 5",
              "empty.csv": "needs 3 header lines and data rows", "ours.csv": "missing required column",
              "junk.mat": "not a readable MATLAB .mat file"}
    for name, text in cases.items():
        path = tmp_path / name if text is None else _write(tmp_path, name, text)
        with pytest.raises(RecordingFileError) as err:
            read_recording_file(path)
        msg = str(err.value)
        assert msg.startswith(name + ":") and expect[name] in msg, msg
        assert isinstance(err.value, RecordingError)


def test_bad_rows_can_be_skipped(tmp_path):
    p = _write(tmp_path, "q.csv", "Fs,50\nInitialization time,0\nmx,my,mz\n1,2,3\n4,x,6\n\n7,8,9\n")
    rec = read_recording_file(p, skip_bad_rows=True)
    assert len(rec) == 2 and rec.meta["skipped_rows"] == "1"
    # a message about the second sample names its data row of the file (the skipped one counted)
    assert rec.meta["skipped_at_rows"] == "1" and [file_row(rec, i) for i in range(2)] == [0, 2]


def test_mat_layouts_are_checked(tmp_path):
    scipy.io.savemat(str(tmp_path / "other.mat"), {"x": np.zeros((3, 3))})
    with pytest.raises(RecordingFileError, match=r"other.mat: unknown MATLAB layout.*found \['x'\].*--mapping"):
        read_recording_file(tmp_path / "other.mat")
    scipy.io.savemat(str(tmp_path / "g.mat"), {"data": np.ones((5, 9))})
    with pytest.raises(RecordingFileError,
                       match=r"g.mat: variable 'data' has shape \(5, 9\), expected \(N, 10\) .* or \(N, 14\)"):
        read_recording_file(tmp_path / "g.mat")
    d = np.ones((5, 10))
    d[3, 0] = -1.0
    scipy.io.savemat(str(tmp_path / "g2.mat"), {"data": d})
    with pytest.raises(RecordingFileError, match=r"g2.mat: column 1 \(dt, ms\) is not positive in row\(s\) \[4\]"):
        read_recording_file(tmp_path / "g2.mat")
    n = 20
    broad = {"imu_mag": np.ones((n, 3)), "imu_acc": np.ones((n, 3)), "imu_gyr": np.zeros((n, 3)),
             "opt_quat": np.full((n, 4), np.nan), "movement": np.zeros((n, 1)), "sampling_rate": np.array([[100.0]])}
    scipy.io.savemat(str(tmp_path / "b.mat"), broad)
    with pytest.raises(RecordingFileError, match="b.mat: opt_quat has no valid row"):
        read_recording_file(tmp_path / "b.mat")
    broad["opt_quat"] = np.tile([1.0, 0, 0, 0], (n, 1))
    broad["imu_acc"] = np.ones((n - 1, 3))
    scipy.io.savemat(str(tmp_path / "b2.mat"), broad)
    with pytest.raises(RecordingFileError, match="b2.mat: variable 'imu_acc' has 19 rows, imu_mag has 20"):
        read_recording_file(tmp_path / "b2.mat")


def test_our_csv_is_read_through_parse_recording(tmp_path):
    text = ("# compasscal-recording: 1\n# serial: X1\nt,step,psi_t,theta_t,phi_t,mx,my,mz\n"
            "0,a,,,,1,2,3\n0.1,a,,,,1,2,4\n")
    rec = read_recording_file(_write(tmp_path, "r.csv", text))
    assert rec.serial == "X1" and not rec.has_angles and len(rec) == 2
    assert rec.meta["source_file"] == "r.csv"
    assert len(parse_recording(text)) == 2


# --------------------------------------------------------------------------------------------------
# Other documented layouts: GimbalPlatform's servo-platform files, BROAD's HDF5, MATLAB v7.3
# --------------------------------------------------------------------------------------------------

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
ENC = (360.0 / 4096.0) / 0.087  # the platform firmware's encoder scale error (0.087 deg per count)


def _platform_file(path: Path, n_hold: int = 100, n: int = 400) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A synthetic datasets/platform file written as the firmware does, from known stage angles.

    Physics in our conventions: C_Lb = Rz(psi) Ry(theta) Rx(phi); the body frame b is the source's NED
    frame, in which the LSM9DS1 reads acc (ax, ay, -az), mag (-mx, my, -mz), gyro (gx, gy, -gz). The file
    holds tx = phi / ENC, ty = theta / ENC (the firmware's 0.087 deg per count), tz = -psi.
    """
    rng = np.random.default_rng(1)
    k = np.arange(n)
    moving = k >= n_hold
    phi = np.where(moving, 60 * np.sin(k / 25.0), 0.0)
    theta = np.where(moving, 30 * np.sin(k / 17.0 + 0.3), 0.0)
    psi = np.where(moving, 50 * np.sin(k / 40.0), 0.0)
    C = rot_z(psi) @ rot_y(theta) @ rot_x(phi)
    f_b = np.einsum("nji,j->ni", C, [0.0, 0.0, -1.0])  # specific force in g
    H_L = np.array([20.0, 3.0, 42.0])  # uT, lab frame (z down)
    h_b = np.einsum("nji,j->ni", C, H_L)
    data = np.zeros((n, 14))
    data[:, 0] = 1234.5 + 0.01 * k  # UNO millis()/1000
    data[:, 1], data[:, 2], data[:, 3] = phi / ENC, theta / ENC, -psi
    data[:, 4:7] = f_b * [1, 1, -1]
    data[:, 7:10] = rng.normal(0, 1, (n, 3))
    data[:, 10:13] = h_b * [-1, 1, -1]
    data[:, 13] = 10.0
    scipy.io.savemat(str(path), {"data": data})
    return data, {"psi": psi, "theta": theta, "phi": phi, "f_b": f_b, "h_b": h_b}


def test_gimbal_platform_14_columns_become_table_angles(tmp_path):
    data, truth = _platform_file(tmp_path / "turn_XYZ_slow.mat")
    rec = read_recording_file(tmp_path / "turn_XYZ_slow.mat")
    assert len(rec) == 400 and rec.has_angles
    # time: column 0 in s, from the first sample
    assert rec.t[0] == 0.0 and rec.t[-1] == pytest.approx(3.99)
    # angles: phi_t = tx * 1.0102 (encoder scale), theta_t = ty * 1.0102, psi_t = -tz
    assert np.allclose(rec.phi_t, truth["phi"]) and np.allclose(rec.theta_t, truth["theta"])
    assert np.allclose(rec.psi_t, truth["psi"]) and np.allclose(rec.psi_t, -data[:, 3])
    assert rec.phi_t[150] == pytest.approx(data[150, 1] * 1.010237, rel=1e-6)
    # sensor readings in the body frame at the nominal scales: the angles reproduce them (PHYSICS.md)
    assert np.allclose(rec.acc, truth["f_b"] * 16384.0) and np.allclose(rec.mag, truth["h_b"] * 100.0)
    assert np.allclose(np.asarray(rec.extra["gz"], float), -data[:, 9], atol=1e-6)
    assert np.allclose(np.asarray(rec.extra["gx"], float), data[:, 7], atol=1e-6)
    # the file's own angles are kept, as are the IMU's intervals
    assert np.allclose(np.asarray(rec.extra["enc_x"], float), data[:, 1], atol=1e-6)
    assert rec.extra["dt_imu_ms"][0] == "10"
    # the firmware's first samples carry angles set to 0 (not read): step origin_hold
    assert (rec.step[:100] == "origin_hold").all() and (rec.step[100:] == "platform").all()
    assert rec.meta["origin_hold_rows"] == "100"
    assert rec.meta["attitude_source"] == "turntable"
    assert "servo command" in rec.meta["angle_sources"] and "psi_t = -tz" in rec.meta["angles"]
    assert rec.meta["mag_unit"] == "0.01 uT per count"


def test_gimbal_platform_encoder_wrap_and_bad_time(tmp_path):
    data, truth = _platform_file(tmp_path / "p.mat", n_hold=0, n=50)
    # the firmware angle wraps by one encoder turn (4096 x 0.087 deg); an encoder angle does not
    data[30:, 1] -= 4096 * 0.087
    scipy.io.savemat(str(tmp_path / "wrap.mat"), {"data": data})
    rec = read_recording_file(tmp_path / "wrap.mat")
    assert np.allclose(rec.phi_t, truth["phi"]) and (rec.step == "platform").all()
    data[20, 0] = data[19, 0] - 1.0
    scipy.io.savemat(str(tmp_path / "back.mat"), {"data": data})
    with pytest.raises(RecordingFileError, match=r"back.mat: column 0 \(t, s\) decreases at row 21"):
        read_recording_file(tmp_path / "back.mat")


def _broad_arrays(n: int = 60) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(2)
    q = rng.normal(size=(n, 4))
    q[5] = np.nan  # the optical reference lost the marker for a row
    return {"imu_mag": rng.normal(20, 5, (n, 3)), "imu_acc": rng.normal(0, 9.8, (n, 3)),
            "imu_gyr": rng.normal(0, 1, (n, 3)), "opt_quat": q,
            "movement": (np.arange(n) > 30).astype(float), "sampling_rate": np.array(285.714)}


@pytest.mark.parametrize("rate_as", ["dataset", "attribute"])
def test_broad_hdf5_reads_like_its_mat_twin(tmp_path, rate_as):
    import h5py

    d = _broad_arrays()
    scipy.io.savemat(str(tmp_path / "01_trial.mat"), {**d, "movement": d["movement"][:, None],
                                                       "sampling_rate": np.array([[285.714]])})
    with h5py.File(tmp_path / "01_trial.hdf5", "w") as f:
        for k, v in d.items():
            if k == "sampling_rate" and rate_as == "attribute":
                f.attrs[k] = float(v)
            else:
                f[k] = v
    a = read_recording_file(tmp_path / "01_trial.mat")
    b = read_recording_file(tmp_path / "01_trial.hdf5")
    assert len(b) == 59 and b.meta["dropped_rows_no_reference"] == "1"
    for name in ("t", "psi_t", "theta_t", "phi_t", "mag", "acc"):
        assert np.allclose(getattr(a, name), getattr(b, name)), name
    assert list(a.step) == list(b.step) and b.step[-1] == "move_1"
    assert np.allclose(b.mag, d["imu_mag"][np.r_[0:5, 6:60]] * 100.0)
    assert "data_hdf5" in b.meta["source"] and "data_mat" in a.meta["source"]
    assert b.meta["attitude_source"] == "optical reference"


def _write_v73(path: Path, variables: dict[str, np.ndarray]) -> None:
    """A MATLAB v7.3 MAT-file: a 512-byte MATLAB header, then HDF5 holding each variable transposed
    (MATLAB is column-major, so h5py sees an N x 4 matrix as 4 x N)."""
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        for k, v in variables.items():
            f[k] = np.asarray(v).T
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write(header.ljust(116, b" ") + b" " * 8 + b"\x00\x02IM")  # version 0x0200, little-endian


def test_matlab_v73_compass_buffer(tmp_path):
    n = 40
    buf = np.column_stack([1.6e9 + 0.013 * np.arange(n), np.full(n, 0.21), np.full(n, -0.05), np.linspace(-0.4, 0.4, n)])
    _write_v73(tmp_path / "hmc5883l_compass.mat", {"compassBuffer": buf})
    with pytest.raises(NotImplementedError):  # scipy refuses it: it is v7.3 indeed
        scipy.io.loadmat(str(tmp_path / "hmc5883l_compass.mat"))
    rec = read_recording_file(tmp_path / "hmc5883l_compass.mat")
    assert len(rec) == n and not rec.has_angles and rec.acc is None
    assert rec.t[0] == 0.0 and rec.t[1] == pytest.approx(0.013, abs=1e-6)  # epoch seconds made relative
    assert float(rec.meta["t0_file_s"]) == pytest.approx(1.6e9)
    # gauss -> 0.01 uT counts: 1 G = 100 uT = 10000 counts
    assert rec.mag[0].tolist() == pytest.approx([2100.0, -500.0, -4000.0])
    assert rec.meta["mag_unit"] == "0.01 uT per count" and "HMC5883L" in rec.meta["sensor"]


def test_matlab_v73_gimbal_platform(tmp_path):
    data, truth = _platform_file(tmp_path / "v5.mat", n_hold=10, n=60)
    _write_v73(tmp_path / "v73.mat", {"data": data})
    a, b = read_recording_file(tmp_path / "v5.mat"), read_recording_file(tmp_path / "v73.mat")
    assert len(b) == 60 and np.allclose(a.mag, b.mag) and np.allclose(a.psi_t, b.psi_t)
    assert np.allclose(b.theta_t, truth["theta"])


def test_hdf5_unknown_layout_and_junk(tmp_path):
    import h5py

    with h5py.File(tmp_path / "x.h5", "w") as f:
        f["foo"] = np.zeros((3, 3))
    with pytest.raises(RecordingFileError, match=r"x.h5: unknown HDF5 layout.*\['foo'\]"):
        read_recording_file(tmp_path / "x.h5")
    (tmp_path / "junk.hdf5").write_bytes(b"not hdf5 at all")
    with pytest.raises(RecordingFileError, match="junk.hdf5: not an HDF5 file"):
        read_recording_file(tmp_path / "junk.hdf5")


# --------------------------------------------------------------------------------------------------
# Mapping files
# --------------------------------------------------------------------------------------------------

def test_example_mapping_reads_its_logger_file(tmp_path):
    """examples/mapping.toml, as documented: ';' separated, one line to skip, ms, uT and g in a frame whose
    axes are (y, -x, z) of ours, yaw counted the other way."""
    text = ("MyLogger v2, unit 17\n"
            "tms;Bx;By;Bz;Ax;Ay;Az;yaw;pitch;roll;T\n"
            "# a comment line\n"
            "1000;12.5;-3.1;40.2;0.01;0.00;-1.00;10.0;0.0;0.0;24.8\n"
            "1020;12.0;-3.5;40.0;0.02;0.01;-0.99;12.5;1.0;-2.0;24.9\n")
    p = _write(tmp_path, "logger.csv", text)
    rec = read_recording_file(p, mapping=EXAMPLES / "mapping.toml")
    assert len(rec) == 2 and rec.t.tolist() == pytest.approx([0.0, 0.02])
    assert rec.meta["t0_file_s"] == "1.000000"
    # our (mx, my, mz) = file (y, -x, z), uT -> 0.01 uT counts
    assert rec.mag[0].tolist() == pytest.approx([-310.0, -1250.0, 4020.0])
    assert rec.acc[1].tolist() == pytest.approx([0.01 * 16384, -0.02 * 16384, -0.99 * 16384])
    # psi_t negated (angles.negate), the others as they are
    assert rec.psi_t.tolist() == [-10.0, -12.5] and rec.theta_t[1] == 1.0 and rec.phi_t[1] == -2.0
    assert rec.temp_c.tolist() == [24.8, 24.9] and (rec.step == "data").all()
    assert rec.meta["serial"] == "SN-0017" and rec.meta["attitude_source"] == "turntable"
    assert rec.meta["mapping"] == "mapping.toml" and "file y, -x, z" in rec.meta["mag_axes"]


def test_mapping_without_header_by_index_with_rate_and_factor(tmp_path):
    p = _write(tmp_path, "raw.txt", "  100   -200  300  s1\n 101 -201 301  s1\n\n 102 -202 302 s2\n")
    m = {"file": {"delimiter": "whitespace", "header": False},
         "columns": {"mx": 0, "my": 1, "mz": 2, "step": 3},
         "time": {"rate_hz": 4.0},
         "mag": {"unit": 2.5, "axes": ["-z", "x", "y"]}}
    rec = read_recording_file(p, mapping=m)
    assert rec.t.tolist() == [0.0, 0.25, 0.5] and rec.step.tolist() == ["s1", "s1", "s2"]
    assert rec.mag[2].tolist() == pytest.approx([-302 * 2.5, 102 * 2.5, -202 * 2.5])
    assert rec.meta["sample_rate_hz"] == "4" and "2.5" in rec.meta["mag_unit"]
    assert not rec.has_angles and rec.acc is None


def test_mapping_dt_column_counts_and_quaternion(tmp_path):
    """A dt column in ms, raw counts, and an attitude as quaternions (x, y, z, w) mapping body to NED."""
    yaw, pitch = np.radians(30.0), np.radians(-20.0)
    qz = [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]  # xyzw: yaw 30 deg about z (down)
    qy = [0.0, np.sin(pitch / 2), 0.0, np.cos(pitch / 2)]  # pitch -20 deg about y
    rows = ["dt,mx,my,mz,qx,qy,qz,qw",
            "5,1,2,3," + ",".join(f"{v:.12f}" for v in qz),
            "20,1,2,3,,,,",  # the reference lost track: row dropped, counted
            "25,4,5,6," + ",".join(f"{v:.12f}" for v in qy)]
    p = _write(tmp_path, "q.csv", "\n".join(rows) + "\n")
    m = {"columns": {"dt": "dt", "mx": "mx", "my": "my", "mz": "mz"}, "time": {"unit": "ms"},
         "mag": {"unit": "counts"},
         "attitude": {"columns": ["qx", "qy", "qz", "qw"], "order": "xyzw", "frame": "NED"}}
    rec = read_recording_file(p, mapping=m)
    assert rec.t.tolist() == pytest.approx([0.0, 0.045])  # 0, then 20 + 25 ms (the dropped row's time counts)
    assert rec.meta["dropped_rows_no_reference"] == "1" and rec.mag[1].tolist() == [4.0, 5.0, 6.0]
    assert file_row(rec, 1) == 2  # the file's row of the second sample: the dropped row counted
    assert rec.psi_t[0] == pytest.approx(30.0) and rec.theta_t[0] == pytest.approx(0.0, abs=1e-9)
    assert rec.theta_t[1] == pytest.approx(-20.0) and rec.phi_t[1] == pytest.approx(0.0, abs=1e-9)
    assert rec.meta["attitude_source"] == "attitude reference (quaternion)"
    # the inverse convention turns the yaw the other way; an ENU frame puts the identity at azimuth 90
    m["attitude"]["rotation"] = "lab_to_body"
    assert read_recording_file(p, mapping=m).psi_t[0] % 360 == pytest.approx(330.0)
    m["attitude"].update(rotation="body_to_lab", frame="ENU")
    rows[1] = "5,1,2,3,0,0,0,1"
    p.write_text("\n".join(rows) + "\n")
    enu = read_recording_file(p, mapping=m)
    assert enu.psi_t[0] == pytest.approx(90.0) and abs(enu.phi_t[0]) == pytest.approx(180.0)


def test_mapped_times_are_written_without_float_residue(tmp_path):
    """A dt column summed, or a time column less its first value, gave "0.0500000000000007" and
    "106.049999999998" in the converted file: times are kept to the nanosecond."""
    rows = ["dt,t,mx,my,mz"] + [f"0.05,{1000.3 + 0.05 * i:.2f},1,2,3" for i in range(40)]
    p = _write(tmp_path, "d.csv", "\n".join(rows) + "\n")
    for col in ("dt", "t"):
        m = {"columns": {col: col, "mx": "mx", "my": "my", "mz": "mz"}, "time": {"unit": "s", "start_at_zero": True}}
        if col == "dt":
            del m["time"]["start_at_zero"]
        text = format_recording(read_recording_file(p, mapping=m))
        times = [line.split(",")[0] for line in text.splitlines()[1:] if line and not line.startswith(("#", "t,"))]
        assert all(len(x.split(".")[-1]) <= 3 for x in times), [x for x in times if len(x.split(".")[-1]) > 3]


@pytest.mark.parametrize("sequence", ["XYZ", "ZXY", "yxz"])
def test_mapping_angles_in_another_rotation_sequence_give_the_same_attitudes_and_calibration(tmp_path, sequence):
    """A logger whose three angles (about z, y and x) compose the attitude in another order: converted to
    PHYSICS.md's ZYX table angles they give the same attitudes, and the fit the same calibration as the
    recording written with ours; the stage-frame tests are then not run (no stage of a z, y, x table)."""
    from scipy.spatial.transform import Rotation

    from physics.fit import fit
    from physics.sensor import reference_unit
    from physics.simulate import simulate_recording
    from procedures.calibrate import calibration_poses

    rec = simulate_recording(reference_unit(), calibration_poses(), rng=np.random.default_rng(3))
    C = Rotation.from_euler("ZYX", np.column_stack([rec.psi_t, rec.theta_t, rec.phi_t]), degrees=True)
    a = C.as_euler(sequence, degrees=True)
    about = {ax: a[:, i] for i, ax in enumerate(sequence.lower())}
    lines = ["t,mx,my,mz,ax,ay,az,yaw,pitch,roll"] + [
        f"{t:.6f},{m[0]:.6f},{m[1]:.6f},{m[2]:.6f},{f[0]:.6f},{f[1]:.6f},{f[2]:.6f},{-z:.9f},{y:.9f},{x:.9f}"
        for t, m, f, z, y, x in zip(rec.t, rec.mag, rec.acc, about["z"], about["y"], about["x"])]  # yaw counted the other way
    p = _write(tmp_path, "log.csv", "\n".join(lines) + "\n")
    m = {"columns": {"t": "t", "mx": "mx", "my": "my", "mz": "mz", "ax": "ax", "ay": "ay", "az": "az",
                     "psi_t": "yaw", "theta_t": "pitch", "phi_t": "roll"},
         "mag": {"unit": "counts"}, "acc": {"unit": "counts"}, "angles": {"sequence": sequence, "negate": ["psi_t"]}}
    got = read_recording_file(p, mapping=m)
    back = Rotation.from_euler("ZYX", np.column_stack([got.psi_t, got.theta_t, got.phi_t]), degrees=True)
    assert np.degrees((back * C.inv()).magnitude()).max() < 1e-6
    assert f"sequence {sequence}" in got.meta["angles"]
    assert got.meta["attitude_source"] == f"turntable with its stages nested {sequence}, not z, y, x"
    ours, theirs = fit(rec, "joint", bootstrap=0), fit(got, "joint", bootstrap=0)
    assert np.abs(theirs.mag.M_o - ours.mag.M_o).max() < 1e-6 and np.abs(theirs.mag.k / ours.mag.k - 1).max() < 1e-6
    assert np.abs(theirs.mag.bias - ours.mag.bias).max() < 1e-3
    # ours, said outright or as the lab-axes (extrinsic) sequence x, y, z, is a table's: nothing converted
    for same in ("ZYX", "xyz"):
        m["angles"]["sequence"] = same
        plain = read_recording_file(p, mapping=m)
        assert plain.meta["attitude_source"] == "turntable" and "sequence" not in plain.meta["angles"]


def test_mapping_mat_variables_and_radians(tmp_path):
    n = 30
    log = np.column_stack([np.arange(n) * 0.1, np.full(n, 0.3), np.full(n, -0.1), np.full(n, 0.5),
                           np.linspace(0, np.pi, n)])
    scipy.io.savemat(str(tmp_path / "log.mat"), {"log": log, "temp": np.full((n, 1), 300.15), "zero": np.zeros((n, 1)),
                                                 "acc": np.tile([0.0, 0.0, -9.80665], (n, 1))})
    # one constant column may stand for the two angles of axes the table lacks
    m = {"file": {"variable": "log"},
         "columns": {"t": 0, "mx": 1, "my": 2, "mz": 3, "psi_t": 4, "theta_t": "zero", "phi_t": "zero",
                     "ax": "acc[0]", "ay": "acc[1]", "az": "acc[2]", "temp_c": "temp"},
         "mag": {"unit": "gauss"}, "acc": {"unit": "m/s^2"}, "angles": {"unit": "rad"}, "temp": {"unit": "K"}}
    rec = read_recording_file(tmp_path / "log.mat", mapping=m)
    assert rec.mag[0].tolist() == pytest.approx([3000.0, -1000.0, 5000.0])
    assert rec.acc[0].tolist() == pytest.approx([0.0, 0.0, -16384.0])
    assert rec.psi_t[-1] == pytest.approx(180.0) and rec.temp_c[0] == pytest.approx(27.0)
    assert "log[4]" in rec.meta["angles"]


def test_a_time_column_named_in_milliseconds_needs_its_unit_said(tmp_path):
    """A column "tms" with no [time] unit was read as seconds: a two-minute log became one of 106,050 s,
    unsaid. A time column named in ms, us or ns needs [time] unit (either way); one named in seconds does not."""
    data = "tms,t_sec,a,b,c\n0,0.0,1,2,3\n10,0.01,2,3,4\n20,0.02,3,4,5\n"
    said = _mapping_error(tmp_path, {"columns": {**MAG_ABC, "t": "tms"}}, data)
    assert "column 'tms' is named like a time in milliseconds" in said and 'say unit = "ms" in [time]' in said, said
    p = _write(tmp_path, "d.csv", data)
    for mapping, span in (({"columns": {**MAG_ABC, "t": "tms"}, "time": {"unit": "ms"}}, 0.02),
                          ({"columns": {**MAG_ABC, "t": "tms"}, "time": {"unit": "s"}}, 20.0),
                          ({"columns": {**MAG_ABC, "t": "t_sec"}}, 0.02)):
        rec = read_recording_file(p, mapping=mapping)
        assert rec.t[-1] - rec.t[0] == pytest.approx(span), mapping


def _mapping_error(tmp_path: Path, mapping: dict | str, data: str = "a,b,c\n1,2,3\n") -> str:
    p = _write(tmp_path, "d.csv", data)
    if isinstance(mapping, str):
        mapping = _write(tmp_path, "map.toml", mapping)
    with pytest.raises(RecordingFileError) as err:
        read_recording_file(p, mapping=mapping)
    return str(err.value)


MAG_ABC = {"mx": "a", "my": "b", "mz": "c"}


@pytest.mark.parametrize("mapping, expect", [
    ({"colums": {}}, "mapping: unknown key 'colums' in the top level; accepted keys: file, columns, time"),
    ({"columns": MAG_ABC, "time": {"rate_hz": 1}, "mag": {"units": "uT"}},
     "unknown key 'units' in [mag]; accepted keys: unit, axes"),
    ({"columns": {**MAG_ABC, "mx": "Bx"}, "time": {"rate_hz": 1}},
     "d.csv: mapping: mag column 'Bx' (mx) not found in header [a, b, c]"),
    ({"columns": MAG_ABC}, "give exactly one time base"),
    ({"columns": {**MAG_ABC, "t": "a", "dt": "b"}}, "got columns.t, columns.dt"),
    ({"columns": {**MAG_ABC, "ax": "a"}, "time": {"rate_hz": 1}}, "columns.ay, columns.az not given: acc needs all three columns (ax, ay, az) or none"),
    ({"columns": MAG_ABC, "time": {"rate_hz": 1}, "mag": {"unit": "furlongs"}},
     "mag.unit 'furlongs' is not known; accepted: uT, nT"),
    ({"columns": MAG_ABC, "time": {"rate_hz": 1}, "mag": {"axes": ["x", "x", "z"]}}, "each of x, y, z once"),
    ({"columns": MAG_ABC, "time": {"rate_hz": 1}, "mag": {"axes": ["x", "w", "z"]}}, "'w' is not an axis"),
    ({"columns": {**MAG_ABC, "mz": 7}, "time": {"rate_hz": 1}}, "mag column 7 (mz) is beyond the header's 3 columns"),
    ({"file": {"header": False}, "columns": MAG_ABC, "time": {"rate_hz": 1}},
     "mag column 'a' (mx) is given by name but file.header = false"),
    ({"columns": {"my": "b", "mz": "c"}, "time": {"rate_hz": 1}}, "mag needs all three columns"),
    # with [mag] given too: the one column missing, not all three ("[mag] is given but columns.mx, ... are not")
    ({"columns": {"my": "b", "mz": "c"}, "time": {"rate_hz": 1}, "mag": {"unit": "uT"}}, "columns.mx not given"),
    ({"columns": {**MAG_ABC, "t": 1.5}}, "columns.t must be a column name (text) or a 0-based index"),
    ({"columns": MAG_ABC, "time": {"rate_hz": -2}}, "time.rate_hz must be a number > 0, got -2"),
    ({"columns": {**MAG_ABC, "psi_t": "a", "theta_t": "b", "phi_t": "c"}, "time": {"rate_hz": 1},
      "attitude": {"columns": ["a", "b", "c", "a"]}}, "either angle columns"),
    ({"columns": {**MAG_ABC, "psi_t": "a", "theta_t": "b", "phi_t": "c"}, "time": {"rate_hz": 1},
      "angles": {"sequence": "ZXZ"}}, "angles.sequence 'ZXZ' is not a rotation sequence of three different axes"),
    ({"columns": {**MAG_ABC, "psi_t": "a", "theta_t": "b", "phi_t": "c"}, "time": {"rate_hz": 1},
      "angles": {"sequence": "Zyx"}}, "angles.sequence 'Zyx' is not a rotation sequence"),
    ({"columns": MAG_ABC, "time": {"rate_hz": 1}, "angles": {"negate": ["yaw"]}}, "[angles] is given but"),
    ({"file": {"format": "xlsx"}}, "file.format 'xlsx' is not known; accepted: csv, mat, hdf5"),
    ({"columns": {**MAG_ABC, "psi_t": "a", "theta_t": "b", "phi_t": "c"}, "time": {"rate_hz": 1}},
     "columns.mx and columns.psi_t both name column 'a': each quantity needs a column of its own"),
    ({"columns": {**MAG_ABC, "temp_c": 2}, "time": {"rate_hz": 1}},  # by index, the same column as mz by name
     "columns.mz and columns.temp_c both name column 2 ('c')"),
])
def test_mapping_errors_name_the_key_and_the_problem(tmp_path, mapping, expect):
    assert expect in _mapping_error(tmp_path, mapping)


def test_mapping_refuses_an_ambiguous_header_and_rows_longer_than_it(tmp_path):
    """What the native reader refuses, the mapped one does too: a mapped name the header holds twice, a
    row with more fields than the header (a shifted or merged line), each named by column or line."""
    m = {"columns": {"t": "tms", "mx": "a", "my": "b", "mz": "c"}, "time": {"unit": "ms"}}
    msg = _mapping_error(tmp_path, m, "tms,a,b,c,a\n0,1,2,3,4\n")
    assert "mag column 'a' (mx) appears 2 times in the header (0-based columns 1, 4)" in msg
    msg = _mapping_error(tmp_path, m, "tms,a,b,c\n0,1,2,3\n10,1,2,3,9\n20,1,2,3\n")
    assert "1 problem(s) in 1 row(s)" in msg and "line 3: 5 fields, the header has 4" in msg
    rec = read_recording_file(tmp_path / "d.csv", mapping=m, skip_bad_rows=True)
    assert len(rec) == 2 and rec.meta["skipped_rows"] == "1"
    twice = {"columns": {"t": "tms", "mx": "a", "my": "b", "mz": "a"}, "time": {"unit": "ms"}}
    msg = _mapping_error(tmp_path, twice, "tms,a,b\n0,1,2\n10,5,2\n")  # a column that changes, read twice
    assert "columns.mx and columns.mz both name column 'a', whose values change" in msg
    # a header name repeated in a column the mapping does not read is no one's business
    assert len(read_recording_file(_write(tmp_path, "e.csv", "tms,a,b,c,x,x\n0,1,2,3,4,5\n"), mapping=m)) == 1


def test_mapping_data_errors_name_the_column_and_line(tmp_path):
    m = {"columns": {"t": "tms", "mx": "a", "my": "b", "mz": "c"}, "time": {"unit": "ms"}}
    msg = _mapping_error(tmp_path, m, "tms,a,b,c\n0,1,2,3\n10,1,2,3\nabc,1,2,3\n30,1,,3\n40,1,2\n")
    assert msg.startswith("d.csv: 3 problem(s) in 3 row(s)")
    assert "column 'tms' line 4: not a number ('abc')" in msg
    assert "column 'b' line 5: not a number ('')" in msg
    assert "column 'c' line 6: missing (the row has 3 fields)" in msg
    rec = read_recording_file(tmp_path / "d.csv", mapping=m, skip_bad_rows=True)
    assert len(rec) == 2 and rec.meta["skipped_rows"] == "3"
    assert [file_row(rec, i) for i in range(2)] == [0, 1] and rec.meta["skipped_at_rows"] == "2,3,4"
    # the rows after a skipped one are named by their row of the file, comments not counted
    rec = read_recording_file(_write(tmp_path, "d.csv", "tms,a,b,c\n0,1,2,3\n# note\nx,1,2,3\n10,1,2,3\n"),
                              mapping={**m, "file": {"comment": "#"}}, skip_bad_rows=True)
    assert len(rec) == 2 and [file_row(rec, i) for i in range(2)] == [0, 2]
    msg = _mapping_error(tmp_path, m, "tms,a,b,c\n0,1,2,3\n10,1,2,3\n5,1,2,3\n")
    assert "column 'tms' line 4: time goes backwards (5 after 10 ms)" in msg


def test_mapping_file_errors(tmp_path):
    assert "map.toml: not valid TOML" in _mapping_error(tmp_path, "[columns\nmx = 1\n")
    assert "map.toml: mapping: unknown key 'mxx' in [columns]; accepted keys: t, dt, step, mx" in _mapping_error(
        tmp_path, '[columns]\nmxx = "a"\n')
    with pytest.raises(RecordingFileError, match="nope.toml: mapping file not found"):
        read_recording_file(tmp_path / "d.csv", mapping=tmp_path / "nope.toml")
    scipy.io.savemat(str(tmp_path / "v.mat"), {"log": np.zeros((4, 3))})
    m = {"file": {"variable": "log"}, "columns": {"mx": 0, "my": 1, "mz": "field"}, "time": {"rate_hz": 1}}
    with pytest.raises(RecordingFileError, match=r"v.mat: mapping: mag column 'field' \(mz\) not found; the file holds \[log\]"):
        read_recording_file(tmp_path / "v.mat", mapping=m)
    m["columns"]["mz"] = 3
    with pytest.raises(RecordingFileError, match=r"mag column 3 \(mz\) is beyond variable 'log' with 3 columns"):
        read_recording_file(tmp_path / "v.mat", mapping=m)


def test_cli_fit_and_analyze_take_a_mapping(tmp_path):
    """A simulated recording rewritten as a foreign CSV (other names, order, uT, ms, azimuth counted the
    other way) fits through --mapping to the calibration of the original; a bad mapping fails naming it."""
    from typer.testing import CliRunner

    from service.cli import app

    runner = CliRunner()
    orig = tmp_path / "rec.csv"
    assert runner.invoke(app, ["simulate", "--unit", "reference", "--samples", "3", "-o", str(orig)]).exit_code == 0
    rec = read_recording_file(orig)
    lines = ["time_ms,azimuth,pitch,roll,Bz,By,Bx,phase"]
    for i in range(len(rec)):
        lines.append(f"{rec.t[i] * 1000:.6f},{-rec.psi_t[i]:.6f},{rec.theta_t[i]:.6f},{rec.phi_t[i]:.6f},"
                     f"{rec.mag[i, 2] / 100:.6f},{rec.mag[i, 1] / 100:.6f},{rec.mag[i, 0] / 100:.6f},{rec.step[i]}")
    foreign = _write(tmp_path, "foreign.csv", "\n".join(lines) + "\n")
    mapping = _write(tmp_path, "map.toml", """
[columns]
t = "time_ms"
psi_t = "azimuth"
theta_t = "pitch"
phi_t = "roll"
mx = "Bx"
my = "By"
mz = "Bz"
step = "phase"
[time]
unit = "ms"
[angles]
negate = ["psi_t"]
""")
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    r1 = runner.invoke(app, ["fit", str(orig), "-o", str(a)])
    r2 = runner.invoke(app, ["fit", str(foreign), "--mapping", str(mapping), "-o", str(b)])
    assert r1.exit_code == 0 and r2.exit_code == 0, r2.output

    ca, cb = (json.loads(x.read_text())["magnetometer"] for x in (a, b))
    # the foreign file rounds to 1e-6 uT (0.0001 count): the same calibration
    assert np.allclose(ca["k"], cb["k"], rtol=1e-5) and np.allclose(ca["bias"], cb["bias"], atol=0.01)
    assert np.allclose(ca["M_o"], cb["M_o"], atol=1e-6) and ca["k"][0] == pytest.approx(3268.0, rel=0.01)
    bad = _write(tmp_path, "bad.toml", '[columns]\nmx = "Bx"\nmy = "By"\nmz = "Bq"\n[time]\nrate_hz = 10\n')
    r = runner.invoke(app, ["analyze", str(foreign), "--mapping", str(bad)])
    assert r.exit_code == 2 and "mag column 'Bq' (mz) not found in header" in r.output


def test_mapping_refuses_radians_said_to_be_degrees_and_a_quaternion_that_is_not_one(tmp_path):
    """Angles in radians mapped as degrees were written as a table recording without a word (fit refused
    it only later); four columns that are no unit quaternion (a temperature of 23 as q3) were normalised
    into garbage angles. Both are refused when the file is read, naming the fix."""
    yaw = np.linspace(0.0, 2 * np.pi * 0.9, 40)
    rows = ["t,a,b,c,yaw,pitch,roll,T"] + [f"{0.05 * i:.2f},1,2,3,{y:.6f},0.1,-0.1,23.0" for i, y in enumerate(yaw)]
    p = _write(tmp_path, "r.csv", "\n".join(rows) + "\n")
    m = {"columns": {**MAG_ABC, "t": "t", "psi_t": "yaw", "theta_t": "pitch", "phi_t": "roll"}, "angles": {"unit": "deg"}}
    with pytest.raises(RecordingFileError, match=r"column 'yaw' \(psi_t\) spans 5\.655: these look like radians \(angles\.unit = \"rad\"\)"):
        read_recording_file(p, mapping=m)
    m["angles"]["unit"] = "rad"
    assert read_recording_file(p, mapping=m).psi_t.max() == pytest.approx(324.0, abs=0.01)
    # the fit's own rule (physics.fit.radian_like): a yaw of radians turning by 2 (less than pi) is refused
    # when the file is read too, not only by the fit later
    short = ["t,a,b,c,yaw,pitch,roll,T"] + [f"{0.05 * i:.2f},1,2,3,{y:.6f},0.1,-0.1,23.0" for i, y in enumerate(np.linspace(0, 2, 40))]
    p2 = _write(tmp_path, "r2.csv", "\n".join(short) + "\n")
    m["angles"]["unit"] = "deg"
    with pytest.raises(RecordingFileError, match=r"column 'yaw' \(psi_t\) spans 2\.000: these look like radians"):
        read_recording_file(p2, mapping=m)
    q = {"columns": {**MAG_ABC, "t": "t"}, "attitude": {"columns": ["yaw", "pitch", "roll", "T"], "order": "xyzw"}}
    with pytest.raises(RecordingFileError, match=r"quaternion's norm is 23\.\d+ .* not 1"):
        read_recording_file(p, mapping=q)


def test_a_mapped_file_converts_without_float_noise(tmp_path):
    """A unit's factor left noise in a double's last bits, which the recording then printed: 350 ms became
    t = 0.35000000000000003 and 38.48 uT 3847.9999999999995 counts. Converted values print as the file
    had them; the values themselves move by less than 1e-15 of themselves."""
    m = {"columns": {"t": "tms", "mx": "a", "my": "b", "mz": "c"}, "time": {"unit": "ms"}, "mag": {"unit": "uT"}}
    p = _write(tmp_path, "d.csv", "tms,a,b,c\n0,38.48,-12.07,0.3\n350,38.49,-12.06,0.29\n700,1e-12,5,6\n")
    rec = read_recording_file(p, mapping=m)
    text = format_recording(rec)
    assert "0.35000000000000003" not in text and "3847.9999999999995" not in text
    assert rec.t.tolist() == [0.0, 0.35, 0.7] and rec.mag[0].tolist() == [3848.0, -1207.0, 30.0]
    raw = np.array([[38.48, -12.07, 0.3], [38.49, -12.06, 0.29], [1e-12, 5, 6]]) * 100
    assert np.allclose(rec.mag, raw, rtol=1e-15, atol=0)
    assert rec.mag[2, 0] == 1e-12 * 100  # a value too small to round by powers of ten: as computed


def test_readings_held_over_a_few_reference_samples_are_not_screened_as_bad():
    """BROAD's optical reference and IMU are sampled apart: its "poses" are a few repeats of one reading,
    whose MAD is next to nothing, and ordinary readings were dropped as 3810 sigma off (102 rows of
    broad_01). The screen's noise is now never below the sample-to-sample noise of the held readings."""
    from physics.fit import screen_rows

    rec = read_recording_file(REAL / "broad_01_undisturbed_slow_rotation_A.mat")
    dropped = screen_rows(rec)
    assert len(dropped) <= 5, (len(dropped), list(dropped.values())[:3])
    assert all(int(re.search(r"\((\d+) sigma\)", why).group(1)) < 100 for why in dropped.values() if "sigma" in why)
