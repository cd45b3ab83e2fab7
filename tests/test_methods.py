"""Tests for physics.methods: each comparison method reproduces its paper on data that fits its assumptions,
shows its documented limitation where the data do not, and refuses recordings that cannot support it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from physics.calibration import Calibration, attitude_grid, level_turn, truth_errors, truth_summary
from physics.errorsep import Accel, InsufficientData, accelerometer
from physics.frames import rot_x, rot_y, rot_z
from physics.heading import wrap180
from physics.methods import TWELVE_POSITIONS, deviation5, ellipsoid, maxmin, twelve_position, two_axis
from physics.recording import Recording
from physics.sensor import LinearSensor, Unit, random_unit, reference_unit
from physics.simulate import Pose, World, simulate_recording
from procedures.calibrate import PROCEDURES, calibration_poses, twelve_position_poses
from procedures.steps import simulate_run

WORLD = World()  # I = 55 deg, D = 23 deg, ideal table


def _rec(unit: Unit, poses: list[Pose], world: World = WORLD, seed: int = 1):
    return simulate_recording(unit, poses, world, rng=np.random.default_rng(seed))


def _true_acc(unit: Unit) -> Accel:
    """The unit's true accelerometer and a level base (for recordings the joint accelerometer fit cannot use)."""
    return Accel(unit.acc, np.zeros(2))


def _with_mag(M: np.ndarray, bias: np.ndarray, noise: float = 0.0, serial: str = "TEST") -> Unit:
    ref = reference_unit()
    return replace(ref, serial=serial, mag=LinearSensor.from_matrix(M, bias, noise_lsb=noise))


def _level_poses(step_deg: float, samples: int = 5) -> list[Pose]:
    return [Pose("rotate_z", float(p), 0.0, 0.0, samples) for p in np.arange(0.0, 360.0 - 1e-9, step_deg)]


def _max_err(cal: Calibration, unit: Unit, angles: np.ndarray, world: World = WORLD) -> float:
    return float(np.max(np.abs(truth_errors(cal, unit, world, angles))))


# Hard iron (bias) and soft iron as a symmetric positive-definite matrix: what an ellipsoid can represent.
SYMMETRIC_M = 3000.0 * rot_z(20.0) @ rot_x(10.0) @ np.diag([1.06, 0.95, 1.01]) @ (rot_z(20.0) @ rot_x(10.0)).T
BIAS = np.array([400.0, -300.0, 200.0])


@pytest.fixture(scope="module")
def reference_default():
    """The paper's reference unit, 3 LSB noise, the default calibration poses, and its accelerometer fit."""
    unit = reference_unit(mag_noise_lsb=3.0, acc_noise_lsb=3.0)
    rec = _rec(unit, calibration_poses())
    return unit, rec, accelerometer(rec)


# --------------------------------------------------------------------------------------------------
# ellipsoid (seed 001)
# --------------------------------------------------------------------------------------------------

def test_ellipsoid_symmetric_unit_is_exact():
    unit = _with_mag(SYMMETRIC_M, BIAS)
    rec = _rec(unit, calibration_poses())
    cal = ellipsoid(rec, accelerometer(rec))
    assert cal.method == "ellipsoid" and np.isnan(cal.declination_deg)
    np.testing.assert_allclose(cal.mag.M, SYMMETRIC_M, rtol=1e-8, atol=1e-8 * 3000)
    np.testing.assert_allclose(cal.mag.bias, BIAS, atol=1e-6)
    assert np.all(np.diag(cal.mag.M_o) > 0)
    # |h| = 1 at every attitude of the Fig. 6 grid, and no heading error level or tilted
    grid = attitude_grid()
    h_b, _ = WORLD.body_vectors(grid[:, 0], grid[:, 1], grid[:, 2])
    h = cal.mag.correct(unit.mag.measure(h_b))
    np.testing.assert_allclose(np.linalg.norm(h, axis=1), 1.0, atol=1e-6)
    s = truth_summary(cal, unit, WORLD)
    assert s["level_max"] < 1e-4 and s["tilted_max"] < 1e-4


def test_ellipsoid_reference_unit_keeps_the_triad_rotation(reference_default):
    unit, rec, acc = reference_default
    cal = ellipsoid(rec, acc)
    # the corrected field has unit length (to the noise) ...
    grid = attitude_grid()
    h_b, _ = WORLD.body_vectors(grid[:, 0], grid[:, 1], grid[:, 2])
    np.testing.assert_allclose(np.linalg.norm(cal.mag.correct(unit.mag.measure(h_b)), axis=1), 1.0, atol=2e-3)
    # ... and E is the symmetric part of the true M (M M^T = P^2), so the rotation part stays in the heading
    w, V = np.linalg.eigh(unit.mag.M @ unit.mag.M.T)
    P = (V * np.sqrt(w)) @ V.T
    np.testing.assert_allclose(cal.mag.M, P, atol=2e-3 * 3200)
    s = truth_summary(cal, unit, WORLD)
    assert s["level_max"] > 0.05 and s["tilted_max"] > 0.05
    assert 2.0 < s["level_max"] < 6.0  # about 3.7 deg for this unit
    symmetric_only = Calibration("sym", LinearSensor.from_matrix(P, unit.mag.bias), acc=cal.acc)
    sym = truth_errors(symmetric_only, unit, WORLD, attitude_grid())
    np.testing.assert_allclose(truth_errors(cal, unit, WORLD, attitude_grid()), sym, atol=0.05)
    assert any("rotation" in n for n in cal.notes)


@pytest.mark.parametrize("noise", [0.0, 3.0])
@pytest.mark.parametrize("which", ["level turn", "level turn and one sweep"])
def test_ellipsoid_refuses_readings_that_do_not_span_3d(noise: float, which: str):
    unit = reference_unit(mag_noise_lsb=noise)
    poses = _level_poses(15.0)
    if which != "level turn":
        poses += [Pose("sweep_y", 315.0, float(t), 0.0, 5) for t in range(30, 360, 30)]
    rec = _rec(unit, poses)
    with pytest.raises(InsufficientData, match=r"ellipsoid.*(bias).*(sweeps about the table's x and y)"):
        ellipsoid(rec, _true_acc(unit))


# --------------------------------------------------------------------------------------------------
# deviation5 (seed 004)
# --------------------------------------------------------------------------------------------------

def test_deviation5_level_swing_of_hard_and_soft_iron():
    """The paper's 24 level headings 15 deg apart: semicircular (hard iron) and quadrantal (soft iron)
    deviation is removed; only a level turn, so the ellipsoid cannot be fitted and raw readings are the base."""
    soft = np.array([[1.0, 0.04, 0.0], [0.04, 0.93, 0.0], [0.0, 0.0, 1.0]])
    unit = _with_mag(3000.0 * soft, np.array([120.0, -90.0, 150.0]))
    rec = _rec(unit, _level_poses(15.0))
    cal = deviation5(rec, _true_acc(unit))
    assert cal.heading_model["kind"] == "deviation5" and cal.heading_model["base"] == "raw"
    assert any("ellipsoid not fitted" in n for n in cal.notes)
    turn = level_turn()
    before = _max_err(replace(cal, heading_model=None), unit, turn)
    after = _max_err(cal, unit, turn)
    assert before > 3.0  # like the paper's 4.18 deg
    assert after < before / 5.0  # paper: 4.18 -> 0.46 deg
    assert abs(cal.declination_deg - WORLD.declination_deg) < 0.1
    tilted = _max_err(cal, unit, attitude_grid(30.0, 30.0))
    assert tilted > after  # the curve is a function of heading, fitted at level only


def test_deviation5_on_ellipsoid_removes_the_level_error_only():
    """Seed 004's pipeline: ellipsoid first, then the curve. A triad tilted about x and y (no rotation
    about z) leaves the ellipsoid a once-per-turn level error that the curve removes; tilted it does not."""
    M = SYMMETRIC_M @ rot_x(1.5) @ rot_y(-1.0)
    unit = _with_mag(M, BIAS, noise=3.0)
    rec = _rec(unit, calibration_poses() + _level_poses(15.0, samples=20))
    acc = accelerometer(rec)
    cal = deviation5(rec, acc)
    assert cal.heading_model["base"] == "ellipsoid"
    assert len(cal.heading_model["coefficients_deg"]) == 5
    turn = level_turn()
    before = _max_err(ellipsoid(rec, acc), unit, turn)
    after = _max_err(cal, unit, turn)
    assert before > 1.0
    assert after < before / 5.0
    assert _max_err(cal, unit, attitude_grid()) > 2.0 * after
    # consistent: at its own level poses the compensated heading is psi_t - D, with D the one it reports
    # (per-pose means: one sample's heading noise is 3 LSB / (k cos I) ~ 0.1 deg)
    level = (rec.theta_t == 0) & (rec.phi_t == 0)
    psi_t = np.unique(rec.psi_t[level])
    mag = np.array([rec.mag[level & (rec.psi_t == p)].mean(axis=0) for p in psi_t])
    f_b = cal.specific_force(np.array([rec.acc[level & (rec.psi_t == p)].mean(axis=0) for p in psi_t]))
    err = (cal.heading(mag, f_b) - (psi_t - cal.declination_deg) + 180.0) % 360.0 - 180.0
    assert len(psi_t) == 24 and np.max(np.abs(err)) < 0.05
    assert abs(cal.declination_deg - WORLD.declination_deg) < 0.1


def test_deviation5_refuses_too_few_level_headings():
    unit = reference_unit()
    poses = [Pose("rotate_z", float(p), 0.0, 0.0, 5) for p in (0.0, 90.0, 180.0, 270.0)]
    poses += [Pose("sweep_y", 0.0, float(t), 0.0, 5) for t in range(30, 360, 30)]
    rec = _rec(unit, poses)
    with pytest.raises(InsufficientData, match=r"deviation5.*found 4 heading.*A\.\.E.*level turn"):
        deviation5(rec, _true_acc(unit))


# --------------------------------------------------------------------------------------------------
# two_axis (seed 003)
# --------------------------------------------------------------------------------------------------

TWO_AXIS_WORLD = World(inclination_deg=62.0, declination_deg=-12.0)


def _two_axis_unit() -> Unit:
    """An ideal x-y pair (orthogonal, along the body axes, own scale and bias) and a useless z sensor."""
    M_o = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, -0.4, 0.2]])  # z row: the method must not use it
    mag = LinearSensor(M_o / np.linalg.norm(M_o, axis=1)[:, None], np.array([2900.0, 3100.0, 40.0]),
                       np.array([350.0, -220.0, 5000.0]))
    return replace(reference_unit(), serial="XY-PAIR", mag=mag)


def _two_axis_poses() -> list[Pose]:
    poses = _level_poses(2.0, samples=2)
    for psi in range(0, 360, 45):
        poses += [Pose("tilt", float(psi), t, 0.0, 5) for t in (-30.0, 30.0)]
        poses += [Pose("tilt", float(psi), 0.0, r, 5) for r in (-30.0, 30.0)]
    return poses


def test_two_axis_ideal_pair_extended_dip_and_heading():
    unit = _two_axis_unit()
    rec = _rec(unit, _two_axis_poses(), TWO_AXIS_WORLD)
    cal = two_axis(rec, accelerometer(rec))
    dip = cal.heading_model["extended_dip_deg"]
    assert cal.heading_model["kind"] == "two_axis"
    assert abs(dip - TWO_AXIS_WORLD.inclination_deg) < 0.5
    assert abs(cal.declination_deg - TWO_AXIS_WORLD.declination_deg % 360.0) < 0.05
    np.testing.assert_array_equal(cal.mag.M_o, np.eye(3))
    assert cal.mag.k[2] == 1.0 and cal.mag.bias[2] == 0.0 and any("z sensor is not used" in n for n in cal.notes)
    level = _max_err(cal, unit, level_turn(), TWO_AXIS_WORLD)
    tilted = _max_err(cal, unit, attitude_grid(30.0, 30.0), TWO_AXIS_WORLD)
    assert level < 0.1 and tilted < 0.1
    # the rebuilt vertical component is what makes the tilted heading right: a wrong dip spoils it
    wrong = replace(cal, heading_model={"kind": "two_axis", "extended_dip_deg": dip + 5.0})
    assert _max_err(wrong, unit, attitude_grid(30.0, 30.0), TWO_AXIS_WORLD) > 1.0


def test_two_axis_refuses_without_level_turn_or_tilt():
    unit = _two_axis_unit()
    only_tilt = [p for p in _two_axis_poses() if p.step == "tilt"]
    rec = _rec(unit, only_tilt, TWO_AXIS_WORLD)
    with pytest.raises(InsufficientData, match=r"two_axis: needs a level turn.*bias and scale.*D"):
        two_axis(rec, _true_acc(unit))
    rec = _rec(unit, _level_poses(10.0), TWO_AXIS_WORLD)
    with pytest.raises(InsufficientData, match=r"two_axis: needs poses tilted.*extended dip"):
        two_axis(rec, _true_acc(unit))


# --------------------------------------------------------------------------------------------------
# maxmin
# --------------------------------------------------------------------------------------------------

MAXMIN_WORLD = World(inclination_deg=55.0, declination_deg=20.0)


def _maxmin_poses(world: World) -> list[Pose]:
    """Level turn, a y sweep in the field's vertical plane (x_b, z_b reach +-field) and an x sweep whose
    plane holds the field (y_b, z_b), in 1 deg steps so the dip is hit exactly."""
    d = world.declination_deg
    poses = _level_poses(5.0, samples=1)
    poses += [Pose("sweep_y", d, float(t), 0.0, 1) for t in range(0, 360)]
    poses += [Pose("sweep_x", (d - 90.0) % 360.0, 0.0, float(r), 1) for r in range(0, 360)]
    return poses


def test_maxmin_exact_for_bias_and_scale_only():
    unit = _with_mag(np.diag([3268.0, 3163.0, 3201.0]), np.array([423.0, -480.0, 301.0]))
    rec = _rec(unit, _maxmin_poses(MAXMIN_WORLD), MAXMIN_WORLD)
    cal = maxmin(rec, _true_acc(unit))
    np.testing.assert_allclose(cal.mag.k, [3268.0, 3163.0, 3201.0], rtol=1e-9)
    np.testing.assert_allclose(cal.mag.bias, [423.0, -480.0, 301.0], atol=1e-6)
    s = truth_summary(cal, unit, MAXMIN_WORLD)
    assert s["level_max"] < 1e-6 and s["tilted_max"] < 1e-6


def test_maxmin_leaves_misalignment():
    unit = reference_unit()
    rec = _rec(unit, _maxmin_poses(MAXMIN_WORLD), MAXMIN_WORLD)
    cal = maxmin(rec, _true_acc(unit))
    s = truth_summary(cal, unit, MAXMIN_WORLD)
    assert s["level_max"] > 0.1 and s["tilted_max"] > 0.1


def test_maxmin_refuses_when_an_axis_misses_the_field():
    unit = reference_unit(mag_noise_lsb=3.0)
    rec = _rec(unit, _level_poses(15.0))
    with pytest.raises(InsufficientData, match=r"(?s)maxmin.*z axis.*sweep about the y axis.*x axis"):
        maxmin(rec, _true_acc(unit))


def test_maxmin_without_table_angles_checks_the_span_from_the_readings():
    """A hand-held recording of a level spin: z never saw the field. maxmin wrote a calibration with k_z a
    fifth of x's (its check needs the table angles, and NaN passed it); now it is judged from the readings.
    A recording whose axes each met the field (the maxmin plan's poses, angles dropped) still calibrates."""
    unit = reference_unit(mag_noise_lsb=3.0)

    def hand_held(rec: Recording) -> Recording:
        nan = np.full(len(rec), np.nan)
        return Recording.from_arrays(rec.t, rec.step, nan, nan, nan, rec.mag, rec.acc, rec.temp_c, dict(rec.meta))

    with pytest.raises(InsufficientData, match=r"(?s)no table angles.*z axis: at its largest and smallest readings"):
        maxmin(hand_held(_rec(unit, _level_poses(15.0))), _true_acc(unit))
    cal = maxmin(hand_held(_rec(unit, _maxmin_poses(MAXMIN_WORLD), MAXMIN_WORLD)), _true_acc(unit))
    np.testing.assert_allclose(cal.mag.k, unit.mag.k, rtol=0.01)
    assert any("the span checked from the readings alone" in n for n in cal.notes)


def test_maxmin_refuses_default_poses_and_names_the_axes(reference_default):
    # the default y and x sweeps are made at psi_t = 315, whose planes miss the field (D = 23) by far
    _, rec, acc = reference_default
    with pytest.raises(InsufficientData) as e:
        maxmin(rec, acc)
    msg = str(e.value)
    assert "x axis: comes within 3" in msg and "sweep about the table's y axis (pitch) at psi_t = 2" in msg


def _run_calibrate(method: str, unit: Unit, world: World, seed: int = 2):
    """``calibrate`` with ``method`` offline (procedures.steps.simulate_run): slot 0's result and the
    table angles of every move."""
    proc = PROCEDURES["calibrate"]
    out, moves = simulate_run(proc.run(proc.validate({"method": method})), unit, world, np.random.default_rng(seed))
    return out.results[0], [(m.psi, m.theta, m.phi) for m in moves]


def test_maxmin_has_a_plan_that_points_every_axis_along_the_field():
    """method maxmin: its turns about y and x are made where the level turn found x and y along the
    field (here D = -37 deg, far from the default sweep azimuth), and each axis is then held at its
    extremes: the method is no longer refused, each axis reaches the field within a degree."""
    world = World(inclination_deg=62.0, declination_deg=-37.0)
    unit = random_unit(np.random.default_rng(5))
    result, moves = _run_calibrate("maxmin", unit, world)
    cal = result["calibration"]
    assert cal.method == "maxmin"
    [closest] = [n for n in cal.notes if n.startswith("maxmin: closest approach")]
    approach = [float(x) for x in closest.split(": ")[-1].replace("/", " ").replace(",", " ").split() if x[0].isdigit()]
    assert len(approach) == 6 and max(approach) < 2.0, closest
    sweep_psi = {round(m[0], 1) for m in moves if abs(m[1]) > 1 or abs(m[2]) > 1}
    assert all(min(abs(wrap180(p - d)) for d in (-37.0, -127.0)) < 3.0 for p in sweep_psi), sweep_psi
    np.testing.assert_allclose(cal.mag.k, unit.mag.k, rtol=0.01)  # the extremes are measured, not missed


def test_twelve_position_is_exact_on_a_linear_unit_and_finds_the_field():
    """Seed 002's twelve positions: noise-free, the bias, the full sensor matrix (misalignment
    included), I and D come out exact; with noise the heading error is small and the procedure
    visits exactly the twelve positions."""
    world = World(inclination_deg=48.0, declination_deg=-12.0)
    unit = random_unit(np.random.default_rng(11))
    exact = replace(unit, mag=replace(unit.mag, noise_lsb=0.0))
    rec = _rec(exact, twelve_position_poses(), world)
    cal = twelve_position(rec, _true_acc(exact))
    np.testing.assert_allclose(cal.mag.M, exact.mag.M, rtol=1e-3, atol=0.5)
    np.testing.assert_allclose(cal.mag.bias, exact.mag.bias, atol=0.5)
    assert abs(cal.inclination_deg - 48.0) < 0.01 and abs(wrap180(cal.declination_deg + 12.0)) < 0.01
    # the truth itself is not error-free here (quantised counts): within 0.05 deg of its figure
    truth = Calibration("truth", exact.mag, acc=exact.acc)
    truth.inclination_deg, truth.declination_deg = 48.0, -12.0
    assert truth_summary(cal, exact, world)["tilted_max"] < truth_summary(truth, exact, world)["tilted_max"] + 0.05

    result, moves = _run_calibrate("twelve-position", unit, world)
    assert sorted(set(moves)) == sorted(set(TWELVE_POSITIONS))
    s = truth_summary(result["calibration"], unit, world)
    assert s["level_max"] < 0.1 and s["tilted_max"] < 0.2


def test_twelve_position_refuses_without_its_faces_and_names_them(reference_default):
    _, rec, acc = reference_default  # the default poses: no face has x or y vertical at two headings
    with pytest.raises(InsufficientData, match=r"twelve_position: needs each body axis.*missing: .*x down"):
        twelve_position(rec, acc)


# --------------------------------------------------------------------------------------------------
# all methods
# --------------------------------------------------------------------------------------------------

def test_results_carry_the_shared_fields(reference_default):
    unit, rec, acc = reference_default
    for fn in (ellipsoid, deviation5, two_axis):
        cal = fn(rec, acc)
        assert cal.serial == unit.serial and cal.acc is acc.sensor
        assert cal.base_tilt_deg == tuple(float(t) for t in acc.tilt_deg)
        assert cal.quality == {} and cal.sigma == {} and cal.notes
        Calibration.from_json(cal.to_json())  # JSON-ready


@pytest.mark.parametrize("seed", [7, 8])
def test_ellipsoid_on_random_production_units_is_the_symmetric_part(seed: int):
    """Random production units (quantised, 1-5 LSB noise, triad misaligned up to 3 deg, default poses):
    the ellipsoid's heading errors are those of the symmetric part of the true M, whatever it is."""
    unit = random_unit(np.random.default_rng(seed))
    rec = _rec(unit, calibration_poses())
    acc = accelerometer(rec)
    cal = ellipsoid(rec, acc)
    w, V = np.linalg.eigh(unit.mag.M @ unit.mag.M.T)
    sym = Calibration("sym", LinearSensor.from_matrix((V * np.sqrt(w)) @ V.T, unit.mag.bias), acc=cal.acc)
    grid = attitude_grid()
    np.testing.assert_allclose(truth_errors(cal, unit, WORLD, grid), truth_errors(sym, unit, WORLD, grid), atol=0.1)


def test_a_comparison_methods_misfit_is_said_to_be_the_methods_not_the_recordings():
    """The ellipsoid fit of a clean simulated recording leaves many times the noise against the table
    angles (it does not see the sensor's rotation to the body): the note blamed "physics the model leaves
    out ... the calibration is not to be trusted", sending a user to look for physics that is not there."""
    from physics.fit import fit

    rng = np.random.default_rng(5)
    rec = simulate_recording(random_unit(rng), calibration_poses(), World(55.0, 23.0), rng=rng)
    said = " ".join(fit(rec, "ellipsoid", bootstrap=0).notes)
    assert "times the noise" in said and "the ellipsoid method's model leaves out part of what the joint fit models" in said
    assert "physics the model leaves out" not in said
    assert not any("times the noise" in n for n in fit(rec, "joint", bootstrap=0).notes)


def test_a_fit_near_the_magnetic_pole_says_heading_is_poorly_defined_there():
    """At I = 88 deg the field's horizontal part is 3.5 % of it: the level heading error was about a degree
    (and at 90 deg, 170 deg with D "250 +- 45") without a word; the note says why."""
    from physics.fit import fit

    rng = np.random.default_rng(2)
    unit = random_unit(rng)
    near = " ".join(fit(simulate_recording(unit, calibration_poses(), World(88.0, 23.0), rng=rng), "joint", bootstrap=0).notes)
    assert "deg from vertical" in near and "times as sensitive" in near
    usual = " ".join(fit(simulate_recording(unit, calibration_poses(), World(60.0, 23.0), rng=rng), "joint", bootstrap=0).notes)
    assert "from vertical" not in usual
