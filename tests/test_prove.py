"""The blind proof (proof/): the generator sets effect sizes by non-centrality, nulls have none, the
non-centrality is the expected increase of the whitened residual, the out-of-catalogue concealments
add what their closed form says, the scorer counts right (catalogue and open-world cases), and the
whole proof runs end to end against the analyser."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import proof.runner
from physics.effects import CONCEAL, make_effect, stage_to_body
from physics.simulate import Noise, Pose, Scan, World, simulate_timeline
from physics.sensor import random_unit
from physics.table import Motion, platform_attitude
from proof.concealments import OPEN_KINDS, make_open
from proof.generator import (EFFECTS, INTERMITTENT_GAP, WINDOW_FRAC, Case, draw_windows, equivalent_frames, field_base,
                             make_case, make_open_case, nominal_misfit, ordinary_plan, recording_span, sweeping_plan)
from proof.runner import proof_tasks, run_proof
from proof.score import (Outcome, ceiling_power, clopper_pearson_upper, format_open_report, format_report, judge_open,
                         logistic_fit, merge_segments, score, score_open)
from scipy.stats import chi2, ncx2

RATE = Motion().sample_rate_hz


def small_plan(samples: int = 20) -> list[Pose | Scan]:
    """Holds at several azimuths and tilts approached from both sides, turns about z both ways at two
    speeds, a turn about y, and a closing hold repeating the first."""
    plan: list[Pose | Scan] = [Pose("first", 0, 0, 0, 4 * samples, approach_deg=10.0)]
    plan += [Pose(f"up {psi}", psi, 0, 0, samples, approach_deg=10.0) for psi in range(45, 360, 45)]
    plan += [Pose(f"down {psi}", psi, 0, 0, samples, approach_deg=-10.0) for psi in range(0, 360, 90)]
    for psi in (0, 120, 240):
        plan += [Pose(f"theta {th} at {psi}", psi, th, 0, samples, approach_deg=10.0) for th in (-60, -30, 30, 60)]
        plan += [Pose(f"phi {ph} at {psi}", psi, 0, ph, samples, approach_deg=-10.0) for ph in (-60, -30, 30, 60)]
    plan += [Scan("z up slow", "psi", -180, 180, 10.0), Scan("z down slow", "psi", 180, -180, 10.0),
             Scan("z up fast", "psi", -180, 180, 30.0), Scan("z down fast", "psi", 180, -180, 30.0),
             Scan("y up", "theta", -90, 90, 30.0, psi_t=30.0), Scan("x up", "phi", -90, 90, 30.0, psi_t=30.0)]
    plan += [Pose("closing", 0, 0, 0, 4 * samples, approach_deg=10.0)]
    return plan


PLAN = small_plan()


@pytest.mark.parametrize("effect", EFFECTS)
def test_effect_size_hits_the_target_non_centrality(effect: str) -> None:
    for seed, target in ((1, 4.0), (2, 40.0), (3, 250.0)):
        case = make_case(effect, np.random.default_rng(seed), PLAN, target)
        assert case.nc[effect] == pytest.approx(target, rel=0.2)
        assert case.effects == [effect] and case.params[effect] == make_effect_params(effect, case)
        # the recorded lambda is the misfit of the recording's own clean truth
        assert nominal_misfit(case.clean, case.clean.mag, case.noise, RATE, field_base(case.world)) == pytest.approx(
            case.nc[effect], rel=1e-6)


def make_effect_params(effect: str, case: Case) -> dict:
    """The case's params rebuilt through the catalogue's constructor (checks they are Effect.params())."""
    p = dict(case.params[effect])
    if effect == "nonlinearity":
        p.update(k=case.unit.mag.k, bias=case.unit.mag.bias)
    if effect == "mains_interference":
        p.pop("alias_hz")
        p["sample_rate_hz"] = RATE
    return make_effect(effect, p).params()


def test_pairs_get_each_effect_at_its_own_target() -> None:
    case = make_case("stage_hard_iron+time_lag", np.random.default_rng(4), PLAN, {"stage_hard_iron": 10.0, "time_lag": 100.0})
    assert case.nc["stage_hard_iron"] == pytest.approx(10.0, rel=0.2)
    assert case.nc["time_lag"] == pytest.approx(100.0, rel=0.2)
    assert set(case.params) == {"stage_hard_iron", "time_lag"}
    assert 60.0 < case.nc_total < 160.0  # nearly additive: the two signatures are nearly orthogonal


def test_nulls_have_no_effect_and_the_full_spread() -> None:
    phis, sigmas, warm = [], [], []
    for seed in range(12):
        case = make_case("null", np.random.default_rng(seed), PLAN)
        assert case.effects == [] and case.nc == {} and case.nc_total == 0.0 and case.params == {}
        # the clean truth is exactly nominal at the true angles: lambda 0
        assert nominal_misfit(case.clean, case.clean.mag, case.noise, RATE, field_base(case.world)) < 1e-6
        assert 0.0 <= case.nc_floor < 1.0  # encoder rounding: tiny
        phis.append(case.noise.phi)
        sigmas.append(case.noise.sigma.mean())
        warm.append(case.world.warmup_c)
        assert np.ptp(case.rec.temp_c) > 0 or case.world.warmup_c < 1e-3
        assert np.all(case.rec.mag == np.round(case.rec.mag))
    assert 0 < sum(p == 0 for p in phis) < 12 and all(p == 0 or 0.3 <= p <= 0.9 for p in phis)
    assert all(0.85 <= s <= 5 * 1.15 for s in sigmas) and all(0 <= w <= 4 for w in warm)


def test_non_centrality_is_the_expected_increase_of_the_whitened_residual() -> None:
    """lambda = E[RSS_w(noisy with effect)] - E[RSS_w(noisy without)] under the case's own noise."""
    case = make_case("field_drift", np.random.default_rng(7), PLAN, 50.0)
    noise = Noise(tuple(case.noise.sigma), 0.6, quantized=False)
    lam = nominal_misfit(case.clean, case.clean.mag, noise, RATE, field_base(case.world))
    _, clean0 = simulate_timeline(case.unit, PLAN, case.world, effects=(), noise=noise)
    rng = np.random.default_rng(0)
    diffs = []
    for _ in range(30):
        e = noise.sample(len(case.clean), rng)  # a fresh noise (continuous AR(1) over the kept rows is close enough)
        with_e = nominal_misfit(case.clean, case.clean.mag + e, noise, RATE, field_base(case.world))
        without = nominal_misfit(case.clean, clean0.mag + e, noise, RATE, field_base(case.world))
        diffs.append(with_e - without)
    assert np.mean(diffs) == pytest.approx(lam, abs=4 * 2 * np.sqrt(lam) / np.sqrt(30))


def test_non_centrality_scales_with_the_square_of_a_linear_effect() -> None:
    case = make_case("temperature_drift", np.random.default_rng(8), PLAN, 20.0)
    k = np.asarray(case.params["temperature_drift"]["bias_per_c"])
    _, c2 = simulate_timeline(case.unit, PLAN, case.world, effects=[make_effect("temperature_drift", {"bias_per_c": 2 * k})],
                              noise=case.noise)
    lam2 = nominal_misfit(c2, c2.mag, case.noise, RATE, field_base(case.world))
    assert lam2 == pytest.approx(4 * case.nc["temperature_drift"], rel=1e-3)


def test_proof_tasks_counts_and_spread() -> None:
    tasks = proof_tasks(6, 3, PLAN)
    kinds = [t.kind for t in tasks]
    assert all(kinds.count(e) == 6 for e in EFFECTS)
    assert kinds.count("null") == 20 and sum("+" in k for k in kinds) == 3
    assert proof_tasks(40, 3, PLAN, nulls=300).__len__() == 400 + 300 + 20
    pair_targets = [x for t in tasks if "+" in t.kind for x in t.target_nc.values()]
    assert all(25 <= x <= 300 for x in pair_targets)
    targets = sorted(t.target_nc["time_lag"] for t in tasks if t.kind == "time_lag")
    assert 3 <= targets[0] < 6 and 140 < targets[-1] <= 300  # stratified log-uniform
    assert len({t.seed for t in tasks}) == len(tasks)
    assert [t.seed for t in proof_tasks(6, 3, PLAN)] == [t.seed for t in tasks]  # reproducible
    for t in tasks:
        if "+" in t.kind:
            a, b = t.kind.split("+")
            assert a != b and a in CONCEAL and b in CONCEAL


# ---------------------------------------------------------------------------------------------------
# Scorer on hand-made analyses
# ---------------------------------------------------------------------------------------------------

def fake_case(kind: str, nc: float = 20.0, params: dict | None = None) -> Case:
    ids = [] if kind == "null" else kind.split("+")
    return Case(kind=kind, effects=ids, params=params or {e: {} for e in ids}, target_nc={e: nc for e in ids},
                nc={e: nc for e in ids}, nc_total=nc * len(ids), nc_floor=0.01, unit=None, world=None,  # type: ignore[arg-type]
                noise=Noise(2.0))


def finding(effect: str, confusable: list[str] | None = None, **params: object) -> dict:
    sig = {k: v[1] for k, v in params.items()}
    return {"effect": effect, "confusable_with": confusable or [], "parameters": {k: v[0] for k, v in params.items()},
            "sigma": sig}


def analysis(verdict: str, *findings: dict) -> dict:
    return {"verdict": verdict, "findings": list(findings)}


def test_scorer_counts_detection_naming_confusion_and_false_alarms() -> None:
    cases = [fake_case("time_lag", 4.0), fake_case("time_lag", 10.0), fake_case("time_lag", 50.0),
             fake_case("time_lag", 200.0), fake_case("hysteresis", 30.0), fake_case("hysteresis", 30.0),
             fake_case("stage_hard_iron", 8.0),
             fake_case("null"), fake_case("null"), fake_case("null"), fake_case("null"),
             fake_case("time_lag+hysteresis", 50.0), fake_case("field_drift+temperature_drift", 50.0)]
    analyses = [
        analysis("consistent"),
        analysis("discrepancy", finding("time_lag")),
        analysis("discrepancy", finding("hysteresis", ["time_lag"])),  # confusable, right set
        analysis("discrepancy", finding("time_lag")),
        analysis("discrepancy", finding("time_lag")),  # wrong name, identifiable
        analysis("discrepancy", finding("hysteresis")),
        analysis("discrepancy", finding("stage_soft_iron", ["table_axis_error"])),  # confusable, wrong set
        analysis("consistent"), analysis("consistent"), analysis("consistent"),
        analysis("discrepancy", finding("unexplained")),
        analysis("discrepancy", finding("time_lag"), finding("stage_hard_iron", ["hysteresis"])),
        analysis("discrepancy", finding("field_drift")),
    ]
    sc = score(cases, analyses)
    d = sc["detection"]["time_lag"]
    assert d["cases"] == 4 and d["detected"] == 3
    assert d["bins"] == [[0, 1], [1, 1], [0, 0], [1, 1], [1, 1]]  # 4, 10, 50, 200
    assert sc["detection"]["hysteresis"]["bins"][2] == [2, 2]
    fa = sc["false_alarms"]
    assert (fa["nulls"], fa["false_alarms"], fa["rate"]) == (4, 1, 0.25)
    assert fa["upper95"] == pytest.approx(clopper_pearson_upper(1, 4))
    assert sc["confusion"]["time_lag"] == {"(none)": 1, "time_lag": 2, "hysteresis": 1}
    assert sc["confusion"]["hysteresis"] == {"time_lag": 1, "hysteresis": 1}
    assert sc["confusion"]["null"] == {"(none)": 3, "unexplained": 1}
    nm = sc["naming"]
    # detected singles: time_lag x3 (2 right identifiable, 1 right confusable), hysteresis x2 (1 right, 1 wrong),
    # stage_hard_iron x1 (confusable, wrong)
    assert (nm["detected"], nm["right"]) == (6, 4)
    assert (nm["identifiable"], nm["right_first_rate"]) == (4, 0.75)
    assert (nm["confusable"], nm["right_set_rate"]) == (2, 0.5)
    assert sc["pairs"] == {"cases": 2, "both_named": 1, "detected": 2, "both_named_rate": 0.5, "nc_min": 50.0, "nc_max": 50.0}
    text = format_report(sc)
    assert "False alarms on nulls: 1/4" in text and "time_lag" in text and "Confusion matrix" in text
    json.dumps(sc)  # JSON-safe


def test_scorer_parameter_recovery_and_coverage() -> None:
    true_m = [0.01, 0.0, -0.02]
    cases = [fake_case("stage_hard_iron", 50.0, {"stage_hard_iron": {"stage": "outer", "m": true_m}}) for _ in range(3)]
    cases.append(fake_case("table_axis_error", 50.0, {"table_axis_error": {"nonperp_deg": [0.1, -0.1], "encoder_zero_deg": [0.2, 0.0]}}))
    analyses = [
        # within 1.96 sigma on all 3 components, rel err |(0.001, 0, 0.001)| / |m|
        Outcome(analysis("discrepancy", finding("stage_hard_iron", stage=("outer", None),
                                                m=([0.011, 0.0, -0.019], [0.001, 0.001, 0.001]))), 1.01, 2.0),
        # 1 of 3 components outside (0.005 off with sigma 0.001)
        Outcome(analysis("discrepancy", finding("stage_hard_iron", stage=("outer", None),
                                                m=([0.015, 0.0, -0.02], [0.001, 0.001, 0.001]))), 1.03, 4.0),
        # wrong stage: not compared
        Outcome(analysis("discrepancy", finding("stage_hard_iron", stage=("middle", None),
                                                m=([0.01, 0.0, -0.02], [0.001, 0.001, 0.001]))), 1.2, 3.0),
        Outcome(analysis("discrepancy", finding("table_axis_error", nonperp_deg=([0.1, -0.1], [0.01, 0.01]),
                                                encoder_zero_deg=([0.25, 0.0], [0.01, 0.01]))), None, 35.0),
    ]
    sc = score(cases, analyses)
    r = sc["recovery"]["stage_hard_iron"]
    assert r["cases"] == 2 and r["wrong_stage"] == 1 and r["components"] == 6
    assert r["coverage"] == pytest.approx(5 / 6)
    errs = sorted([np.linalg.norm([0.001, 0, 0.001]) / np.linalg.norm(true_m), 0.005 / np.linalg.norm(true_m)])
    assert r["rel_err_median"] == pytest.approx(np.median(errs))
    t = sc["recovery"]["table_axis_error"]
    assert t["cases"] == 1 and t["coverage"] == pytest.approx(3 / 4)
    assert t["rel_err_median"] == pytest.approx(0.05 / np.linalg.norm([0.1, -0.1, 0.2, 0.0]))
    h = sc["heldout"]["effects"]
    assert h["cases"] == 3 and h["median"] == pytest.approx(1.03)
    assert sc["seconds"] == {"analyses": 4, "median": 3.5, "max": 35.0}
    assert "MISSED" in format_report(sc)  # 35 s is over the 30 s target


def test_scorer_heldout_before_and_after() -> None:
    cases = [fake_case("time_lag", 30.0), fake_case("time_lag", 30.0), fake_case("null")]
    outs = [Outcome(analysis("discrepancy", finding("time_lag")), 1.01, 1.0, None, 1.05),
            Outcome(analysis("consistent"), 1.02, 1.0, None, 1.02),
            Outcome(analysis("consistent"), 1.0, 1.0, None, 1.0)]
    h = score(cases, outs)
    assert h["heldout"]["effects"]["median"] == pytest.approx(1.015)
    assert h["heldout"]["effects"]["before_median"] == pytest.approx(1.035)
    assert h["heldout"]["detected"]["cases"] == 1 and h["heldout"]["nulls"]["median"] == 1.0
    assert h["heldout_excess_removed"]["median"] == pytest.approx(1 - (1.01 ** 2 - 1) / (1.05 ** 2 - 1))
    assert h["detection"]["time_lag"]["heldout_median"] == pytest.approx(1.015)


def test_logistic_fit_and_clopper_pearson() -> None:
    nc = np.exp(np.linspace(np.log(3), np.log(300), 200))
    p_true = 1 / (1 + np.exp(-3 * np.log(nc / 12)))
    rng = np.random.default_rng(0)
    det = rng.random(200) < p_true
    fit = logistic_fit(nc, det)
    assert fit is not None
    assert fit["10"] == pytest.approx(1 / (1 + np.exp(-3 * np.log(10 / 12))), abs=0.12)
    assert fit["25"] == pytest.approx(1 / (1 + np.exp(-3 * np.log(25 / 12))), abs=0.08)
    all_detected = logistic_fit([3, 10, 30, 100, 300], [True] * 5)
    assert all_detected is not None and all_detected["10"] > 0.9
    assert clopper_pearson_upper(0, 300) == pytest.approx(1 - 0.05 ** (1 / 300))
    assert clopper_pearson_upper(0, 300) < 0.01 < clopper_pearson_upper(1, 300)


def test_scorer_reports_analyser_errors() -> None:
    cases = [fake_case("null"), fake_case("time_lag", 30.0)]
    sc = score(cases, [Outcome(None, None, 0.1, "ValueError: boom"), Outcome(None, None, 0.1, "RuntimeError: x")])
    assert sc["false_alarms"]["false_alarms"] == 0 and sc["detection"]["time_lag"]["detected"] == 0
    assert [e["error"] for e in sc["errors"]] == ["ValueError: boom", "RuntimeError: x"]
    assert "Analyses that raised: 2" in format_report(sc)


# ---------------------------------------------------------------------------------------------------
# End to end, against the analyser
# ---------------------------------------------------------------------------------------------------

#: The end-to-end tests check the outcome's structure, not the analyser's power: fewer simulated
#: nulls (the analyser's default is 200) keep the file within its time budget.
E2E_ANALYZE = {"null_sims": 20}

def test_run_proof_end_to_end() -> None:
    progress: list[tuple[int, int, str]] = []
    out = run_proof(1, 5, workers=2, progress=lambda d, t, k: progress.append((d, t, k)), plan=PLAN, nulls=2,
                    analyze_kwargs=E2E_ANALYZE)
    json.dumps(out)
    assert len(out["cases"]) == len(EFFECTS) + 2
    assert progress[-1][:2] == (len(EFFECTS) + 2, len(EFFECTS) + 2)
    assert out["score"]["false_alarms"]["nulls"] == 2
    assert not out["score"]["errors"], out["score"]["errors"]
    for c in out["cases"]:
        assert c["verdict"] in ("consistent", "discrepancy")
        assert c["seconds"] is not None and c["heldout_ratio"] is not None
    assert "Detection rate" in format_report(out["score"])


def test_cli_prove_passes_the_characterize_plan_and_prints_the_report(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    from typer.testing import CliRunner

    from procedures.calibrate import characterize_plan
    from service.cli import app

    seen: dict = {}

    def fake_run_proof(n, seed, workers=2, progress=None, *, plan, nulls=None, **kw):  # noqa: ANN001, ANN202
        seen.update(n=n, seed=seed, workers=workers, plan=plan, nulls=nulls, **kw)
        progress(1, 2, "null")
        progress(2, 2, "time_lag")
        cases = [fake_case("null"), fake_case("time_lag", 30.0)]
        results = [analysis("consistent"), analysis("discrepancy", finding("time_lag"))]
        if kw.get("open_n"):
            cases.append(open_case("segment_offset_lab", 40.0, [[50.0, 120.0]]))
            results.append(open_result(found("lab", segments=[[51.0, 119.0]])))
        sc = score(cases, results)
        return {"score": sc, "cases": [c.summary() for c in cases], "config": {"wall_s": 1.0}}

    monkeypatch.setattr(proof.runner, "run_proof", fake_run_proof)
    out = tmp_path / "proof.json"
    res = CliRunner().invoke(app, ["prove", "--n", "3", "--seed", "7", "--nulls", "5", "--workers", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert (seen["n"], seen["seed"], seen["workers"], seen["nulls"]) == (3, 7, 1, 5)
    assert seen["plan"] == characterize_plan()
    assert "False alarms on nulls: 0/1" in res.output and "Confusion matrix" in res.output
    assert json.loads(out.read_text())["score"]["detection"]["time_lag"]["detected"] == 1
    assert seen["open_n"] == 0 and seen["open_nulls"] == 0 and "Out-of-catalogue" not in res.output

    res = CliRunner().invoke(app, ["prove", "--n", "0", "--nulls", "0", "--open-n", "2", "--open-nulls", "4", "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert (seen["n"], seen["open_n"], seen["open_nulls"]) == (0, 2, 4)
    assert seen["open_plan"] == ordinary_plan()
    assert "Out-of-catalogue" in res.output and "segment_offset_lab" in res.output
    res = CliRunner().invoke(app, ["prove", "--open-n", "1", "--open-plan", "characterize", "--workers", "1"])
    assert res.exit_code == 0 and seen["open_plan"] == characterize_plan()
    res = CliRunner().invoke(app, ["prove", "--open-n", "1", "--open-plan", "sweeps", "--workers", "1"])
    assert res.exit_code == 0 and seen["open_plan"] == sweeping_plan()
    res = CliRunner().invoke(app, ["prove", "--n", "0", "--nulls", "0", "--open-large", "3", "--workers", "1"])
    assert res.exit_code == 0 and (seen["open_n"], seen["open_large"]) == (0, 3)
    assert CliRunner().invoke(app, ["prove", "--open-n", "1", "--open-plan", "nope"]).exit_code != 0


# ---------------------------------------------------------------------------------------------------
# Open world (issue 12): concealments against their closed form, sizing, scorer, end to end
# ---------------------------------------------------------------------------------------------------

OPEN_PLAN = ordinary_plan()


def _pair(effect: object, seed: int = 0, world: World | None = None):  # noqa: ANN202
    """(clean without, clean with) ``effect`` for one random unit on the ordinary plan, and the unit."""
    unit = random_unit(np.random.default_rng(seed))
    world = world or World(warmup_c=3.0, warmup_tau_s=80.0)
    _, c0 = simulate_timeline(unit, OPEN_PLAN, world, effects=(), noise=Noise(0.0, 0.0, False))
    _, c1 = simulate_timeline(unit, OPEN_PLAN, world, effects=[effect], noise=Noise(0.0, 0.0, False))
    return c0, c1, unit, world


def _inside(t: np.ndarray, segments: list[list[float]]) -> np.ndarray:
    return np.any([(t >= a) & (t < b) for a, b in segments], axis=0)


@pytest.mark.parametrize("kind,segments", [("segment_offset_sensor", [[40.0, 110.0]]),
                                           ("intermittent_interference", [[10.0, 30.0], [60.0, 75.0], [150.0, 190.0]])])
def test_sensor_offset_adds_exactly_d_inside_its_windows_and_nothing_outside(kind: str, segments: list) -> None:
    d = np.array([30.0, -12.0, 7.0])
    c0, c1, _, _ = _pair(make_open(kind, {"offset": d, "segments": segments}))
    inside = _inside(c0.t, segments)
    assert 0 < inside.sum() < len(c0) and len(c0.t[inside]) > 0
    np.testing.assert_allclose(c1.mag[inside] - c0.mag[inside], np.tile(d, (inside.sum(), 1)), atol=1e-9)
    np.testing.assert_array_equal(c1.mag[~inside], c0.mag[~inside])


@pytest.mark.parametrize("frame", ["lab", "outer", "middle"])
def test_lab_and_stage_offsets_turn_with_the_table(frame: str) -> None:
    d = np.array([0.02, -0.01, 0.03])
    segments = [[0.0, 120.0]]
    c0, c1, unit, world = _pair(make_open(f"segment_offset_{frame}", {"offset": d, "segments": segments}), 1)
    inside = _inside(c0.t, segments)
    if frame == "lab":  # fixed in the lab: seen in body axes through the attitude, C_LP^T d
        C = platform_attitude(c0.psi_t, c0.theta_t, c0.phi_t, world.geometry)
        h = np.einsum("nji,j->ni", C, d)
    else:  # fixed in a stage: Q(theta, phi) d
        h = np.array([stage_to_body(frame, th, ph) @ d for th, ph in zip(c0.theta_t, c0.phi_t)])
    expected = h @ unit.mag.M.T
    np.testing.assert_allclose(c1.mag[inside] - c0.mag[inside], expected[inside], atol=1e-9)
    np.testing.assert_array_equal(c1.mag[~inside], c0.mag[~inside])
    # it turns: the added counts differ from pose to pose (unlike the sensor-frame offset)
    assert np.ptp(expected[inside], axis=0).max() > 0.1 * np.abs(unit.mag.M @ d).max()


def test_gain_vs_temp_scales_the_linear_output_with_temperature() -> None:
    g = np.array([2e-3, -1e-3, 5e-4])
    unit = random_unit(np.random.default_rng(2))
    effect = make_open("gain_vs_temp", {"gain_per_c": g, "bias": unit.mag.bias, "t_ref_c": 23.0})
    c0, c1, unit, world = _pair(effect, 2)
    assert np.ptp(c0.temp_c) > 2.0
    expected = g * (c0.temp_c - 23.0)[:, None] * (c0.mag - unit.mag.bias)
    np.testing.assert_allclose(c1.mag - c0.mag, expected, rtol=1e-9, atol=1e-9)
    # a gain, not a bias: twice the field, twice the added counts (at the same temperature)
    early = c0.t < 5.0
    assert np.abs(expected[early]).max() < 0.5 * np.abs(expected[c0.t > 150.0]).max()


def test_misalignment_drift_is_a_rotation_growing_linearly_in_time() -> None:
    w = np.array([1e-5, -2e-5, 3e-5])
    unit = random_unit(np.random.default_rng(3))
    effect = make_open("misalignment_drift", {"rate_rad_per_s": w, "bias": unit.mag.bias, "t_mid": 100.0})
    c0, c1, unit, _ = _pair(effect, 3)
    lin = c0.mag - unit.mag.bias
    expected = -np.cross(w * (c0.t - 100.0)[:, None], lin)  # the axes turn by w: the field they see by -w
    np.testing.assert_allclose(c1.mag - c0.mag, expected, rtol=1e-9, atol=1e-9)
    # a rotation: the length of the linear output is kept to first order
    assert np.abs(np.einsum("ni,ni->n", expected, lin)).max() < 1e-9 * np.abs(lin).max() ** 2


def test_windows_are_long_enough_may_touch_either_end_and_keep_apart() -> None:
    rng = np.random.default_rng(0)
    span = (0.3, 199.9)
    dur = span[1] - span[0]
    starts = ends = 0
    for _ in range(400):
        (w,) = draw_windows(rng, span, 1, WINDOW_FRAC)
        assert WINDOW_FRAC[0] * dur - 1e-9 <= w[1] - w[0] <= WINDOW_FRAC[1] * dur + 1e-9
        assert span[0] <= w[0] < w[1] <= span[1] and not (w[0] == span[0] and w[1] == span[1])
        starts += w[0] == span[0]
        ends += w[1] == span[1]
    assert 20 < starts < 120 and 20 < ends < 120
    for k in (2, 3):
        ws = np.array(draw_windows(rng, span, k, (0.08, 0.15), INTERMITTENT_GAP))
        assert len(ws) == k and np.all(ws[1:, 0] - ws[:-1, 1] >= INTERMITTENT_GAP * dur - 1e-9)


@pytest.mark.parametrize("kind", OPEN_KINDS)
def test_open_case_is_sized_to_its_non_centrality_and_records_its_truth(kind: str) -> None:
    target = {0: 8.0, 1: 40.0, 2: 200.0}[OPEN_KINDS.index(kind) % 3]
    case = make_open_case(kind, np.random.default_rng(OPEN_KINDS.index(kind)), OPEN_PLAN, target)
    assert case.nc[kind] == pytest.approx(target, rel=0.1) and case.effects == [kind]
    assert nominal_misfit(case.clean, case.clean.mag, case.noise, RATE, field_base(case.world)) == pytest.approx(
        case.nc[kind], rel=1e-6)
    assert case.generator == "open" and case.span_s == recording_span(OPEN_PLAN)
    assert case.span_s[0] == pytest.approx(case.rec.t[0]) and case.span_s[1] > case.rec.t[-1]
    np.testing.assert_allclose(case.noise.sigma, 3.0)
    m = case.model
    assert m["frame"] in ("sensor", "lab", "outer", "middle") and m["form"] in ("offset", "gain", "rotation")
    rebuilt = dict(case.params[kind], **({"bias": case.unit.mag.bias} if kind in ("gain_vs_temp", "misalignment_drift") else {}))
    assert make_open(kind, rebuilt).model() == m  # the truth is what the concealment says of itself
    dur = case.span_s[1] - case.span_s[0]
    assert m["frame"] in case.frames
    if kind.startswith("segment_offset"):
        assert m["frame"] == kind.rsplit("_", 1)[1] and m["against"] is None and len(m["segments"]) == 1
        assert m["segments"][0][1] - m["segments"][0][0] >= 0.15 * dur - 1e-9
        if m["frame"] != "sensor":  # the table turns the frame against the unit within the window
            assert "sensor" not in case.frames
            inside = _inside(case.rec.t, m["segments"])
            assert equivalent_frames(m["frame"], np.column_stack([case.rec.psi_t, case.rec.theta_t, case.rec.phi_t])[inside]) \
                == case.frames
    elif kind == "intermittent_interference":
        assert m["frame"] == "sensor" and 2 <= len(m["segments"]) <= 3
    else:
        assert m["segments"] == [] and m["against"] == {"gain_vs_temp": "temp_c", "misalignment_drift": "time"}[kind]
    if kind == "gain_vs_temp":  # it needs a temperature that moves within the run
        assert case.world.warmup_c >= 2.0 and 0.3 * dur <= case.world.warmup_tau_s <= 1.0 * case.span_s[1]
        assert np.ptp(case.rec.temp_c) > 0.5


def test_equivalent_frames_are_those_joined_by_gimbal_angles_that_hold_still() -> None:
    level_turn = np.array([[a, 0.0, 0.0] for a in range(0, 360, 45)])
    assert equivalent_frames("lab", level_turn) == ["lab"]
    assert equivalent_frames("outer", level_turn) == ["outer", "middle", "sensor"]  # theta, phi still
    assert equivalent_frames("sensor", level_turn) == ["outer", "middle", "sensor"]
    sweep_x = np.array([[315.0, 0.0, a] for a in range(0, 360, 60)])
    assert equivalent_frames("middle", sweep_x) == ["lab", "outer", "middle"]  # psi, theta still
    assert equivalent_frames("sensor", sweep_x) == ["sensor"]
    everything = np.array([[0.0, 0.0, 0.0], [90.0, 30.0, -30.0]])
    assert [equivalent_frames(f, everything) for f in ("lab", "outer", "middle", "sensor")] == [
        ["lab"], ["outer"], ["middle"], ["sensor"]]


def test_open_tasks_follow_the_catalogue_tasks_unchanged() -> None:
    base = proof_tasks(2, 3, PLAN)
    tasks = proof_tasks(2, 3, PLAN, open_n=4, open_nulls=3)
    assert [(t.kind, t.seed, t.target_nc, t.plan) for t in tasks[:len(base)]] == [
        (t.kind, t.seed, t.target_nc, t.plan) for t in base]
    extra = tasks[len(base):]
    assert all(t.generator == "open" and t.plan == tuple(OPEN_PLAN) for t in extra)
    assert [t.kind for t in extra] == [k for k in OPEN_KINDS for _ in range(4)] + ["null"] * 3
    targets = sorted(t.target_nc["gain_vs_temp"] for t in extra if t.kind == "gain_vs_temp")
    assert 3 <= targets[0] < 10 and 90 < targets[-1] <= 300  # stratified log-uniform, 4 strata
    assert len({t.seed for t in tasks}) == len(tasks)
    # the large departures come last, from their own stream: the cases before them are unchanged
    with_large = proof_tasks(2, 3, PLAN, open_n=4, open_nulls=3, open_large=2)
    assert [(t.kind, t.seed, t.target_nc) for t in with_large[:len(tasks)]] == [(t.kind, t.seed, t.target_nc) for t in tasks]
    large = with_large[len(tasks):]
    assert [t.kind for t in large] == [k for k in OPEN_KINDS for _ in range(2)]
    assert all(300 <= t.target_nc[t.kind] <= 1e6 and t.generator == "open" for t in large)


def test_generator_never_imports_the_analyser() -> None:
    code = ("import sys, numpy as np; import proof.generator, proof.concealments, proof.score; "
            "from proof.generator import make_open_case; make_open_case('segment_offset_lab', np.random.default_rng(0)); "
            "assert not [m for m in sys.modules if m.startswith('physics.discrepancy')], 'analyser imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


# --- the open-world scorer on hand-made results (independent of the analyser) ---

def open_case(kind: str, nc: float, segments: list | None = None, span: tuple[float, float] = (0.0, 200.0),
              frames: list | None = None) -> Case:
    truth = make_open(kind, {"offset": [1.0, 0.0, 0.0], "segments": segments} if segments else
                      {"gain_per_c": [1e-4] * 3, "bias": [0.0] * 3, "t_ref_c": 23.0} if kind == "gain_vs_temp" else
                      {"rate_rad_per_s": [1e-5] * 3, "bias": [0.0] * 3, "t_mid": 100.0}).model()
    return Case(kind=kind, effects=[kind], params={kind: {}}, target_nc={kind: nc}, nc={kind: nc}, nc_total=nc,
                nc_floor=0.0, unit=None, world=None, noise=Noise(3.0), generator="open", model=truth,  # type: ignore[arg-type]
                span_s=span, frames=frames)


def found(frame: str, form: str = "offset", against: str | None = None, segments: list | None = None,
          effect: str = "discovered") -> dict:
    return {"effect": effect, "model": {"frame": frame, "form": form, "against": against, "segments": segments or []},
            "plausible": True}


def open_result(*findings: dict, after: tuple = (3.3, 3.0, 2.9), floor: tuple = (3.0, 3.0, 3.0),
                heading: tuple | None = (0.8, 0.3)) -> dict:
    """A result; ``heading`` is (max before, max after) or (max before, max after, rms before, rms after)."""
    he = None if heading is None else {"before": heading[0], "after": heading[1]}
    if heading is not None and len(heading) == 4:
        he.update(rms_before=heading[2], rms_after=heading[3])
    return {"verdict": "discrepancy" if findings else "consistent", "findings": list(findings),
            "noise_floor_lsb": list(floor), "residual_rms_before_lsb": [9.0, 9.0, 9.0], "residual_rms_after_lsb": list(after),
            "heldout": {"rms_before_lsb": [9.0] * 3, "rms_after_lsb": [3.1] * 3, "improvement_pct": 60.0},
            "heading_error_deg": he}


WIN = [[50.0, 120.0]]  # edges within 5 % of 200 s: +-10 s


@pytest.mark.parametrize("kind,truth,result,failed", [
    ("segment_offset_sensor", WIN, open_result(found("sensor", segments=[[52.0, 118.0]])), []),
    # the unit's own frame under the analyser's other name; a window split at a move is one window
    ("segment_offset_sensor", WIN, open_result(found("platform", segments=[[51.0, 80.0], [83.0, 125.0]])), []),
    ("segment_offset_sensor", WIN, open_result(found("lab", segments=[[50.0, 120.0]])), ["frame", "where"]),
    ("segment_offset_lab", WIN, open_result(found("lab", segments=[[50.0, 131.0]])), ["where"]),  # 11 s > 10 s
    ("segment_offset_lab", WIN, open_result(found("lab", segments=[[38.0, 120.0]])), ["where"]),
    ("segment_offset_outer", WIN, open_result(found("outer", segments=WIN), after=(4.0, 3.0, 3.0)), ["residual"]),
    ("segment_offset_middle", WIN, open_result(found("middle", segments=WIN), heading=(0.5, 0.6)), ["heading"]),
    # the RMS over the level holds decides when the result gives it (one hold's noise moves the maximum)
    ("segment_offset_middle", WIN, open_result(found("middle", segments=WIN), heading=(0.5, 0.6, 0.3, 0.2)), []),
    ("segment_offset_middle", WIN, open_result(found("middle", segments=WIN), heading=(0.5, 0.4, 0.3, 0.31)), ["heading"]),
    ("segment_offset_middle", WIN, open_result(found("middle", segments=WIN), heading=None), []),  # heading unknown
    ("segment_offset_middle", WIN, open_result(found("middle", segments=WIN), heading=(0.5, None)), []),
    ("segment_offset_sensor", WIN, open_result(), ["frame", "where"]),  # nothing found, nothing fitted
    # the unit's bias takes a constant: offset outside the window is the same data as offset inside it
    ("segment_offset_sensor", [[84.6, 200.0]], open_result(found("sensor", segments=[[0.0, 85.0]])), []),
    ("segment_offset_lab", WIN, open_result(found("lab", segments=[[0.0, 52.0], [118.0, 200.0]])), []),
    # a stage's constant is not absorbed: its complement is a different departure
    ("segment_offset_outer", [[84.6, 200.0]], open_result(found("outer", segments=[[0.0, 85.0]])), ["where"]),
    ("intermittent_interference", [[20.0, 40.0], [100.0, 130.0]],
     open_result(found("sensor", segments=[[21.0, 41.0]]), found("sensor", segments=[[99.0, 131.0]])), []),
    ("intermittent_interference", [[20.0, 40.0], [100.0, 130.0]],
     open_result(found("sensor", segments=[[21.0, 41.0]])), ["where"]),  # one window of two
    ("gain_vs_temp", None, open_result(found("sensor", "gain", "temp_c")), []),
    ("gain_vs_temp", None, open_result(found("sensor", "offset", "temp_c", effect="temperature_drift")), []),  # form not required
    ("gain_vs_temp", None, open_result(found("sensor", "gain", "time")), ["where"]),
    ("misalignment_drift", None, open_result(found("platform", "rotation", "time")), []),
    ("misalignment_drift", None, open_result(found("lab", "offset", "time", effect="field_drift")), ["frame", "where"]),
    # a parameter shift (the nominal model's own parameter out of range) is not a model of the departure
    ("misalignment_drift", None, open_result(found("platform", "linear", None, effect="parameter_shift")),
     ["frame", "where"]),
])
def test_open_scorer_judges_frame_windows_input_residual_and_heading(kind: str, truth: list | None, result: dict,
                                                                     failed: list) -> None:
    j = judge_open(open_case(kind, 40.0, truth), result)
    assert j["failed"] == failed and j["success"] == (not failed)


def test_open_scorer_accepts_a_frame_the_recording_cannot_tell_from_the_true_one() -> None:
    case = open_case("segment_offset_outer", 40.0, WIN, frames=["outer", "middle"])  # theta still in the window
    assert judge_open(case, open_result(found("middle", segments=WIN)))["success"]
    assert judge_open(case, open_result(found("outer", segments=WIN)))["success"]
    assert judge_open(case, open_result(found("sensor", segments=WIN)))["failed"] == ["frame", "where"]
    assert judge_open(case, open_result(found("platform", segments=WIN)))["failed"] == ["frame", "where"]


def test_open_scorer_reports_per_kind_and_the_target() -> None:
    ok = open_result(found("lab", segments=WIN))
    bad = open_result(found("sensor", segments=WIN))
    cases = [open_case("segment_offset_lab", nc, WIN) for nc in (4.0, 10.0, 30.0, 60.0, 200.0)]
    cases += [open_case("gain_vs_temp", 50.0), open_case("gain_vs_temp", 5.0)]
    results = [bad, bad, ok, ok, bad, open_result(found("sensor", "gain", "temp_c"), heading=(0.4, 0.5)),
               Outcome(None, None, 0.2, "ValueError: boom")]
    so = score_open(cases, [Outcome(r, None, 2.0) if isinstance(r, dict) else r for r in results])
    lab = so["by_kind"]["segment_offset_lab"]
    assert lab["bins"] == [[0, 1], [0, 1], [1, 1], [1, 1], [0, 1]] and lab["success"] == 2
    assert lab["frame_right"] == pytest.approx(0.4) and lab["residual_ratio_median"] == pytest.approx(1.1)
    assert (lab["heading_before_median"], lab["heading_after_median"], lab["heading_better"]) == (0.8, 0.3, 1.0)
    gain = so["by_kind"]["gain_vs_temp"]
    assert gain["cases"] == 2 and gain["success"] == 0 and gain["where_right"] == 0.5
    at = so["at_target"]  # lambda >= 25: 30, 60, 200 (lab), 50 (gain)
    assert (at["cases"], at["success"], at["rate"]) == (4, 2, 0.5)
    assert at["failed"] == {"frame": 1, "where": 1, "residual": 0, "heading": 1}
    assert so["overall"]["cases"] == 7 and [e["error"] for e in so["errors"]] == ["ValueError: boom"]
    assert so["seconds"]["median"] == 2.0
    assert merge_segments([[5, 8], [0, 2], [2.5, 4]], 0.5) == [[0.0, 4.0], [5.0, 8.0]]

    # mixed with catalogue cases: the catalogue figures do not see them, the report prints both
    mixed = [fake_case("time_lag", 30.0), fake_case("null"), *cases]
    sc = score(mixed, [analysis("discrepancy", finding("time_lag")), analysis("consistent"),
                       *[Outcome(r, None, 2.0) if isinstance(r, dict) else r for r in results]])
    assert sc["detection"]["time_lag"]["cases"] == 1 and sc["false_alarms"]["nulls"] == 1
    assert sc["seconds"]["analyses"] == 0 and sc["open"]["at_target"]["success"] == 2
    assert len(sc["errors"]) == 1
    text = format_report(sc)
    assert "Detection rate" in text and "Out-of-catalogue" in text and "success at lambda >= 25: 2/4 = 50%" in text
    assert "MISSED" in text
    json.dumps(sc)
    # open-world cases alone: no empty catalogue tables
    only = format_report(score(cases, [Outcome(r, None, 2.0) if isinstance(r, dict) else r for r in results]))
    assert "Detection rate" not in only and "Out-of-catalogue" in only and "Analyses that raised: 1" in only


def test_open_scorer_keeps_the_large_departures_apart() -> None:
    """Large departures (a target above 300) are scored in their own column and line: they never lift the
    figure at lambda >= 25, and their failures are counted by reason."""
    ok = open_result(found("lab", segments=WIN))
    cases = [open_case("segment_offset_lab", 30.0, WIN), open_case("segment_offset_lab", 3e4, WIN),
             open_case("segment_offset_lab", 2e5, WIN), open_case("segment_offset_sensor", 5e3, WIN)]
    results = [open_result(found("sensor", segments=WIN)), ok, open_result(found("lab", segments=WIN), after=(4.0, 3.0, 3.0)),
               open_result(found("sensor", segments=WIN))]
    so = score_open(cases, [Outcome(r, None, s) for r, s in zip(results, (2.0, 3.0, 40.0, 4.0))])
    assert (so["at_target"]["cases"], so["at_target"]["success"]) == (1, 0)
    assert so["large"] == {"cases": 3, "success": 2, "rate": pytest.approx(2 / 3),
                           "failed": {"frame": 0, "where": 0, "residual": 1, "heading": 0}}
    assert so["by_kind"]["segment_offset_lab"]["large"] == [1, 2] and so["by_kind"]["segment_offset_lab"]["cases"] == 1
    assert so["by_kind"]["segment_offset_sensor"]["large"] == [1, 1] and so["by_kind"]["segment_offset_sensor"]["cases"] == 0
    assert so["seconds"]["max"] == 40.0  # every analysis counts against the time target
    text = format_open_report(so)
    assert "large departures (lambda 300-1e+06" in text and "2/3 = 67%" in text and "residual 1" in text
    assert "success at lambda >= 25: 0/1" in text
    # a proof of large departures alone still prints the open-world table
    only = format_report(score(cases[1:], [Outcome(r, None, 2.0) for r in results[1:]]))
    assert "large departures" in only and "2/3 = 67%" in only


def test_open_scorer_states_the_ceiling_no_analysis_can_beat() -> None:
    """Where a perfect model of the effect (the same recording without it) leaves the level heading error no
    lower than the nominal fit's, no analysis can pass the heading criterion: the judgement says so, and the
    score bounds the success rate by those cases and by a test told the frame, form and window."""
    case = open_case("segment_offset_lab", 40.0, WIN)
    good = open_result(found("lab", segments=WIN), heading=(0.5, 0.4, 0.30, 0.31))  # heading "not better"
    assert judge_open(case, good, 0.32)["heading_reachable"] is False
    assert judge_open(case, good, 0.29)["heading_reachable"] is True
    assert judge_open(case, good)["heading_reachable"] is None  # not measured
    assert judge_open(case, open_result(found("lab", segments=WIN), heading=None), 0.2)["heading_reachable"] is None

    # a test told where to look: its power grows with lambda, ~94 % at 25 for 3 parameters at alpha 0.01
    assert ceiling_power(25.0) == pytest.approx(float(ncx2.sf(chi2.isf(0.01, 3), 3, 25.0)))
    assert 0.9 < ceiling_power(25.0) < ceiling_power(40.0) < 1.0 and ceiling_power(3.0) < 0.5

    cases = [open_case("segment_offset_lab", nc, WIN) for nc in (30.0, 60.0, 200.0, 5.0)]
    outs = [Outcome(good, None, 1.0, heading_free=h) for h in (0.32, 0.25, None, 0.1)]
    at = score_open(cases, outs)["at_target"]  # lambda >= 25: the first three
    assert at["ceiling"]["heading_known"] == 2 and at["ceiling"]["heading_reachable"] == 1
    assert at["ceiling"]["rate"] == pytest.approx((ceiling_power(60.0) + ceiling_power(200.0)) / 3)
    text = format_open_report(score_open(cases, outs))
    assert "lower than the nominal fit's in 1/2 cases" in text and "at most 67%" in text


def test_open_world_end_to_end_through_the_analyser() -> None:
    """Three open-world cases through the real analyser: every outcome has the structure the scorer
    reads (not success: the analyser's discovery is being built alongside)."""
    kinds = ("segment_offset_sensor", "segment_offset_lab", "gain_vs_temp")
    out = run_proof(0, 11, workers=2, plan=PLAN, nulls=1, pairs=0, open_n=1, open_kinds=kinds, analyze_kwargs=E2E_ANALYZE)
    json.dumps(out)
    assert [c["kind"] for c in out["cases"]] == ["null", *kinds]
    assert not out["score"]["errors"], out["score"]["errors"]
    for c in out["cases"][1:]:
        assert c["generator"] == "open" and c["model"]["frame"] in ("sensor", "lab") and c["seconds"] is not None
        assert c["verdict"] in ("consistent", "discrepancy") and 3.0 * 0.9 <= c["nc"][c["kind"]] <= 300 * 1.1
        j = c["judgement"]
        assert set(j) >= {"success", "failed", "frame_right", "where_right", "residual_ratio"}
        assert j["residual_ratio"] is not None and j["residual_ratio"] > 0.5
        # the perfect model's level heading error: the nominal fit of the same recording without the effect
        assert j["heading_free"] is not None and 0.0 < j["heading_free"] < 1.0
        assert j["heading_reachable"] == (j["heading_free"] < j["heading_before"])
        assert 0.0 < c["heading_error_deg"]["noise_rms"] < 1.0  # the analysis says its heading figures' noise
    so = out["score"]["open"]
    assert set(so["by_kind"]) == set(kinds) and so["overall"]["cases"] == 3
    assert out["config"]["open_n"] == 1 and out["config"]["open_plan_items"] == len(OPEN_PLAN)
    assert "Out-of-catalogue" in format_report(out["score"])


def test_a_lab_window_on_a_plan_of_continuous_sweeps_is_found_to_its_edges() -> None:
    """The turns and sweeps recorded on the move (no hold in them: the analyser finds its holds itself):
    a steel object set down near the table for a while is named in the lab frame, its window's edges
    within the proof's 5 %, the residual at the floor."""
    from physics.discrepancy import analyze

    plan = sweeping_plan()
    assert sum(isinstance(p, Scan) for p in plan) == 4 and recording_span(plan)[1] > 250.0
    case = make_open_case("segment_offset_lab", np.random.default_rng(5), plan, 3000.0)
    r = analyze(case.rec.select(slice(None)), seed=5).result
    j = judge_open(case, r)
    assert j["success"], (j, case.model, [f.get("model") for f in r["findings"]])


# ---------------------------------------------------------------------------------------------------
# The proof without table angles (hand-held recordings): scorer, CLI end to end
# ---------------------------------------------------------------------------------------------------

def handheld_record(kind: str | None, lam: float, success: bool = False, frame: bool = False, windows: bool = False,
                    failed: list | None = None, alarm: bool = False, error: str | None = None) -> dict:
    rec = {"seed": 1, "kind": kind, "lambda": lam, "seconds": 2.0, "error": error, "alarm": alarm}
    if kind is not None:
        rec.update(success=success, frame=frame, windows=windows, failed=failed or [])
    return rec


def test_handheld_scorer_counts_success_by_bin_failures_and_false_alarms() -> None:
    from proof.score import format_handheld_report, score_handheld

    cases = [handheld_record("segment_offset_sensor", 4.0, failed=["frame", "where"]),
             handheld_record("segment_offset_sensor", 50.0, True, True, True),
             handheld_record("segment_offset_sensor", 150.0, frame=True, failed=["where"]),
             handheld_record("gain_vs_temp", 30.0, True, True, True),
             handheld_record("gain_vs_temp", 20.0, frame=True, windows=True, failed=["residual"]),
             handheld_record(None, 0.0), handheld_record(None, 0.0, alarm=True), handheld_record(None, 0.0),
             handheld_record(None, 0.0, error="ValueError: x")]
    sc = score_handheld(cases)
    s = sc["by_kind"]["segment_offset_sensor"]
    assert s["cases"] == 3 and s["bins"] == [[0, 1], [0, 0], [0, 0], [1, 1], [0, 1]]
    assert s["frame_right"] == pytest.approx(2 / 3) and s["where_right"] == pytest.approx(1 / 3)
    assert sc["by_kind"]["gain_vs_temp"]["bins"] == [[0, 0], [0, 0], [1, 2], [0, 0], [0, 0]]
    # lambda >= 25: the sensor cases at 50 and 150 and the gain case at 30
    at = sc["at_target"]
    assert (at["cases"], at["success"]) == (3, 2) and at["failed"]["where"] == 1 and at["failed"]["frame"] == 0
    fa = sc["false_alarms"]
    assert (fa["nulls"], fa["alarms"]) == (3, 1) and fa["upper95"] == pytest.approx(clopper_pearson_upper(1, 3))
    assert sc["errors"] == [{"kind": None, "seed": 1, "error": "ValueError: x"}]
    text = format_handheld_report(sc)
    assert "success at lambda >= 25: 2/3 = 67% (target >= 90%) MISSED" in text
    assert "false alarms on hand-held nulls: 1/3" in text and "null (seed 1): ValueError: x" in text


def test_cli_prove_runs_the_handheld_proof_alone_end_to_end(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    from typer.testing import CliRunner

    from proof.handheld import HANDHELD_KINDS
    from service.cli import app

    def no_table(*a, **kw):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("no table recording was asked for")

    monkeypatch.setattr(proof.runner, "run_proof", no_table)
    out = tmp_path / "proof.json"
    res = CliRunner().invoke(app, ["prove", "--n", "0", "--nulls", "0", "--handheld-n", "1", "--handheld-nulls", "1",
                                   "--seed", "3", "--workers", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert "Hand-held cases without table angles" in res.output
    assert f"{len(HANDHELD_KINDS) + 1} hand-held recordings" in res.output
    hh = json.loads(out.read_text())["handheld"]
    cases = hh["cases"]
    assert [c["kind"] for c in cases] == [*HANDHELD_KINDS, None]
    for c in cases:
        assert c["error"] is None and 0 < c["seconds"] < 60
        if c["kind"] is not None:  # judged by the open-world rule: success exactly when nothing failed
            assert c["success"] == (not c["failed"]) and c["truth"]["kind"] == c["kind"]
            assert c["success"] <= (c["frame"] and c["windows"])
    assert sum(d["cases"] for d in hh["score"]["by_kind"].values()) == len(HANDHELD_KINDS)
    assert hh["score"]["false_alarms"]["nulls"] == 1
    # the strongest case in this draw is found in its frame and window
    top = max(cases[:-1], key=lambda c: c["lambda"])
    assert top["lambda"] > 25 and top["frame"] and top["windows"], top
