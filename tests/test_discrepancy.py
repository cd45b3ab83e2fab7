"""The discrepancy analyser (physics/discrepancy/) on simulated recordings with concealed effects.

The recordings come from the time-stepped simulator (physics/simulate.simulate_timeline), which applies
the catalogue's concealment classes sample by sample; the analyser sees only the recording.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from physics import effects as fx
from physics.calibration import Calibration
from physics.discrepancy import analyze
from physics.recording import Recording
from physics.sensor import LinearSensor, random_unit
from physics.simulate import Noise, Pose, World, simulate_recording, simulate_timeline
from procedures.calibrate import CalibrateParams, calibration_poses, characterize_plan

PLAN = characterize_plan()
WORLD = World(inclination_deg=60.0, declination_deg=100.0, warmup_c=3.0, warmup_tau_s=200.0)


def _record(effects: list[fx.Effect], seed: int = 5, noise: Noise = Noise(3.0, 0.5, True), plan=PLAN,
            unit=None) -> tuple[Recording, Recording]:
    rng = np.random.default_rng(seed)
    unit = unit or random_unit(rng)
    return simulate_timeline(unit, plan, WORLD, effects=effects, noise=noise, rng=rng)


def _unit(seed: int = 5):
    return random_unit(np.random.default_rng(seed))


def _effect(name: str, unit) -> fx.Effect:
    """One clearly visible instance of each catalogue effect (tens of sigma on the characterize plan)."""
    return {
        "stage_hard_iron": lambda: fx.StageHardIron("outer", [0.002, -0.0015, 0.001]),
        "stage_soft_iron": lambda: fx.StageSoftIron("middle", fx.symmetric([0.0, 0.002, -0.002, 0.001, -0.001, 0.0015])),
        "nonlinearity": lambda: fx.Nonlinearity([6.0, -4.0, 5.0], unit.mag.k, unit.mag.bias),
        "temperature_drift": lambda: fx.TemperatureDrift([2.0, -1.5, 2.5]),
        "field_drift": lambda: fx.FieldDrift([3e-6, -2e-6, 2e-6]),
        "time_lag": lambda: fx.TimeLag(0.01),
        "hysteresis": lambda: fx.Hysteresis([0.001, -0.0008, 0.001]),
        "table_axis_error": lambda: fx.TableAxisError([0.03, -0.02], [0.03, 0.02]),
        "field_gradient": lambda: fx.FieldGradient([0.05, -0.03, 0.02, 0.04, -0.02], [0.04, -0.03, 0.02]),
        "mains_interference": lambda: fx.MainsInterference([1.5, -0.5, 1.0], 50.13, 0.3),
    }[name]()


def test_null_is_consistent_and_the_report_is_complete() -> None:
    rec, _ = _record([])
    a = analyze(rec, null_sims=50)
    r = a.result
    assert r["verdict"] == "consistent", r["findings"]
    json.dumps(r)  # JSON-safe
    for key in ("noise_floor_lsb", "noise_ar1", "residual_rms_before_lsb", "residual_rms_after_lsb"):
        assert len(r[key]) == 3
    # the noise floor and its colour are measured, not assumed
    assert np.allclose(r["noise_floor_lsb"], 3.0, rtol=0.1)
    assert np.allclose(r["noise_ar1"], 0.5, atol=0.08)
    assert r["untestable"] == []  # the characterize plan makes every entry testable
    assert {t["effect"] for t in r["tests"] if not t["generic"]} == set(fx.CATALOGUE) | {"discovered"}
    assert a.series["residual_before"].shape == (len(rec), 3)
    assert set(np.unique(a.series["fold"])) == {0, 1, 2, 3}


def test_nulls_false_alarm_rarely() -> None:
    """Over random units, noise colours and quantisation: at alpha 0.01 at most one alarm in 12."""
    alarms = []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        noise = Noise(float(rng.uniform(1, 5)), float(rng.choice([0.0, rng.uniform(0.3, 0.9)])), True)
        rec, _ = _record([], seed=100 + seed, noise=noise)
        r = analyze(rec, null_sims=30).result
        if r["verdict"] != "consistent":
            alarms.append((seed, [f["effect"] for f in r["findings"]]))
    assert len(alarms) <= 1, alarms


def test_a_null_calibrated_p_is_never_lighter_tailed_than_the_bartlett_scaled_chi_square() -> None:
    """The tests' null distribution is c chi2(nu) from the mean and variance of a few hundred simulated
    statistics. The variance is uncertain by +-10 %; a low draw (nu above df) made the tail lighter than
    chi-square and p several times too small at 1e-4, where the tests decide (false alarms on nulls).
    Whatever the draw, p is at least that of the Bartlett-scaled chi2(df)."""
    from scipy import stats

    from physics.discrepancy.lrt import Test, _orth, _score
    rng = np.random.default_rng(4)
    n, df = 600, 27
    basis = _orth(rng.normal(size=(n, df)))
    lighter = 0
    for _ in range(40):
        null = rng.normal(size=(200, n))
        y = basis @ rng.normal(size=df) * 1.6  # a large statistic, far in the tail
        t = Test("x", basis)
        _score([t], y, null)
        mean = float(np.mean(np.sum((null @ basis) ** 2, axis=1)))
        floor = float(stats.chi2.sf(t.statistic * df / mean, df))
        lighter += t.p_value < floor * (1 - 1e-9)
    assert lighter == 0


@pytest.mark.parametrize("name", list(fx.CATALOGUE))
def test_each_concealed_effect_is_found_named_and_fitted(name: str) -> None:
    unit = _unit()
    effect = _effect(name, unit)
    rec, clean = _record([effect], unit=unit)
    a = analyze(rec, null_sims=30)
    r = a.result
    assert r["verdict"] == "discrepancy"
    named = [f["effect"] for f in r["findings"]]
    assert named[0] == name or name in r["findings"][0]["confusable_with"], named
    f = next(f for f in r["findings"] if f["effect"] == name)
    assert f["p_adjusted"] < 1e-6 and f["heading_impact_deg"] > 0
    # residuals after the fit are back to the noise, and better than before, in and out of sample
    assert np.mean(r["residual_rms_after_lsb"]) < np.mean(r["residual_rms_before_lsb"])
    assert r["heldout"]["improvement_pct"] > 0
    ho = np.sqrt(np.mean((rec.mag - a.series["heldout_pred_after"]) ** 2))
    truth = np.sqrt(np.mean((rec.mag - clean.mag) ** 2))
    assert ho < 1.05 * truth
    _check_parameters(name, effect, f)


def _check_parameters(name: str, effect: fx.Effect, f: dict) -> None:
    """Every parameter the recording determines (finite sigma) is within 4.5 sigma of the truth."""
    truth = effect.params()
    keys = {"stage_hard_iron": ["m"], "nonlinearity": ["c3"], "temperature_drift": ["bias_per_c"],
            "field_drift": ["rate_per_s"], "time_lag": ["lag_s"], "hysteresis": ["offset"],
            "table_axis_error": ["nonperp_deg", "encoder_zero_deg"]}.get(name, [])
    if name == "stage_hard_iron":
        assert f["parameters"]["stage"] == truth["stage"]
    if name == "mains_interference":
        assert f["parameters"]["alias_hz"] == pytest.approx(truth["alias_hz"], abs=2e-3)
        est = np.abs(f["parameters"]["amplitude_lsb"])
        assert np.allclose(est, np.abs(truth["amplitude_lsb"]), atol=0.15)
    for k in keys:
        est = np.atleast_1d(np.asarray(f["parameters"][k], float))
        sd = np.atleast_1d(np.asarray([np.inf if s is None else s for s in np.atleast_1d(f["sigma"][k])], float))
        tru = np.atleast_1d(np.asarray(truth[k], float))
        ok = np.isfinite(sd)
        assert ok.any()
        z = (est[ok] - tru[ok]) / sd[ok]
        assert np.all(np.abs(z) < 4.5), (k, est, tru, sd)


def test_motion_effects_are_untestable_without_motion() -> None:
    rng = np.random.default_rng(3)
    rec = simulate_recording(random_unit(rng), calibration_poses(CalibrateParams()), World(), rng=rng)
    r = analyze(rec, null_sims=20).result
    reasons = {u["effect"]: u["reason"] for u in r["untestable"]}
    assert "time_lag" in reasons and "turns" in reasons["time_lag"]
    assert "temperature_drift" in reasons


def test_indistinguishable_effects_are_reported_together_with_the_experiment_that_separates_them() -> None:
    """The 18-pose calibration plan sweeps the inner axes at one azimuth only: a magnet on the outer
    stage and a field gradient leave the same residual there, so both are named, with the experiment
    (tilted poses at several azimuths) that would tell them apart."""
    rec, _ = _record([fx.StageHardIron("outer", [0.003, -0.002, 0.0])], plan=calibration_poses(CalibrateParams()))
    r = analyze(rec, null_sims=20).result
    assert r["verdict"] == "discrepancy"
    first = r["findings"][0]
    assert {first["effect"], *first["confusable_with"]} == {"stage_hard_iron", "field_gradient"}, r["findings"]
    assert "azimuth" in first["separating_experiment"] or "characterize" in first["separating_experiment"]


def test_structure_outside_the_catalogue_is_reported_as_unexplained() -> None:
    rec, _ = _record([])
    bump = 6.0 * np.cos(np.radians(4 * rec.psi_t))  # a 4th harmonic on x only: no entry makes that
    mag = rec.mag.copy()
    mag[:, 0] += bump
    rec = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, mag, rec.acc, rec.temp_c, rec.meta)
    r = analyze(rec, null_sims=0).result  # the chi-square p alone: the structure is far beyond any null's
    unexplained = [f for f in r["findings"] if f["effect"] == fx.UNEXPLAINED]
    assert any("psi_t" in f["where"]["against"] for f in unexplained), r["findings"]


def test_a_platform_magnet_shows_as_a_parameter_shift_against_the_units_calibration() -> None:
    unit = _unit()
    rec, _ = _record([], unit=unit)
    before = analyze(rec, null_sims=0)
    nominal = before.result["nominal"]
    cal = Calibration(method="joint", mag=LinearSensor(np.array(nominal["M_o"]), np.array(nominal["k"]),
                                                       np.array(nominal["bias"]) + np.array([60.0, 0.0, 0.0])))
    r = analyze(rec, cal, null_sims=0).result
    shift = [f for f in r["findings"] if f["effect"] == fx.PARAMETER_SHIFT]
    assert shift and shift[0]["parameters"]["bias_lsb"][0] == pytest.approx(-60.0, abs=3.0)
    assert analyze(rec, replace(cal, mag=LinearSensor(cal.mag.M_o, cal.mag.k, np.array(nominal["bias"]))),
                   null_sims=0).result["verdict"] == "consistent"
    # the summary says what was found: a shift the nominal model absorbs (it said "the departures are
    # reported as unexplained structure, and the nominal model stands", with no unexplained finding)
    assert [f["effect"] for f in r["findings"]] == [fx.PARAMETER_SHIFT]
    assert r["summary"].startswith("The nominal parameters themselves depart from the unit's calibration") and "unexplained" not in r["summary"]


def test_a_unit_whose_own_fit_is_unusual_is_flagged_but_not_called_a_discrepancy() -> None:
    """Axis sensitivities 40 % apart and a bias of 4 fields (discrete sensors, a magnet in the housing): the
    nominal model fits the readings to their noise, so the verdict is "consistent" and the unusual parameters
    are a flag beside it (an outside probe's clean units drawn with each axis's k apart were all called
    discrepancies by the parameters alone, where the attitude-free model already said "consistent")."""
    u = _unit()
    k = u.mag.k * np.array([1.0, 1.4, 0.9])
    odd = replace(u, mag=replace(u.mag, k=k, bias=np.array([4.0 * k[0], 0.0, -50.0])))
    r = analyze(_record([], unit=odd)[0], null_sims=0).result
    [shift] = [f for f in r["findings"] if f["effect"] == fx.PARAMETER_SHIFT]
    mismatch = np.ptp(k) / np.median(k)
    assert shift["parameters"]["k_mismatch"] == pytest.approx(mismatch, abs=0.01)
    assert max(shift["parameters"]["bias_in_fields"]) == pytest.approx(4.0, abs=0.05)
    assert "Not a departure by itself" in shift["explanation"] and f"{100 * mismatch:.0f} % apart" in shift["explanation"]
    assert r["verdict"] == "consistent" and "unusual for one unit" in r["summary"], r["summary"]
    assert [f["effect"] for f in r["findings"]] == [fx.PARAMETER_SHIFT]


def test_a_recording_that_cannot_determine_the_nominal_says_so() -> None:
    """A level turn alone (a run failed after it) leaves the z axis's part of M and the field free: its own fit
    (k of 333 where the unit has 1100) was called "consistent" with the unit's calibration, unjudged and
    unsaid. The result says the nominal is undetermined, in its summary and notes."""
    rng = np.random.default_rng(3)
    unit = random_unit(rng)
    rec = simulate_recording(unit, calibration_poses(), World(), rng=rng)
    level = rec.step == "rotate_z"
    part = Recording.from_arrays(rec.t[level], rec.step[level], rec.psi_t[level], rec.theta_t[level], rec.phi_t[level],
                                 rec.mag[level], rec.acc[level], rec.temp_c[level], dict(rec.meta))
    r = analyze(part, null_sims=0).result
    assert r["nominal_determined"] is False
    assert r["summary"].startswith("These attitudes cannot determine the unit's nominal model")
    assert any("of the nominal model's 14 parameters" in n and "free" in n for n in r["notes"])
    whole = analyze(rec, null_sims=0).result
    assert whole["nominal_determined"] is True and not whole["summary"].startswith("These attitudes")


def test_too_short_a_recording_is_refused_with_the_reason() -> None:
    rng = np.random.default_rng(0)
    rec = simulate_recording(random_unit(rng), [Pose("a", 0.0, 0.0, 0.0, 10), Pose("b", 90.0, 0.0, 0.0, 10)],
                             World(), rng=rng)
    with pytest.raises(ValueError, match="at least 200 samples"):
        analyze(rec)


@pytest.mark.parametrize("angles", [True, False])
def test_a_recording_without_noise_is_refused_naming_the_axes(angles: bool) -> None:
    """A simulation without noise (the readings repeat exactly at rest): every statistic would be infinite.
    It used to crash the window search (an IndexError) or, without table angles, report findings against
    a noise floor of 0; now it is refused, naming the axes, by the table and the attitude-free model alike."""
    unit = random_unit(np.random.default_rng(0))
    unit = replace(unit, mag=replace(unit.mag, noise_lsb=0.0))
    rec = simulate_recording(unit, calibration_poses(), World(), rng=np.random.default_rng(1))
    assert np.all(np.diff(rec.mag[:60], axis=0) == 0.0)  # one hold's readings repeat exactly
    if not angles:
        nan = np.full(len(rec), np.nan)
        rec = Recording.from_arrays(rec.t, rec.step, nan, nan, nan, rec.mag, rec.acc, rec.temp_c, dict(rec.meta))
    with pytest.raises(ValueError, match="no measurable noise on mx, my, mz"):
        analyze(rec, null_sims=20)
    # one quiet axis is enough to refuse, and it is the one named
    noisy = rec.mag + np.column_stack([np.zeros(len(rec)), np.random.default_rng(2).normal(0.0, 3.0, (len(rec), 2))])
    rec = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, noisy, rec.acc, rec.temp_c, dict(rec.meta))
    with pytest.raises(ValueError, match=r"no measurable noise on mx \("):
        analyze(rec, null_sims=20)


def test_angles_in_the_wrong_convention_are_refused_naming_the_reading_that_fits() -> None:
    """Angles in radians, or one counted the other way: the nominal fit leaves hundreds of times the noise,
    and every effect fitted to that was invented (a 5,000-LSB offset "following the accelerometer", the
    level heading error 3.9 -> 12 deg "improved"). The recording is refused, naming the reading of the
    angles that fits; a large departure of real physics is analysed as before."""
    rng = np.random.default_rng(6)
    rec = simulate_recording(random_unit(rng), calibration_poses(), World(), rng=rng)

    def with_angles(psi, theta, phi, mag=rec.mag) -> Recording:
        return Recording.from_arrays(rec.t, rec.step, psi, theta, phi, mag, rec.acc, rec.temp_c, dict(rec.meta))

    with pytest.raises(ValueError, match=r"fit the nominal twin far better read in radians \(the hold means leave"):
        analyze(with_angles(*(np.radians(a) for a in (rec.psi_t, rec.theta_t, rec.phi_t))), null_sims=20)
    with pytest.raises(ValueError, match=r"cannot tell apart: .*psi_t negated"):
        analyze(with_angles(-rec.psi_t, rec.theta_t, rec.phi_t), null_sims=20)
    # a magnet of 15 % of the field on the unit for 40 % of the run: hundreds of sigma, but physics
    mag = rec.mag.copy()
    mag[300:730] += 0.15 * np.abs(rec.mag).max(axis=0)
    r = analyze(with_angles(rec.psi_t, rec.theta_t, rec.phi_t, mag), null_sims=20).result
    assert r["verdict"] == "discrepancy" and r["findings"][0]["model"]["frame"] == "sensor"


def test_consistent_says_what_the_recording_could_not_show() -> None:
    """One hold at one attitude is "consistent" with the twin, but it tests almost nothing: the summary says
    which catalogue effects and how many of the dictionary's inputs it cannot show."""
    rng = np.random.default_rng(2)
    one = simulate_recording(random_unit(rng), [Pose("hold", 0.0, 0.0, 0.0, 400)], World(), rng=rng)
    r = analyze(one, null_sims=20).result
    assert r["verdict"] == "consistent"
    assert "It cannot show 6 catalogue effect(s) (hysteresis, stage_hard_iron" in r["summary"]
    assert "of the dictionary's inputs or frames: see untestable" in r["summary"]


def test_bad_samples_are_left_out_and_named_but_a_short_event_is_analysed() -> None:
    """Brown-out rows (all axes 0) and lone garbage rows that passed the checksum are no physics: left in, they
    were reported as unexplained structure. They are left out and listed; ten rows of a magnet brought near
    within one hold are kept for the analysis to find."""
    rng = np.random.default_rng(4)
    rec = simulate_recording(random_unit(rng), calibration_poses(), World(), rng=rng)
    mag = rec.mag.copy()
    zeros, garbage = [130, 131, 611], [45, 402, 777, 1001]
    mag[zeros] = 0.0
    mag[garbage] = rng.integers(-32768, 32767, (len(garbage), 3))
    bad = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, mag, rec.acc, rec.temp_c, dict(rec.meta))
    r = analyze(bad, null_sims=50, seed=0).result
    assert r["verdict"] == "consistent" and r["samples"] == len(rec) - 7
    assert [row["index"] for row in r["rejected_rows"]] == sorted(zeros + garbage)
    assert r["notes"][0].startswith("7 of 1080 rows left out as bad samples (3 with a sensor's three axes exactly 0; 4 far off")
    # an axis clipped at the int16 limit for a whole hold: no reading there, said so with when
    clipped = rec.mag.copy()
    clipped[300:360, 2] = 32767.0
    cl = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, clipped, rec.acc, rec.temp_c, dict(rec.meta))
    r = analyze(cl, null_sims=50, seed=0).result
    assert r["verdict"] == "consistent" and [row["index"] for row in r["rejected_rows"]] == list(range(300, 360))
    assert f"60 saturated, at t {rec.t[300]:.1f}-{rec.t[359]:.1f} s" in r["notes"][0]
    # a magnet near the unit for the last ten samples of one hold: an event, not bad samples
    event = rec.mag.copy()
    event[290:300] += [400.0, -300.0, 250.0]
    ev = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, event, rec.acc, rec.temp_c, dict(rec.meta))
    r = analyze(ev, null_sims=50, seed=0).result
    assert "rejected_rows" not in r and r["verdict"] == "discrepancy"
    # ... nor is one arriving in a hold's last row (a lone row off its hold, but the departure carries on)
    event = rec.mag.copy()
    event[299:] += [400.0, -300.0, 250.0]
    ev = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, event, rec.acc, rec.temp_c, dict(rec.meta))
    assert "rejected_rows" not in analyze(ev, null_sims=50, seed=0).result
    # garbage in a hold's first or last row, the holds across those edges as the model says: bad samples
    # (left in, one row at 60 made "unexplained structure against psi_t harmonics")
    edges = rec.mag.copy()
    edges[60, 1] += 256.0  # first row of the third hold
    edges[419, 0] -= 4096.0  # last row of the fourteenth
    ed = Recording.from_arrays(rec.t, rec.step, rec.psi_t, rec.theta_t, rec.phi_t, edges, rec.acc, rec.temp_c, dict(rec.meta))
    r = analyze(ed, null_sims=50, seed=0).result
    assert r["verdict"] == "consistent" and [row["index"] for row in r["rejected_rows"]] == [60, 419]


def test_hysteresis_signs_follow_the_concealed_effect_through_unsampled_moves() -> None:
    """The analyser's hysteresis regressor is the concealed effect's sign state: on a path sampled a
    tenth of a degree apart both agree sample by sample; sampled only at the holds (the moves between
    them unsampled, up to 100 deg) the analyser follows each move along its encoder angles, so the
    signs at the holds are still the effect's."""
    from physics.discrepancy.registry import hysteresis_signs
    from physics.table import platform_attitude

    rng = np.random.default_rng(5)
    holds = np.cumsum(rng.uniform(-100, 100, (40, 3)), axis=0) * [1.0, 0.5, 0.5]
    fine = np.concatenate([a + np.linspace(0, 1, 1000, endpoint=False)[:, None] * (b - a) for a, b in zip(holds, holds[1:])])
    fine = np.vstack([fine, holds[-1]])
    v = np.array([0.35, -0.2, -0.91])
    v /= np.linalg.norm(v)
    h = np.einsum("nji,j->ni", platform_attitude(fine[:, 0], fine[:, 1], fine[:, 2]), v)
    effect = fx.Hysteresis([1.0, 1.0, 1.0])
    truth = np.rint([effect.body_field(0.0, 0, None, None, hb) - hb for hb in h])  # the sign state, +-1 or 0
    assert np.array_equal(hysteresis_signs(fine, v), truth)
    at_holds = np.arange(0, len(fine), 1000)
    assert np.array_equal(hysteresis_signs(fine[at_holds], v), truth[at_holds])
    assert {-1.0, 1.0} <= set(np.unique(truth[at_holds]))  # reversals happen between the holds


def test_the_registry_has_one_entry_per_catalogue_effect_and_builds_its_columns() -> None:
    """physics/discrepancy/registry.py: every catalogue id has an entry and every entry a catalogue id; on a
    recording, each effect (and each stage variant) gets columns (N, 3, len(labels)), or an empty block
    with the reason it cannot be tested; the line effect its columns at a frequency; and each entry says
    how the attitude-free model sees it, or why it needs table angles."""
    from physics.discrepancy import registry, twin

    assert set(registry.REGISTRY) == set(fx.CATALOGUE)
    assert all(fit.id == effect for effect, fit in registry.REGISTRY.items())
    rng = np.random.default_rng(3)  # static holds only: the motion and temperature effects say why not
    rec = simulate_recording(random_unit(rng), calibration_poses(CalibrateParams()), World(), rng=rng)
    ctx = twin.context(rec)
    nom = twin.fit_nominal(ctx, rec.mag)
    cols = registry.effect_columns(ctx, nom, rec.temp_c)
    n = len(rec)
    expected = set()
    for effect, fit in registry.REGISTRY.items():
        if fit.table is None:  # found by the line search: columns at the frequency found
            assert effect == registry.LINE and fit.line(ctx, 1.3).shape[:2] == (n, 3)
            continue
        stages = fx.STAGES if fx.CATALOGUE[effect].model[0] == "stage" else (None,)
        expected |= {effect if s is None else f"{effect}:{s}" for s in stages}
    assert set(cols) == expected
    for name, (X, labels, why) in cols.items():
        assert X.shape == (n, 3, len(labels)), name
        assert np.all(np.isfinite(X)), name
        assert why is None or (isinstance(why, str) and why), name
        assert X.shape[2] > 0 or why, f"{name}: an empty block must say why"
    assert cols["time_lag"][0].shape[2] == 0 and "turns" in cols["time_lag"][2]
    for effect, fit in registry.REGISTRY.items():
        if isinstance(fit.free, str):
            assert "needs table angles" in fit.free, effect
        else:
            assert fit.free.variants and all(b.split("/")[0] == effect for b in fit.free.variants), effect
            assert fit.free.raw or fit.free.magnitude or fit.free.dip, effect


def test_a_large_time_lag_is_fitted_exactly_and_nothing_else_is_named() -> None:
    """A lag of 0.2 s (within the catalogue's range) on the characterize plan: its first-order column left
    residue on the tilt scans that discovery named a middle-stage rotation, lab windows and six generic
    findings (residual 4.5 LSB on a floor of 3). The column is rebuilt as the exact shift by the lag
    fitted: the lag alone, to its sigma, the residual at the floor."""
    rec, _ = _record([fx.TimeLag(0.2)], noise=Noise(3.0, 0.0, True))
    r = analyze(rec, null_sims=100, seed=1).result
    assert [f["effect"] for f in r["findings"]] == ["time_lag"], [(f["effect"], f["explanation"][:80]) for f in r["findings"]]
    [f] = r["findings"]
    assert abs(f["parameters"]["lag_s"] - 0.2) < max(0.002, 4 * f["sigma"]["lag_s"]), f["parameters"]
    assert max(r["residual_rms_after_lsb"]) < 1.05 * max(r["noise_floor_lsb"]), r["residual_rms_after_lsb"]


def test_rows_written_twice_are_left_out_and_said():
    """Every row written twice (same time stamp and readings, a logger's fault) was "unexplained structure in
    time" at p 2e-284, a field varying too slowly for a hold to resolve. The repeats are left out as bad
    samples, saying so, and the recording is consistent; two rows with one time stamp but other readings
    are kept."""
    from physics.sensor import reference_unit

    rec = simulate_recording(reference_unit(3.0, 4.0), calibration_poses(CalibrateParams(samples=20)), World(),
                             rng=np.random.default_rng(1))
    twice = rec.select(np.repeat(np.arange(len(rec)), 2))
    r = analyze(twice, null_sims=50).result
    assert r["verdict"] == "consistent" and not r["findings"], r["findings"]
    assert f"{len(rec)} repeating the row before exactly (a sample written twice)" in r["notes"][0], r["notes"][0]
    assert len(r["rejected_rows"]) == len(rec) and r["rejected_rows"][0]["index"] == 1
    stamped = rec.select(slice(None))
    stamped.t[1] = stamped.t[0]  # one time stamp, two readings: both kept
    assert "a sample written twice" not in " ".join(analyze(stamped, null_sims=20).result["notes"])


def test_a_frozen_sensor_is_left_out_not_modelled_as_physics():
    """A compass that froze four times for 15 rows (its last reading repeated on all six axes, new time
    stamps): the repeats were "discovered" offsets following phi_t with a heading impact of 2.3 deg. They
    are left out as bad samples, saying so, and the recording is consistent."""
    from physics.sensor import reference_unit

    rec = simulate_recording(reference_unit(3.0, 4.0), calibration_poses(CalibrateParams(samples=30)), World(),
                             rng=np.random.default_rng(2))
    rec.mag, rec.acc = np.round(rec.mag), np.round(rec.acc)  # whole counts, as the compass reports them
    frozen = []
    for start in (50, 200, 330, 470):  # two of them across a move to the next pose
        rec.mag[start + 1:start + 16] = rec.mag[start]
        rec.acc[start + 1:start + 16] = rec.acc[start]
        frozen += list(range(start + 1, start + 16))
    r = analyze(rec, null_sims=50).result
    assert r["verdict"] == "consistent" and not r["findings"], [(f["effect"], f.get("model")) for f in r["findings"]]
    assert "60 repeating the row before on all six axes in runs (a frozen sensor)" in r["notes"][0], r["notes"][0]
    assert [row["index"] for row in r["rejected_rows"]] == frozen


def test_the_level_heading_errors_noise_is_the_scatter_of_clean_recordings() -> None:
    """``heading_error_deg.noise_rms`` is what the readings' noise alone makes of the level heading error:
    the variance of a hold's mean under the AR(1)-plus-white model matches simulated noise, and over clean
    recordings of one unit the nominal fit's level heading RMS scatters about it (in-sample a little
    under it: the fit takes part of the noise in)."""
    from physics.discrepancy.analysis import _heading_noise, _mean_variance
    from physics.discrepancy.noise import NoiseModel, estimate_noise, simulate_noise
    from physics.discrepancy.twin import context, fit_nominal
    from physics.discrepancy import level_heading_error

    model = NoiseModel(np.array([2.0, 2.5, 0.0]), np.array([0.8, 0.5, 0.0]), np.array([1.0, 0.5, 3.0]))
    n = np.array([1, 10, 60])
    sims = simulate_noise(60 * 3, model, np.repeat(np.arange(3), 60), np.random.default_rng(0), k=4000)
    got = np.array([sims[60 * i:60 * i + k].mean(axis=0).var(axis=1) for i, k in enumerate(n)])
    assert got == pytest.approx(_mean_variance(n, model), rel=0.08)

    unit = _unit(8)
    plan = [Pose("rotate_z", psi, 0.0, 0.0, 60) for psi in range(0, 360, 45)] + calibration_poses(CalibrateParams())
    rms, noise_rms = [], []
    for seed in range(12):
        rec, _ = simulate_timeline(unit, plan, WORLD, noise=Noise(3.0), rng=np.random.default_rng(100 + seed))
        rms.append(level_heading_error(rec)[1])
        ctx = context(rec)
        y = np.asarray(rec.mag, float)
        nom = fit_nominal(ctx, y)
        noise_rms.append(_heading_noise(ctx, y, nom, estimate_noise(y - nom.predict(ctx), ctx)))
    ratio = np.sqrt(np.mean(np.square(rms)) / np.mean(np.square(noise_rms)))
    assert 0.6 < ratio < 1.1, (ratio, rms, noise_rms)
    # and twice the noise makes twice the heading noise
    rec, _ = simulate_timeline(unit, plan, WORLD, noise=Noise(6.0), rng=np.random.default_rng(100))
    ctx, y = context(rec), np.asarray(rec.mag, float)
    nom = fit_nominal(ctx, y)
    assert _heading_noise(ctx, y, nom, estimate_noise(y - nom.predict(ctx), ctx)) == pytest.approx(2 * noise_rms[0], rel=0.15)


def test_ljung_box_is_the_textbook_statistic_on_any_layout_and_chi_square_on_white_columns() -> None:
    """noise.ljung_box on a transposed (non-contiguous) array, as the whiteness check passes it, equals
    n (n + 2) sum_k rho_k^2 / (n - k) computed one column at a time; on white columns its mean is the lags'
    count (chi-square), and an AR(1) column with phi 0.5 is far above it."""
    from scipy.signal import lfilter
    from physics.discrepancy.noise import ljung_box
    rng = np.random.default_rng(3)
    E = rng.normal(size=(400, 2000)).T
    E[:, 0] = lfilter([1.0], [1.0, -0.5], E[:, 0])
    q = ljung_box(E, 10)
    for j in (0, 1, 399):
        x = E[:, j] - E[:, j].mean()
        rho = np.array([np.dot(x[k:], x[:-k]) for k in range(1, 11)]) / np.dot(x, x)
        assert q[j] == pytest.approx(2000 * 2002 * np.sum(rho ** 2 / (2000 - np.arange(1, 11))), rel=1e-10)
    assert abs(np.mean(q[1:]) - 10.0) < 1.0 and q[0] > 300.0


def test_garbled_temperatures_are_interpolated_for_the_temperature_tests_and_said():
    """A temp_c of 9999 or -273.15 deg C in 3 % of the rows (a garbled field) made the temperature tests tests
    of those rows. Such values, and values far from their neighbours', are interpolated from the rows around
    them, saying which; the readings are kept, and a real step of the temperature stays."""
    from physics.discrepancy.analysis import _plausible_temperature

    rec, _ = _record([], seed=3)
    clean = analyze(rec, null_sims=50, seed=1).result
    odd = np.random.default_rng(1).choice(len(rec), round(0.03 * len(rec)), replace=False)
    garbled = rec.select(slice(None))
    garbled.temp_c[odd] = np.where(np.arange(len(odd)) % 2, 9999.0, -273.15)
    r = analyze(garbled, null_sims=50, seed=1).result
    assert r["verdict"] == clean["verdict"] and len(r["findings"]) == len(clean["findings"]), r["findings"]
    assert r["samples"] == clean["samples"]  # the readings kept
    assert any(n.startswith(f"temp_c of {len(odd)} row(s) is implausible") for n in r["notes"]), r["notes"]
    fixed, _ = _plausible_temperature(garbled)
    assert np.abs(fixed.temp_c - rec.temp_c).max() < 0.5
    stepped = rec.select(slice(None))
    stepped.temp_c = np.where(np.arange(len(rec)) < len(rec) // 2, 20.0, 35.0)  # a real step: kept
    assert _plausible_temperature(stepped)[1] is None
