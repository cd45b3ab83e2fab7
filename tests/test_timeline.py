"""The time-stepped simulator (physics.simulate.simulate_timeline): each concealed effect changes the
clean recording exactly as its closed form says, the motion and sampling follow the plan, and the
noise is what Noise says it is."""

from __future__ import annotations


import numpy as np
import pytest

from physics.effects import (HYSTERESIS_STEP, FieldDrift, FieldGradient, Hysteresis, MainsInterference, Nonlinearity,
                             StageHardIron, StageSoftIron, TableAxisError, TemperatureDrift, TimeLag, gradient_matrix,
                             stage_to_body)
from physics.frames import rot_x, rot_y
from physics.sensor import random_unit, reference_unit
from physics.simulate import (ENCODER_STEP_DEG, Noise, Pose, Scan, World, ar1_whiten, plan_timeline, simulate_recording,
                              simulate_timeline)
from physics.table import Motion, TableGeometry, move_seconds, platform_attitude

MOTION = Motion()
RATE = MOTION.sample_rate_hz
WORLD = World(55.0, 45.0, TableGeometry(base_tilt_deg=(0.03, -0.05)), temperature_c=21.0, warmup_c=3.0, warmup_tau_s=200.0)


def small_plan(samples: int = 20) -> list[Pose | Scan]:
    """Holds at several azimuths and tilts approached from both sides, turns about z both ways at two
    speeds, a turn about y, and a closing hold repeating the first."""
    plan: list[Pose | Scan] = [Pose("first", 0, 0, 0, samples, approach_deg=10.0)]
    plan += [Pose(f"up {psi}", psi, 0, 0, samples, approach_deg=10.0) for psi in range(45, 360, 45)]
    plan += [Pose(f"down {psi}", psi, 0, 0, samples, approach_deg=-10.0) for psi in (0, 90, 180, 270)]
    for psi in (0, 120, 240):
        plan += [Pose(f"theta {th} at {psi}", psi, th, 0, samples, approach_deg=10.0) for th in (-60, -30, 30, 60)]
        plan += [Pose(f"phi {ph} at {psi}", psi, 0, ph, samples, approach_deg=-10.0) for ph in (-60, -30, 30, 60)]
    plan += [Pose("both", 45, 30, 30, samples)]
    plan += [Scan("z up slow", "psi", -180, 180, 10.0), Scan("z down fast", "psi", 180, -180, 30.0),
             Scan("y up", "theta", -60, 60, 10.0, psi_t=30.0)]
    plan += [Pose("closing", 0, 0, 0, samples, approach_deg=10.0)]
    return plan


def quiet_unit(seed: int = 0):  # noqa: ANN201
    """A random unit (misaligned, biased) with no noise and no quantisation on either sensor."""
    u = random_unit(np.random.default_rng(seed), mag_noise_lsb=0.0, acc_noise_lsb=0.0)
    from dataclasses import replace
    return replace(u, mag=replace(u.mag, quantized=False), acc=replace(u.acc, quantized=False))


NO_NOISE = Noise(0.0, 0.0, quantized=False)


def clean(plan, effects=(), world=WORLD, unit=None):  # noqa: ANN001, ANN201
    unit = unit or quiet_unit()
    return simulate_timeline(unit, plan, world, MOTION, effects, NO_NOISE, np.random.default_rng(0))[1]


def rows(rec, step: str) -> np.ndarray:  # noqa: ANN001
    return np.flatnonzero(rec.step == step)


# ---------------------------------------------------------------------------------------------------
# Motion, sampling and the no-effect case
# ---------------------------------------------------------------------------------------------------

def test_no_effects_equals_simulate_recording_for_poses() -> None:
    unit = reference_unit()
    poses = [Pose(f"p{i}", psi, th, ph, 10) for i, (psi, th, ph) in
             enumerate([(0, 0, 0), (90, 0, 0), (200, 0, 0), (30, 45, 0), (30, 0, -60), (300, 20, 70)])]
    world = World(60.0, 12.0, TableGeometry(base_tilt_deg=(0.05, 0.02)))
    a = simulate_recording(unit, poses, world, MOTION, np.random.default_rng(0))
    b, c = simulate_timeline(unit, poses, world, MOTION, noise=NO_NOISE, rng=np.random.default_rng(0))
    assert list(a.step) == list(b.step) == list(c.step)
    for name in ("psi_t", "theta_t", "phi_t"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert np.allclose(a.mag, b.mag, atol=1e-9) and np.allclose(a.mag, c.mag, atol=1e-9)
    assert np.allclose(a.acc, b.acc, atol=1e-9)
    # each hold starts at the compass's first sample after settling: at most one sample period later per hold
    lag = b.t - a.t
    assert np.all(lag >= -1e-9) and np.all(lag <= len(poses) / RATE + 1e-9)
    assert np.allclose(np.diff(b.t)[b.step[1:] == b.step[:-1]], 1 / RATE)


def test_timeline_moves_settles_and_samples_on_the_compass_clock() -> None:
    plan = [Pose("a", 90, 0, 0, 5), Pose("b", 90, 30, 0, 5, approach_deg=20.0)]
    tl = plan_timeline(plan, MOTION)
    t_a = move_seconds([90, 0, 0], MOTION) + MOTION.settle_s
    i_a = int(np.ceil(t_a * RATE - 1e-9))
    assert tl.keep[:5].tolist() == list(range(i_a, i_a + 5))
    end_a = (i_a + 5) / RATE
    # b: first to psi 70 (and theta 30: all axes move together), then to psi 90, then settle
    t_b = end_a + move_seconds([-20, 30, 0], MOTION) + move_seconds([20, 0, 0], MOTION) + MOTION.settle_s
    assert tl.keep[5] == int(np.ceil(t_b * RATE - 1e-9))
    mid = end_a + move_seconds([-20, 30, 0], MOTION)
    assert np.allclose(tl.angles([mid]), [[70, 30, 0]])
    assert tl.n >= tl.keep[-1] + 1


def test_scan_turns_at_its_speed_and_records_continuous_angles() -> None:
    plan = [Scan("z", "psi", -90, 90, 10.0, theta_t=20.0)]
    rec = clean(plan)
    psi = rec.psi_t
    assert psi[0] == pytest.approx(-90, abs=1e-9) and psi[-1] == pytest.approx(90, abs=0.02)
    assert np.all(rec.theta_t == 20.0) and np.all(rec.phi_t == 0.0)
    speed = np.diff(psi) * RATE
    ramp = 10.0 / MOTION.max_accel_dps2
    steady = (rec.t[1:] - rec.t[0] > ramp + 0.05) & (rec.t[-1] - rec.t[1:] > ramp + 0.05)
    assert np.allclose(speed[steady], 10.0)
    assert np.all(speed >= 0) and speed.max() <= 10.0 + 1e-9
    # the whole turn is sampled, ramps included: 180 deg at 10 deg/s plus one ramp time
    assert len(rec) == pytest.approx((18.0 + ramp) * RATE, abs=2)
    noisy, _ = simulate_timeline(quiet_unit(), plan, WORLD, MOTION, noise=NO_NOISE)
    assert np.allclose(noisy.psi_t, np.round(psi / ENCODER_STEP_DEG) * ENCODER_STEP_DEG)
    assert len(np.unique(noisy.psi_t)) > 300  # continuous, not the commanded holds


def test_temperature_follows_warm_up() -> None:
    rec = clean(small_plan())
    expected = 21.0 + 3.0 * (1 - np.exp(-rec.t / 200.0))
    assert np.allclose(rec.temp_c, expected)
    assert WORLD.temperature_at(0.0) == pytest.approx(21.0)
    assert np.allclose(WORLD.temperature_at(np.array([200.0, 1e9])), [21.0 + 3.0 * (1 - np.exp(-1)), 24.0])


def test_simulate_timeline_of_a_ten_minute_plan_records_every_planned_sample() -> None:
    """(Its speed, < 1 s for a 10-minute plan, is measured by benchmarks/procedure.py, not timed here.)"""
    plan = small_plan(samples=60) * 2
    tl = plan_timeline(plan, MOTION)
    assert tl.duration_s > 500
    unit = random_unit(np.random.default_rng(1))
    rec, clean = simulate_timeline(unit, plan, WORLD, MOTION, [StageHardIron("outer", [0.01, 0.0, 0.02]),
                                                              Hysteresis([0.002, 0.001, 0.0])],
                                   Noise(3.0, 0.7), np.random.default_rng(0))
    assert len(rec) == len(clean) == len(tl.keep) and np.all(np.isfinite(rec.mag))


# ---------------------------------------------------------------------------------------------------
# Each effect against its closed form
# ---------------------------------------------------------------------------------------------------

def _hold_field(world: World, psi: float, theta: float, phi: float, geometry: TableGeometry | None = None) -> tuple[np.ndarray, np.ndarray]:
    C = platform_attitude(psi, theta, phi, geometry or world.geometry)[0]
    return C, C.T @ world.field_L


@pytest.mark.parametrize("stage", ["outer", "middle"])
def test_stage_hard_iron_adds_the_magnet_turned_into_the_body(stage: str) -> None:
    plan = small_plan()
    m = np.array([0.02, -0.01, 0.03])
    unit = quiet_unit()
    base = clean(plan, unit=unit)
    d = clean(plan, [StageHardIron(stage, m)], unit=unit).mag - base.mag
    for step in ("theta 30 at 120", "phi -60 at 240", "both"):
        i = rows(base, step)
        th, ph = base.theta_t[i[0]], base.phi_t[i[0]]
        Q = (rot_y(th) @ rot_x(ph)).T if stage == "outer" else rot_x(ph).T
        assert np.allclose(d[i], unit.mag.M @ Q @ m, atol=1e-9)


def test_stage_soft_iron_adds_the_induced_field() -> None:
    plan = small_plan()
    A = np.array([[0.01, 0.002, 0.0], [0.002, -0.005, 0.003], [0.0, 0.003, 0.004]])
    unit = quiet_unit()
    base = clean(plan, unit=unit)
    d = clean(plan, [StageSoftIron("outer", A)], unit=unit).mag - base.mag
    i = rows(base, "both")
    _, h = _hold_field(WORLD, 45, 30, 30)
    Q = stage_to_body("outer", 30, 30)
    assert np.allclose(d[i], unit.mag.M @ (Q @ A @ Q.T @ h), atol=1e-9)


def test_nonlinearity_adds_the_cubic_of_the_linear_output() -> None:
    plan = small_plan()
    unit = quiet_unit()
    c3 = np.array([20.0, -10.0, 5.0])
    base = clean(plan, unit=unit)
    got = clean(plan, [Nonlinearity(c3, unit.mag.k, unit.mag.bias)], unit=unit)
    u = (base.mag - unit.mag.bias) / unit.mag.k
    assert np.allclose(got.mag, base.mag + c3 * u ** 3, atol=1e-9)


def test_temperature_drift_follows_the_warm_up() -> None:
    plan = small_plan()
    unit = quiet_unit()
    k = np.array([4.0, -2.0, 1.0])
    base = clean(plan, unit=unit)
    got = clean(plan, [TemperatureDrift(k, t_ref_c=23.0)], unit=unit)
    assert np.allclose(got.mag - base.mag, np.outer(base.temp_c - 23.0, k), atol=1e-9)


def test_field_drift_turns_with_the_table() -> None:
    plan = small_plan()
    unit = quiet_unit()
    rate = np.array([1e-4, -2e-4, 5e-5])
    base = clean(plan, unit=unit)
    d = clean(plan, [FieldDrift(rate)], unit=unit).mag - base.mag
    C = platform_attitude(base.psi_t, base.theta_t, base.phi_t, WORLD.geometry)
    expected = np.einsum("ij,nj->ni", unit.mag.M, np.einsum("nji,j->ni", C, rate) * base.t[:, None])
    assert np.allclose(d, expected, atol=1e-9)


def test_time_lag_shifts_scan_samples_by_lag_times_speed() -> None:
    plan = small_plan()
    unit = quiet_unit()
    lag = 0.05
    base = clean(plan, unit=unit)
    got = clean(plan, [TimeLag(lag)], unit=unit)
    # the recorded angles are the true ones at the sample instant, not the lagged ones
    assert np.array_equal(got.psi_t, base.psi_t)
    for step, speed in (("z up slow", 10.0), ("z down fast", -30.0)):
        i = rows(base, step)
        t = base.t[i]
        ramp = abs(speed) / MOTION.max_accel_dps2
        steady = i[(t - t[0] > ramp + lag + 0.05) & (t[-1] - t > ramp + 0.05)]
        h = np.array([_hold_field(WORLD, base.psi_t[j] - speed * lag, 0.0, 0.0)[1] for j in steady])
        expected = h @ unit.mag.M.T + unit.mag.bias
        assert np.allclose(got.mag[steady], expected, atol=1e-6)
        assert np.abs(got.mag[steady] - base.mag[steady]).max() > 1.0  # it did move the samples
    # holds are long past the lag: unchanged
    hold = np.isin(base.step, ["first", "theta 30 at 120", "closing"])
    assert np.allclose(got.mag[hold], base.mag[hold], atol=1e-9)


def test_hysteresis_makes_the_two_approach_sides_differ() -> None:
    plan = [Pose("up", 90, 0, 0, 10, approach_deg=10.0), Pose("down", 90, 0, 0, 10, approach_deg=-10.0),
            Pose("up again", 90, 0, 0, 10, approach_deg=10.0)]
    unit = quiet_unit()
    offset = np.array([0.01, -0.02, 0.005])
    base = clean(plan, unit=unit)
    got = clean(plan, [Hysteresis(offset)], unit=unit)

    def h(psi: float) -> np.ndarray:
        return _hold_field(WORLD, psi, 0, 0)[1]

    s_up, s_down = np.sign(h(90) - h(80)), np.sign(h(90) - h(100))
    assert np.all(np.abs(h(90) - h(80))[:2] > HYSTERESIS_STEP) and np.all(np.abs(h(90) - h(100))[:2] > HYSTERESIS_STEP)
    s_up[2] = s_down[2] = 0.0  # a level turn never changes h_z: its sign is still unset
    d = got.mag - base.mag
    assert np.allclose(d[rows(base, "up")], unit.mag.M @ (offset * s_up), atol=1e-9)
    assert np.allclose(d[rows(base, "down")], unit.mag.M @ (offset * s_down), atol=1e-9)
    assert np.allclose(d[rows(base, "up again")], unit.mag.M @ (offset * s_up), atol=1e-9)
    assert not np.allclose(got.mag[rows(base, "up")].mean(0), got.mag[rows(base, "down")].mean(0))


def test_effect_state_does_not_leak_between_runs() -> None:
    plan = small_plan()
    eff = Hysteresis([0.01, 0.01, 0.01])
    a, b = clean(plan, [eff]), clean(plan, [eff])
    assert np.array_equal(a.mag, b.mag)
    assert eff._state == {}  # the caller's object is untouched


def test_table_axis_error_changes_the_geometry_for_both_sensors() -> None:
    plan = small_plan()
    unit = quiet_unit()
    eff = TableAxisError([0.2, -0.1], [0.3, 0.15])
    got = clean(plan, [eff], unit=unit)
    g = WORLD.geometry
    world2 = World(WORLD.inclination_deg, WORLD.declination_deg,
                   TableGeometry(g.base_tilt_deg, (0.2, -0.1), (0.0, 0.3, 0.15)), WORLD.temperature_c, WORLD.warmup_c,
                   WORLD.warmup_tau_s)
    ref = clean(plan, world=world2, unit=unit)
    assert np.allclose(got.mag, ref.mag) and np.allclose(got.acc, ref.acc)
    base = clean(plan, unit=unit)
    assert np.abs(got.acc - base.acc).max() > 10  # the accelerometer sees the axis errors too


def test_field_gradient_adds_the_field_at_the_sensor_offset() -> None:
    plan = small_plan()
    unit = quiet_unit()
    g5, off = [0.5, -0.2, 0.1, 0.3, -0.4], np.array([0.03, -0.02, 0.05])
    base = clean(plan, unit=unit)
    d = clean(plan, [FieldGradient(g5, off)], unit=unit).mag - base.mag
    C = platform_attitude(base.psi_t, base.theta_t, base.phi_t, WORLD.geometry)
    G = gradient_matrix(g5)
    expected = np.einsum("nji,jk,nkl,l->ni", C, G, C, off) @ unit.mag.M.T
    assert np.allclose(d, expected, atol=1e-9)


@pytest.mark.parametrize("freq", [50.2, 59.9])
def test_mains_aliases_to_the_expected_frequency(freq: float) -> None:
    plan = [Pose("long", 30, 0, 0, 1200)]  # 60 s
    unit = quiet_unit()
    amp = np.array([8.0, -3.0, 2.0])
    eff = MainsInterference(amp, freq, phase_rad=0.4, sample_rate_hz=RATE)
    base = clean(plan, unit=unit)
    d = clean(plan, [eff], unit=unit).mag - base.mag
    assert np.allclose(d, np.outer(np.cos(2 * np.pi * freq * base.t + 0.4), amp), atol=1e-9)
    spec = np.abs(np.fft.rfft(d[:, 0] - d[:, 0].mean()))
    f = np.fft.rfftfreq(len(d), 1 / RATE)
    assert f[np.argmax(spec)] == pytest.approx(eff.alias_hz, abs=2 / (len(d) / RATE))
    assert eff.alias_hz == pytest.approx({50.2: 9.8, 59.9: 0.1}[freq])


# ---------------------------------------------------------------------------------------------------
# Noise
# ---------------------------------------------------------------------------------------------------

def test_ar1_noise_has_its_marginal_sigma_and_colour_and_whitens() -> None:
    rng = np.random.default_rng(3)
    noise = Noise((2.0, 3.0, 4.0), 0.8)
    x = noise.sample(200_000, rng)
    assert np.allclose(x.std(axis=0), [2.0, 3.0, 4.0], rtol=0.03)
    r1 = [np.corrcoef(x[1:, j], x[:-1, j])[0, 1] for j in range(3)]
    assert np.allclose(r1, 0.8, atol=0.01)
    # a subset of the instants with gaps (holds between moves) whitens exactly with phi ** gap
    t = np.arange(len(x)) / RATE
    keep = np.flatnonzero((np.arange(len(x)) % 50) < 20)
    w = noise.whiten(x[keep], t[keep], RATE)
    assert np.allclose(w.std(axis=0), 1.0, atol=0.02)
    assert np.all(np.abs([np.corrcoef(w[1:, j], w[:-1, j])[0, 1] for j in range(3)]) < 0.01)
    # restarting segments: each starts stationary
    y = Noise(1.0, 0.9).sample(40_000, rng, segments=np.arange(0, 40_000, 4))
    assert y.std() == pytest.approx(1.0, rel=0.03)
    assert np.allclose(ar1_whiten(np.ones((3, 2)), [0.0, 0.05, 0.1], RATE, 0.0), 1.0)


def test_noisy_recording_is_clean_plus_quantised_noise() -> None:
    plan = small_plan()
    unit = random_unit(np.random.default_rng(2))
    noise = Noise(3.0, 0.5, quantized=True)
    rec, cln = simulate_timeline(unit, plan, WORLD, MOTION, [TimeLag(0.02)], noise, np.random.default_rng(1))
    assert np.array_equal(rec.mag, np.round(rec.mag))
    e = rec.mag - cln.mag
    assert e.std() == pytest.approx(np.sqrt(9 + 1 / 12), rel=0.1)
    assert np.array_equal(rec.acc, np.round(rec.acc))
    assert list(rec.step) == list(cln.step) and np.array_equal(rec.t, cln.t)
    assert np.allclose(rec.psi_t, cln.psi_t, atol=ENCODER_STEP_DEG / 2 + 1e-12)
    assert "effects" not in " ".join(rec.meta)  # nothing of the truth in the recording
