"""The blind proof (physics/prove.py): the generator sets effect sizes by non-centrality, nulls have
none, the non-centrality is the expected increase of the whitened residual, the scorer counts right,
and the whole proof runs end to end against the analyser."""

from __future__ import annotations

import json

import numpy as np
import pytest

from physics import prove
from physics.effects import CONCEAL, make_effect
from physics.prove import (EFFECTS, Case, Outcome, clopper_pearson_upper, field_base, format_report, logistic_fit,
                           make_case, nominal_misfit, proof_tasks, run_proof, score)
from physics.simulate import Noise, Pose, Scan, simulate_timeline
from physics.table import Motion

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

def test_run_proof_end_to_end() -> None:
    progress: list[tuple[int, int, str]] = []
    out = run_proof(1, 5, workers=2, progress=lambda d, t, k: progress.append((d, t, k)), plan=PLAN, nulls=2)
    json.dumps(out)
    assert len(out["cases"]) == len(EFFECTS) + 2
    assert progress[-1][:2] == (len(EFFECTS) + 2, len(EFFECTS) + 2)
    assert out["score"]["false_alarms"]["nulls"] == 2
    assert not out["score"]["errors"], out["score"]["errors"]
    for c in out["cases"]:
        assert c["verdict"] in ("consistent", "discrepancy")
        assert c["seconds"] is not None and c["heldout_ratio"] is not None
    assert "Detection rate" in prove.format_report(out["score"])


def test_cli_prove_passes_the_characterize_plan_and_prints_the_report(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    from typer.testing import CliRunner

    from procedures.calibrate import characterize_plan
    from service.cli import app

    seen: dict = {}

    def fake_run_proof(n, seed, workers=2, progress=None, *, plan, nulls=None, **kw):  # noqa: ANN001, ANN202
        seen.update(n=n, seed=seed, workers=workers, plan=plan, nulls=nulls)
        progress(1, 2, "null")
        progress(2, 2, "time_lag")
        cases = [fake_case("null"), fake_case("time_lag", 30.0)]
        sc = score(cases, [analysis("consistent"), analysis("discrepancy", finding("time_lag"))])
        return {"score": sc, "cases": [c.summary() for c in cases], "config": {"wall_s": 1.0}}

    monkeypatch.setattr(prove, "run_proof", fake_run_proof)
    out = tmp_path / "proof.json"
    res = CliRunner().invoke(app, ["prove", "--n", "3", "--seed", "7", "--nulls", "5", "--workers", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert (seen["n"], seen["seed"], seen["workers"], seen["nulls"]) == (3, 7, 1, 5)
    assert seen["plan"] == characterize_plan()
    assert "False alarms on nulls: 0/1" in res.output and "Confusion matrix" in res.output
    assert json.loads(out.read_text())["score"]["detection"]["time_lag"]["detected"] == 1
