"""Procedures run by a fake engine: the steps they emit, and what they conclude from data that the
physics forward model answers with. No I/O."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from physics.calibration import truth_summary
from physics.sensor import random_unit, reference_unit
from physics.simulate import World
from physics.table import TableGeometry
from procedures.calibrate import PROCEDURES, calibration_poses, CalibrateParams
from procedures.steps import MAX_PLAN_S, Acquire, Checkpoint, Compute, Move, Settle, step_seconds
from conftest import FakeEngine


def test_calibrate_emits_the_poses_in_order_then_fits_every_unit():
    units = [reference_unit(3.0, 4.0, serial="A"), random_unit(np.random.default_rng(4), mag_noise_lsb=1.0)]
    eng = FakeEngine(units, World(55.0, 23.0, TableGeometry(base_tilt_deg=(0.05, -0.08))))
    out = eng.run("calibrate")
    moves = [s for s in eng.steps if isinstance(s, Move)]
    poses = calibration_poses(CalibrateParams())
    assert [(m.psi, m.theta, m.phi) for m in moves] == [(p.psi_t, p.theta_t, p.phi_t) for p in poses]
    # each pose: move, settle, acquire, checkpoint
    assert eng.kinds()[:4] == ["Move", "Settle", "Acquire", "Checkpoint"]
    assert [s.step for s in eng.steps if isinstance(s, Acquire)] == [p.step for p in poses]
    assert sorted(out.results) == [0, 1]
    for slot, unit in enumerate(units):
        cal = out.results[slot]["calibration"]
        s = truth_summary(cal, unit, eng.world)
        assert s["level_max"] < 0.05 and s["tilted_max"] < 0.1, (slot, s)


def test_a_unit_with_unusable_data_gets_an_error_and_the_others_their_calibration():
    class Broken(FakeEngine):
        def __call__(self, step):
            out = super().__call__(step)
            if isinstance(step, Acquire):
                out[1].mag[:] = 0.0  # slot 1's magnetometer is dead
            return out
    eng = Broken([reference_unit(3.0, 4.0), reference_unit(3.0, 4.0, serial="B")])
    out = eng.run("calibrate", {"samples": 10})
    assert "calibration" in out.results[0]
    assert "error" in out.results[1] and out.results[1]["error"]


def test_params_are_validated_with_the_field_named():
    with pytest.raises(ValidationError, match="z_step_deg"):
        PROCEDURES["calibrate"].validate({"z_step_deg": 0})
    with pytest.raises(ValidationError, match="method"):
        PROCEDURES["calibrate"].validate({"method": "magic"})
    with pytest.raises(ValidationError, match="samplez"):
        PROCEDURES["calibrate"].validate({"samplez": 3})
    # every step and angle has a range a table can run: a step of 1e-300 failed on the table, an azimuth
    # of 1e308 after the level turn, -720.5 turned the table twice round (every procedure alike)
    for name, bad in (("calibrate", {"tilt_step_deg": 1e-300}), ("calibrate", {"sweep_psi_deg": 1e308}),
                      ("calibrate", {"sweep_psi_deg": -720.5}), ("rotate_z", {"theta_deg": 400}),
                      ("sweep", {"psi_deg": -361}), ("level", {"step_deg": 0.5}),
                      ("evaluate", {"tilt_step_deg": 0.01, "calibrations": {}}), ("calibrate", {"samples": "60"})):
        with pytest.raises(ValidationError, match=next(iter(bad))):
            PROCEDURES[name].validate(bad)
    PROCEDURES["calibrate"].validate({"sweep_psi_deg": -45.0, "z_step_deg": 1.0, "samples": 60.0})  # within range
    # a plan of days (a step and a count each within range) is refused whole, naming its length
    with pytest.raises(ValidationError, match=r"the plan would take [\d,]+ h of table time"):
        PROCEDURES["calibrate"].validate({"z_step_deg": 1, "tilt_step_deg": 1, "samples": 10_000})
    assert sum(step_seconds(PROCEDURES["calibrate"].plan(PROCEDURES["calibrate"].validate({})))) < MAX_PLAN_S / 100


def test_rotate_z_turns_about_z_at_fixed_tilt():
    eng = FakeEngine([reference_unit()])
    eng.run("rotate_z", {"step_deg": 90, "theta_deg": 10, "samples": 5, "settle_s": 0})
    assert [(m.psi, m.theta, m.phi) for m in eng.steps if isinstance(m, Move)] == [(a, 10, 0) for a in (0, 90, 180, 270)]
    assert "Settle" not in eng.kinds()


def test_sweep_finds_where_each_axis_peaks():
    eng = FakeEngine([reference_unit()], World(55.0, 23.0))
    out = eng.run("sweep", {"axis": "z", "step_deg": 30, "samples": 5})
    peak = np.array(out.results[0]["peak_deg"])
    # x_m points (nearly) along body x: it peaks when the table's heading is the field's, psi = D
    assert abs(((peak[0] - 23.0) + 180) % 360 - 180) < 3.0
    assert [m.psi for m in eng.steps if isinstance(m, Move)] == list(np.arange(0, 360, 30.0))


def test_accel6_recovers_the_accelerometer():
    unit = random_unit(np.random.default_rng(2))
    eng = FakeEngine([unit])
    out = eng.run("accel6", {"samples": 30})
    assert len([s for s in eng.steps if isinstance(s, Move)]) == 6
    np.testing.assert_allclose(out.results[0]["k"], unit.acc.k, rtol=2e-3)
    np.testing.assert_allclose(out.results[0]["bias"], unit.acc.bias, atol=30)


def test_level_measures_the_base_tilt_and_levels_the_platform():
    world = World(55.0, 23.0, TableGeometry(base_tilt_deg=(0.08, -0.05)))
    eng = FakeEngine([reference_unit(0.0, 2.0)], world)
    out = eng.run("level", {"samples": 40})
    np.testing.assert_allclose(out.results[0]["base_tilt_deg"], [0.08, -0.05], atol=0.01)
    last = [s for s in eng.steps if isinstance(s, Move)][-1]
    assert last.psi == 0 and abs(last.theta - 0.05) < 0.01 and abs(last.phi + 0.08) < 0.01


def test_evaluate_scores_a_calibration_on_the_table():
    unit = reference_unit(1.0, 2.0)
    world = World(55.0, 23.0, TableGeometry(base_tilt_deg=(0.03, 0.02)))
    eng = FakeEngine([unit], world, seed=5)
    cal = eng.run("calibrate").results[0]["calibration"]
    check = FakeEngine([unit], world, seed=6)
    out = check.run("evaluate", {"calibrations": {0: cal.to_json()}, "samples": 20, "tilted_samples": 20})
    r = out.results[0]
    assert r["level_max_deg"] < 0.05 and r["tilted_max_deg"] < 0.1
    assert 0 < r["level_noise_deg"] < 0.02
    # 8 level headings, then 4 headings at each (pitch, roll) in -60..60 in 60-degree steps but level
    assert len(r["error_deg"]) == 8 + 4 * 8
    # a wrong calibration is caught
    bad = cal.to_json()
    bad["field"]["declination_deg"] += 1.0
    out = FakeEngine([unit], world, seed=7).run("evaluate", {"calibrations": {0: bad}})
    assert out.results[0]["level_max_deg"] > 0.9


def test_plan_lists_the_steps_without_data():
    proc = PROCEDURES["calibrate"]
    steps = proc.plan(proc.validate({}))
    assert sum(isinstance(s, Acquire) for s in steps) == 18
    assert sum(isinstance(s, Checkpoint) for s in steps) == 18
    assert all(isinstance(s, (Move, Settle, Acquire, Checkpoint)) for s in steps[:-1])
    assert steps[-1] == Compute("calibration fit")  # said before the fit (on no data the plan ends there)


def test_maxmin_holds_its_extremes_in_a_short_tour_from_where_the_sweep_ended():
    """Maxmin holds each axis along and against the field after each sweep: visited nearest first, at the
    turn (a or a + 360) nearest the table, the middle and inner axes drive little more than the sweep's own
    span of extremes, not from 300 deg round to -145 and back (an axis drives to the angle it is given)."""
    from physics.simulate import plan_cost
    from physics.table import Motion
    from procedures.calibrate import _short_tour

    assert _short_tour({-145.0, 35.0, 80.0, -100.0}, 300.0, -180.0, 300.0) == [260.0, 215.0, 80.0, 35.0]
    eng = FakeEngine([reference_unit(3.0, 4.0)], World(55.0, 23.0))
    out = eng.run("calibrate", {"method": "maxmin", "samples": 10})
    assert "calibration" in out.results[0], out.results
    moves = [s for s in eng.steps if isinstance(s, Move)]
    for axis, sweep in ((1, "theta"), (2, "phi")):
        angles = [(m.psi, m.theta, m.phi)[axis] for m in moves]
        # the moves after this axis's sweep (its poses at 0, 60, ..., 300) that hold its extremes
        end = max(i for i, a in enumerate(angles) if a == 300.0)
        holds = [a for a in angles[end + 1:end + 5]]
        travel = sum(abs(b - a) for a, b in zip([300.0, *holds], holds))
        assert travel <= 360.0, (sweep, holds, travel)
        assert all(-180.0 <= a <= 300.0 for a in holds)


def test_nested_numbers_and_switches_take_their_type():
    """Lax parsing had read strings and booleans deeper in a request as numbers and switches: an evaluate
    run took a calibration whose sensitivity was ``true`` (a k of 1: level heading error 67.9 deg on a
    unit that had passed), ``"z_speeds_dps": ["10"]`` was 10, ``"apply": 1`` and ``"diagonal": "yes"`` were
    true, an analysis' ``"slot": "0"`` slot 0. Each is refused by its place, as the top-level numbers are."""
    from procedures.calibrate import CharacterizeParams, EvaluateParams, LevelParams
    from service.schemas import AnalysisIn

    for model, body, field, words in ((CharacterizeParams, {"z_speeds_dps": ["10"]}, "z_speeds_dps", "not the string '10'"),
                                      (CharacterizeParams, {"z_speeds_dps": [True]}, "z_speeds_dps", "not true or false"),
                                      (CharacterizeParams, {"diagonal": "yes"}, "diagonal", "boolean"),
                                      (LevelParams, {"apply": 1}, "apply", "boolean"),
                                      (LevelParams, {"apply": "true"}, "apply", "boolean"),
                                      (AnalysisIn, {"slot": "0"}, "slot", "not the string '0'")):
        with pytest.raises(ValidationError) as e:
            model.model_validate(body)
        assert e.value.errors()[0]["loc"][0] == field and words in str(e.value), (body, str(e.value))
    assert CharacterizeParams.model_validate({"z_speeds_dps": [10, 20.5]}).z_speeds_dps == [10.0, 20.5]
    # a whole number written large is judged by its range (it was "an input string ... exceeded maximum size")
    with pytest.raises(ValidationError, match="less than or equal to 10000"):
        CalibrateParams.model_validate({"samples": 1e30})
    assert LevelParams.model_validate({"apply": False}).apply is False

    from physics.calibration import Calibration
    from physics.fit import fit
    from physics.simulate import simulate_recording

    rec = simulate_recording(reference_unit(3.0, 4.0, serial="SN-TYPE"), calibration_poses(CalibrateParams(samples=5)),
                             World(), rng=np.random.default_rng(1))
    good = fit(rec, "joint", bootstrap=0).to_json()
    assert EvaluateParams.model_validate({"calibrations": {"0": good}}).calibrations[0]["serial"] == "SN-TYPE"
    for key, value, words in (("k", [good["magnetometer"]["k"][0], True, good["magnetometer"]["k"][2]], "magnetometer.k[1]"),
                              ("bias", ["1", 0.0, 0.0], "magnetometer.bias[0]"),
                              ("k", [1000.0, 1000.0], "expected 3 numbers")):
        bad = {**good, "magnetometer": {**good["magnetometer"], key: value}}
        with pytest.raises(ValidationError) as e:
            EvaluateParams.model_validate({"calibrations": {"0": bad}})
        assert e.value.errors()[0]["loc"][0] == "calibrations" and words in str(e.value), str(e.value)
        with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
            Calibration.from_json(bad)


def test_a_certificate_states_the_parameters_its_plan_read():
    """A plain run's certificate listed the adaptive targets and budget it never read (and a batch's unit
    its batch's own settings): only what the plan read is stated."""
    from procedures.calibrate import parameters_said

    plain = CalibrateParams().model_dump()
    said = parameters_said({**plain, "serial": "SN-1", "unmount": None})
    assert said["adaptive"] is False and said["samples"] == plain["samples"]
    assert not {"budget_s", "target_level_deg", "target_tilted_deg", "serial", "unmount"} & set(said), said
    adaptive = parameters_said(CalibrateParams(adaptive=True, budget_s=150).model_dump())
    assert adaptive["budget_s"] == 150 and "target_level_deg" in adaptive
