"""The discrepancy analysis in the service: ``compasscal analyze``, the HTML report, and the API
(``POST /runs/{id}/analysis``, ``GET /analyses/{id}``) on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import re
import sys
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from physics.fit import fit
from physics.recording import Recording, format_recording, parse_recording
from physics.sensor import reference_unit
from physics.simulate import World, simulate_recording
from procedures.calibrate import CalibrateParams, calibration_poses
from service.cli import app
from service.db import AuditLog, Run, Sample
from service import report
from service.report import analysis_html, parameter_cells, parameter_rows
from service.store import store_calibration

runner = CliRunner()


def said(output: str) -> str:
    """CLI output with rich's line wrapping undone."""
    return " ".join(output.split())


def simulated(serial: str = "SN-AN", seed: int = 1, samples: int = 20) -> Recording:
    return simulate_recording(reference_unit(3.0, 4.0, serial=serial), calibration_poses(CalibrateParams(samples=samples)),
                              World(), rng=np.random.default_rng(seed))


def with_magnet(rec: Recording, stage: str = "middle", m: tuple[float, float, float] = (0.004, -0.003, 0.002),
                seed: int = 2) -> Recording:
    """The same run by a unit (the reference unit, 3 LSB noise) with a magnet fixed on a table stage,
    concealed by the catalogue's forward form (physics.effects), not by anything of the analyser."""
    from physics.effects import make_effect

    unit, world = reference_unit(3.0, 4.0, serial=rec.serial or ""), World()
    effect = make_effect("stage_hard_iron", {"stage": stage, "m": list(m)})
    angles = np.column_stack([rec.psi_t, rec.theta_t, rec.phi_t])
    h_b, _ = world.body_vectors(rec.psi_t, rec.theta_t, rec.phi_t)
    h = np.array([effect.body_field(t, 0, a, None, hb) for t, a, hb in zip(rec.t, angles, h_b)])
    return Recording.from_arrays(t=rec.t, step=rec.step, psi_t=rec.psi_t, theta_t=rec.theta_t, phi_t=rec.phi_t,
                                 mag=unit.mag.measure(h, np.random.default_rng(seed)), acc=rec.acc, temp_c=rec.temp_c,
                                 meta=dict(rec.meta))


def named(result: dict[str, Any]) -> set[str]:
    """Every effect an analysis names: its findings and what each is confusable with (for a
    recording that cannot separate two effects, the contract is to report both)."""
    return {f["effect"] for f in result["findings"]} | {c for f in result["findings"] for c in f["confusable_with"]}


# --------------------------------------------------------------------------------- a fake analyser

@dataclass
class FakeAnalysis:
    """physics.discrepancy.Analysis's shape, with fixed contents the tests can look for."""

    result: dict[str, Any]
    series: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return self.result


def fake_result(rec: Recording, alpha: float = 0.01) -> dict[str, Any]:
    """A result with every key of the contract (spec: the analyser contract)."""
    steps = list(dict.fromkeys(rec.step.tolist()))
    return {
        "verdict": "discrepancy", "model": "table" if rec.has_angles else "attitude_free", "samples": len(rec),
        "duration_s": float(rec.t[-1] - rec.t[0]), "alpha": alpha,
        "noise_floor_lsb": [3.0, 3.1, 2.9], "noise_ar1": [0.01, 0.02, -0.01],
        "residual_rms_before_lsb": [6.0, 6.1, 5.0], "residual_rms_after_lsb": [3.0, 3.1, 2.95],
        "heldout": {"scheme": "5 folds by step", "rms_before_lsb": [6.2, 6.3, 5.1], "rms_after_lsb": [3.1, 3.2, 3.0],
                    "improvement_pct": 48.0},
        "heading_error_deg": {"before": 0.5, "after": 0.05},
        "findings": [{"effect": "stage_hard_iron", "statistic": 812.5, "df": 3, "p_value": 1e-12, "p_adjusted": 1e-11,
                      "parameters": {"stage": "outer", "m": [0.01, -0.002, 0.003]},
                      "sigma": {"m": [0.0004, 0.0004, 0.0005]}, "heading_impact_deg": 0.45,
                      "where": {"axes": ["x", "y"], "against": "theta_t, phi_t", "frame": "outer stage"},
                      "explanation": "A magnet on the outer stage <script>turns</script> with it.",
                      "confusable_with": ["stage_soft_iron"],
                      "separating_experiment": "repeat the tilted poses at two azimuths 90 deg apart"}],
        "tests": [{"effect": "stage_hard_iron", "variant": "outer", "statistic": 812.5, "df": 3, "p_value": 1e-12,
                   "p_adjusted": 1e-11, "selected": True},
                  {"effect": "nonlinearity", "variant": "odd", "statistic": 0.3, "df": 3, "p_value": 0.96,
                   "p_adjusted": 1.0, "selected": False}],
        "untestable": [{"effect": "time_lag", "reason": "no samples taken while the table moves"}],
        "locate": {"by_axis": {"rms_lsb": [6.0, 6.1, 5.0]},
                   "by_step": [{"step": s, "samples": int((rec.step == s).sum()), "rms_lsb": [4.0 + i % 3, 5.0, 3.5]}
                               for i, s in enumerate(steps)],
                   "harmonics": {"psi_t": {"orders": [1, 2, 3], "amplitude_lsb": [[5.0, 4.0, 0.1], [0.2, 0.1, 0.1],
                                                                                 [0.1, 0.1, 0.1]]}},
                   "time": {"drift_lsb_per_s": [0.0, 0.0, 0.0]}, "frame": {"best": "outer"},
                   "whiteness": {"p_value": [0.001, 0.002, 0.5]}, "witness": {}},
        "notes": ["a fake analysis for the service tests"],
    }


def fake_analyze(rec: Recording, calibration: Any = None, *, alpha: float = 0.01, null_sims: int = 200,
                 seed: Any = None, progress: Any = None) -> FakeAnalysis:
    fake_analyze.calls.append({"samples": len(rec), "calibration": calibration, "null_sims": null_sims,  # type: ignore[attr-defined]
                               "serial": rec.serial})
    for i, stage in enumerate(("compare", "locate", "name", "refit")):
        if progress:
            progress(stage, i / 4)
    n = len(rec)
    g = np.random.default_rng(0)
    before = g.normal(0, 3, (n, 3)) + 5 * np.sin(np.radians(np.nan_to_num(rec.psi_t)))[:, None]
    after = g.normal(0, 3, (n, 3))
    series = {"t": rec.t, "step": rec.step, "mag": rec.mag, "psi_t": rec.psi_t, "theta_t": rec.theta_t, "phi_t": rec.phi_t,
              "residual_before": before, "residual_after": after, "heldout_pred_before": rec.mag - before,
              "heldout_pred_after": rec.mag - after, "fold": np.arange(n) % 5}
    return FakeAnalysis(fake_result(rec, alpha), series)


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> Any:
    """physics.discrepancy.analyze replaced by :func:`fake_analyze` (the module made up when it does
    not exist yet); ``fake.calls`` records each call."""
    fake_analyze.calls = []  # type: ignore[attr-defined]
    try:
        import physics.discrepancy as mod
        monkeypatch.setattr(mod, "analyze", fake_analyze)
    except ImportError:
        mod = types.ModuleType("physics.discrepancy")
        mod.analyze = fake_analyze  # type: ignore[attr-defined]
        monkeypatch.setitem(sys.modules, "physics.discrepancy", mod)
    return fake_analyze


def self_contained(html: str) -> None:
    """Nothing in the page is fetched from elsewhere: no remote src, href, url() or @import."""
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", html, re.I), "a remote resource"
    assert not re.search(r"url\(\s*['\"]?(https?:)?//", html, re.I) and "@import" not in html
    assert "<script" not in html.lower()


# ----------------------------------------------------------------------------------------- report

def test_report_from_a_stored_result_has_every_table_and_no_external_resource(fake):
    rec = simulated()
    a = fake(rec)
    html = analysis_html(json.loads(json.dumps(a.result)), None, "Stored <analysis>")
    self_contained(html)
    assert "<title>Stored &lt;analysis&gt;</title>" in html
    assert "&lt;script&gt;turns&lt;/script&gt;" in html  # the analyser's text is escaped, never markup
    for text in ("stage_hard_iron", "0.01 ± 0.0004", "stage_soft_iron", "two azimuths 90 deg apart", "time_lag",
                 "no samples taken while the table moves", "a fake analysis for the service tests", "nonlinearity",
                 "48 %", "by_step", "whiteness"):
        assert text in html, text
    assert 'id="fig-by_step"' in html and 'id="fig-harmonics"' in html and 'id="fig-fit"' in html
    assert 'id="fig-time"' not in html  # per-sample plots need the series


def test_report_with_series_plots_residuals_against_time_angles_and_held_out(fake):
    rec = simulated()
    a = fake(rec)
    html = analysis_html(a.result, {**a.series, "mag": rec.mag}, "With series")
    self_contained(html)
    for key in ("fit", "time", "angles", "by_step", "harmonics", "heldout"):
        assert f'id="fig-{key}"' in html, key
    assert html.count("<svg") >= 6 and "data:image/png;base64," in html  # dense layers rasterised inline


def test_report_without_table_angles_leaves_out_the_angle_plots(fake):
    rec = simulated()
    free = Recording.from_arrays(t=rec.t, step=rec.step, psi_t=np.full(len(rec), np.nan), theta_t=np.full(len(rec), np.nan),
                                 phi_t=np.full(len(rec), np.nan), mag=rec.mag, meta={})
    a = fake(free)
    series = {**a.series, "residual_before": np.c_[a.series["residual_before"][:, :1], np.full((len(rec), 2), np.nan)],
              "residual_after": np.c_[a.series["residual_after"][:, :1], np.full((len(rec), 2), np.nan)]}
    html = analysis_html(a.result, series, "hand-held")
    self_contained(html)
    assert 'id="fig-time"' in html and 'id="fig-angles"' not in html and "attitude_free" in html



def test_report_shows_where_the_mismatch_lives_as_labelled_tables_and_links_back_to_the_run():
    """With the real analyser: the locate part of the result is labelled tables (axes as columns with
    units, harmonic orders as rows, turning + / turning - per angle), never the raw dict dump; odd or
    unknown parts fall back to the generic rendering; a run's report links back to the run page."""
    from physics.discrepancy import analyze

    result = json.loads(json.dumps(analyze(with_magnet(simulated("SN-LOC")), null_sims=10,
                                           seed=4).to_json()))
    locate = result["locate"]
    assert locate["harmonics"] and locate["whiteness"]["per_axis"] and locate["frame"]
    html = analysis_html(result, None, "located")
    self_contained(html)
    for angle, label in (("psi_t", "ψ"), ("theta_t", "θ"), ("phi_t", "φ")):
        if angle in locate["harmonics"]:
            assert f"<caption>against {angle} ({label})</caption>" in html, angle
    assert "<th>order</th><th>amplitude m_x (LSB)</th><th>amplitude m_y (LSB)</th><th>amplitude m_z (LSB)</th>" in html
    assert "<th>1 × per turn</th>" in html and "<th>4 × per turn</th>" in html
    assert "<th>m_x (LSB)</th><th>m_y (LSB)</th><th>m_z (LSB)</th>" in html  # by axis
    assert "linear trend over the run (LSB/min)" in html and "Ljung-Box Q (10 lags)" in html
    assert "<th>the residual is…</th><th>statistic</th><th>df</th><th>p</th>" in html
    assert f"<th>{next(iter(locate['frame']))}</th>" in html
    for raw in ("amplitude_lsb", "orders", "ljung_box_q", "per_axis", "trend_lsb_per_min", "rms_lsb", "mean_lsb",
                "p_value", "dominant"):
        assert raw not in html.split('id="locate"')[1].split("</div>")[0], raw
    if not locate["direction"]:
        assert "No turns in both directions were recorded" in html
    # turns both ways (the shape physics.discrepancy.analysis.locate gives): a row per direction and angle
    turned = {**result, "locate": {**locate, "direction": {
        "psi": {"positive_mean_lsb": [1.5, -0.25, 0.125], "negative_mean_lsb": [-1.5, 0.25, -0.125], "speeds_dps": [10.0, 20.0]},
        "theta": {"positive_mean_lsb": [0.5, 0.5, 0.5], "negative_mean_lsb": [0.5, 0.5, 0.5], "speeds_dps": [5.0]}}}}
    html = analysis_html(turned, None, "turned")
    section = html.split('id="locate-direction"')[1].split("</section>")[0]
    assert "<th>angle</th><th>direction</th><th>mean m_x (LSB)</th><th>mean m_y (LSB)</th><th>mean m_z (LSB)</th>" in section
    assert section.count("turning +") == 2 and section.count("turning −") == 2
    assert '<td class="n">turning +</td><td class="n">1.5</td><td class="n">-0.25</td><td class="n">0.125</td>' in section
    assert "positive_mean_lsb" not in html and "speeds_dps" not in html and "10, 20" in section
    # odd values never break the page; unknown keys and shapes are shown as they came
    odd = {**result, "locate": {"by_axis": None, "harmonics": {"psi_t": {"amplitude_lsb": [[None, "a"], 3]}, "psi_x": 5},
                                "direction": {"psi": None}, "frame": {"somewhere": {"statistic": float("nan")}},
                                "whiteness": {"ljung_box": 3.0}, "witness": None, "brand_new": {"answer": 42}}}
    html = analysis_html(odd, None, "odd")
    assert 'id="locate-brand_new"' in html and "<th>answer</th><td>42</td>" in html and "<th>psi_x</th><td>5</td>" in html
    assert "<th>ljung_box</th><td>3</td>" in html and "<th>somewhere</th>" in html
    # the report of a run links back to the run page; a report of a file has no such link
    assert 'href="/ui/runs/7"' in analysis_html(result, None, "of run 7", run_url="/ui/runs/7")
    assert 'id="run-link"' not in analysis_html(result, None, "of a file")


def test_a_discovered_blocks_raw_coefficients_are_shown_once_under_their_names():
    """The JSON keeps a discovered block's coefficients for programs ("values", named by "labels"); a
    person sees them once: not at all where a named parameter repeats them, else under their labels."""
    offset = {"effect": "discovered", "parameters": {"labels": ["d[0]", "d[1]", "d[2]"], "values": [-197.6, -25.7, None],
                                                     "offset_lsb": [-197.6, -25.7, None], "offset_ut": [-1.976, -0.257, None]},
              "sigma": {"values": [12.0, 7.5, None], "offset_lsb": [12.0, 7.5, None], "offset_ut": [0.12, 0.075, None]}}
    rows = dict(parameter_rows(offset))
    assert list(rows) == ["offset_lsb", "offset_ut"], rows
    assert rows["offset_lsb"].startswith("[-197.6 ± 12")
    smooth = {"effect": "discovered", "parameters": {"labels": ["x P1", "y P1"], "values": [0.5, -0.25], "span_lsb": [3.0, 1.5]},
              "sigma": {"values": [0.125, 0.0625]}}
    rows = dict(parameter_rows(smooth))
    assert list(rows) == ["values (x P1, y P1)", "span_lsb"] and rows["values (x P1, y P1)"] == "[0.5 ± 0.12, -0.25 ± 0.062]", rows
    assert parameter_cells(smooth)[0] == ("values (x P1, y P1)", ["0.5 ± 0.12", "-0.25 ± 0.062"])
    # a catalogue finding's parameters are shown as they are
    catalogue = {"effect": "time_lag", "parameters": {"lag_s": 0.2}, "sigma": {"lag_s": 0.01}}
    assert parameter_rows(catalogue) == [("lag_s", "0.2 ± 0.01")]


# -------------------------------------------------------------------------------------------- CLI

def test_cli_analyze_with_the_real_analyser_names_a_concealed_magnet(tmp_path: Path):
    """End to end with physics.discrepancy: a magnet on the middle stage is found, named first, its
    parameters printed; the JSON is exactly the analyser's; the report is one self-contained file."""
    from physics.discrepancy import analyze

    rec_path, out_json, out_html = tmp_path / "magnet.csv", tmp_path / "a.json", tmp_path / "a.html"
    rec_path.write_text(format_recording(with_magnet(simulated("SN-MAG"))))
    r = runner.invoke(app, ["analyze", str(rec_path), "--json", str(out_json), "--html", str(out_html),
                            "--null-sims", "30", "--seed", "4"])
    assert r.exit_code == 0, r.output
    out = said(r.output)
    assert "verdict: discrepancy" in out and "noise floor" in out and "held-out improvement" in out
    expected = analyze(parse_recording(rec_path.read_text()), null_sims=30, seed=4).to_json()
    written = json.loads(out_json.read_text())
    assert written == json.loads(json.dumps(expected))
    assert "stage_hard_iron" in named(written), written["findings"]
    first = written["findings"][0]
    assert f"1. {first['effect']}" in out and f"p {report.num(first['p_value'], 3)}" in out
    if first["confusable_with"]:
        assert f"confusable with {', '.join(first['confusable_with'])}" in out
    for u in written["untestable"]:
        assert f"{u['effect']}: {u['reason']}" in out
    assert written["heldout"]["improvement_pct"] > 10
    html = out_html.read_text()
    self_contained(html)
    for key in ("fit", "time", "angles", "by_step", "harmonics", "heldout"):
        assert f'id="fig-{key}"' in html, key
    assert f'data-effect="{first["effect"]}"' in html and "SN-MAG" in html


def test_cli_analyze_with_the_real_analyser_finds_a_clean_recording_consistent(tmp_path: Path):
    rec_path, out_json = tmp_path / "clean.csv", tmp_path / "a.json"
    rec_path.write_text(format_recording(simulated("SN-CLEAN")))
    r = runner.invoke(app, ["analyze", str(rec_path), "--json", str(out_json), "--null-sims", "30", "--seed", "4"])
    assert r.exit_code == 0, r.output
    assert "verdict: consistent" in said(r.output) and "findings: none beyond the noise" in said(r.output)
    written = json.loads(out_json.read_text())
    assert written["verdict"] == "consistent" and written["findings"] == []


def test_cli_analyze_prints_the_summary_and_writes_json_and_html(tmp_path: Path, fake):
    rec_path, out_json, out_html = tmp_path / "rec.csv", tmp_path / "out" / "a.json", tmp_path / "out" / "a.html"
    rec_path.write_text(format_recording(simulated()))
    out_json.parent.mkdir()  # (analyze no longer makes a missing directory: a mistyped one is said, as every command does)
    r = runner.invoke(app, ["analyze", str(rec_path), "--json", str(out_json), "--html", str(out_html),
                            "--null-sims", "7", "--seed", "3"])
    assert r.exit_code == 0, r.output
    out = said(r.output)
    for text in ("verdict: discrepancy", "noise floor", "held-out improvement: 48 %", "1. stage_hard_iron",
                 "heading impact 0.45 deg", "m = [0.01 ± 0.0004", "confusable with stage_soft_iron",
                 "untestable on this recording", "time_lag: no samples taken while the table moves"):
        assert text in out, text
    assert fake.calls[0]["null_sims"] == 7 and fake.calls[0]["calibration"] is None
    assert json.loads(out_json.read_text()) == json.loads(json.dumps(fake_result(parse_recording(rec_path.read_text()))))
    html = out_html.read_text()
    self_contained(html)
    assert 'id="fig-heldout"' in html and "Held-out residuals" in html  # the series carry the measurement


def without_angles(rec: Recording) -> Recording:
    """The same readings as a recording without table angles (a hand-held one)."""
    nan = np.full(len(rec), np.nan)
    return Recording.from_arrays(t=rec.t, step=rec.step, psi_t=nan, theta_t=nan, phi_t=nan, mag=rec.mag, acc=rec.acc,
                                 temp_c=rec.temp_c, meta=dict(rec.meta))


def test_cli_analyze_with_the_real_analyser_on_a_recording_without_table_angles(tmp_path: Path):
    rec_path, out_json, out_html = tmp_path / "handheld.csv", tmp_path / "a.json", tmp_path / "a.html"
    rec_path.write_text(format_recording(without_angles(simulated("SN-HAND"))))
    r = runner.invoke(app, ["analyze", str(rec_path), "--json", str(out_json), "--html", str(out_html),
                            "--null-sims", "20", "--seed", "1"])
    assert r.exit_code == 0, r.output
    written = json.loads(out_json.read_text())
    assert written["model"] == "attitude_free" and "model attitude_free" in said(r.output)
    assert f"verdict: {written['verdict']}" in said(r.output) and "|m|" in r.output
    html = out_html.read_text()
    self_contained(html)
    assert 'id="fig-time"' in html and 'id="fig-angles"' not in html


def test_cli_analyze_takes_the_unit_calibration_as_nominal_model(tmp_path: Path, fake):
    rec = simulated()
    rec_path, cal_path = tmp_path / "rec.csv", tmp_path / "cal.json"
    rec_path.write_text(format_recording(rec))
    cal_path.write_text(json.dumps(fit(rec, "joint").to_json()))
    r = runner.invoke(app, ["analyze", str(rec_path), "--calibration", str(cal_path)])
    assert r.exit_code == 0, r.output
    assert fake.calls[0]["calibration"].method == "joint"


def test_cli_analyze_names_the_line_of_a_bad_csv_and_the_field_of_a_bad_calibration(tmp_path: Path, fake):
    bad = tmp_path / "bad.csv"
    bad.write_text("# compasscal-recording: 1\nt,step,psi_t,theta_t,phi_t,mx,my,mz\n0,a,0,0,0,1,2,3\n0.1,a,0,0,0,x,2,3\n")
    r = runner.invoke(app, ["analyze", str(bad)])
    assert r.exit_code == 2 and "line 4" in r.output and "mx" in r.output and "bad.csv:" in said(r.output)
    good = tmp_path / "rec.csv"
    good.write_text(format_recording(simulated()))
    cal = fit(simulated(), "joint").to_json()
    for broken, field in (({**cal, "format": "other"}, "format"), ({**cal, "magnetometer": {"k": [1, 2, 3]}}, "magnetometer")):
        path = tmp_path / "cal.json"
        path.write_text(json.dumps(broken))
        r = runner.invoke(app, ["analyze", str(good), "--calibration", str(path)])
        assert r.exit_code == 2 and f"{field}:" in said(r.output) and "cal.json" in said(r.output), r.output
    path.write_text("{not json")
    r = runner.invoke(app, ["analyze", str(good), "--calibration", str(path)])
    assert r.exit_code == 2 and "not JSON: line 1" in said(r.output)
    # another unit's calibration, refused as the API refuses it (every difference between two units would
    # read as a "parameter shift": a discrepancy, exit 0)
    path.write_text(json.dumps(fit(simulated("SN-OTHER", seed=2), "joint").to_json()))
    r = runner.invoke(app, ["analyze", str(good), "--calibration", str(path)])
    assert r.exit_code == 2 and "the calibration of unit SN-OTHER, but rec.csv is of unit" in said(r.output), r.output
    assert not fake.calls  # nothing analysed on bad input


# -------------------------------------------------------------------------------------------- API

def upload(api: Any, serial: str = "SN-AN", seed: int = 1) -> int:
    r = api.post("/recordings", role="operator", content=format_recording(simulated(serial, seed)).encode())
    assert r.status_code == 201, r.text
    return r.json()["id"]


def analysed(api: Any, run_id: int, timeout: float = 120.0, **kw: Any) -> list[dict[str, Any]]:
    """POST an analysis of the run: it answers 202 at once with the analyses queued; each is then
    polled at its url until it has ended. The ended analyses."""
    r = api.post(f"/runs/{run_id}/analysis", role="operator", **kw)
    assert r.status_code == 202, r.text
    queued = r.json()["analyses"]
    assert queued and r.json()["run_id"] == run_id and r.headers["location"] == f"/analyses/{queued[0]['id']}"
    for a in queued:
        assert a["status"] in ("queued", "running", "completed") and a["url"] == f"/analyses/{a['id']}"
    done = []
    for a in queued:
        deadline = time.monotonic() + timeout
        while True:
            got = api.get(a["url"], role="viewer").json()
            if got["status"] in ("completed", "failed"):
                break
            assert time.monotonic() < deadline, got
            time.sleep(0.05)
        done.append(got)
    return done


def audited(api: Any, action: str) -> list[AuditLog]:
    with api.client.app.state.sessions() as s:
        return list(s.scalars(select(AuditLog).where(AuditLog.action == action)))


def test_api_analysis_is_stored_and_read_back(api):
    """With the real analyser: an uploaded recording with a concealed magnet, analysed through the
    API, stored, read back identical, listed, reported in HTML, audited, linked from the run page."""
    from physics.discrepancy import analyze

    rec = with_magnet(simulated("SN-AN"))
    r = api.post("/recordings", role="operator", content=format_recording(rec).encode())
    assert r.status_code == 201, r.text
    run_id = r.json()["id"]
    [created] = analysed(api, run_id, json={"null_sims": 20})
    assert created["status"] == "completed" and created["report_url"] == f"/analyses/{created['id']}/report"
    assert created["slot"] == 0 and created["serial"] == "SN-AN" and created["verdict"] == "discrepancy"
    assert created["null_sims"] == 20 and created["calibration_id"] is None
    assert "stage_hard_iron" in named(created), created["findings"]
    got = api.get(f"/analyses/{created['id']}", role="viewer")
    assert got.status_code == 200 and got.json() == created
    # the stored result is the analyser's on the recording as exported, seeded by its fingerprint: the
    # export analysed anywhere without a seed gives the same result
    stored = parse_recording(api.get(f"/runs/{run_id}/samples", role="viewer").text)
    expected = json.loads(json.dumps(analyze(stored, null_sims=20).to_json()))
    assert expected["seed"] == stored.fingerprint() == rec.fingerprint()
    assert {k: v for k, v in got.json().items() if k in expected} == expected
    listed = api.get(f"/runs/{run_id}/analyses", role="viewer").json()
    effects = [f["effect"] for f in created["findings"]]
    assert [(a["id"], a["verdict"], a["findings"]) for a in listed] == [(created["id"], "discrepancy", effects)]
    page = api.get(f"/analyses/{created['id']}/report", role="viewer")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    self_contained(page.text)
    assert f"run {run_id}, slot 0 (SN-AN)" in page.text and f'data-effect="{effects[0]}"' in page.text
    assert 'id="fig-by_step"' in page.text and 'id="fig-harmonics"' in page.text
    assert f'href="/ui/runs/{run_id}"' in page.text and '<th>1 × per turn</th>' in page.text  # back to the run
    [log] = audited(api, "analysis.create")
    assert log.owner == "operator-user" and log.target == f"run {run_id}" and log.detail["analyses"][0]["id"] == created["id"]
    page = api.get(f"/ui/runs/{run_id}", role="viewer")
    assert page.status_code == 200 and f'href="/analyses/{created["id"]}/report"' in page.text


def test_api_analysis_of_an_uploaded_recording_without_table_angles(api):
    text = format_recording(without_angles(simulated("SN-HAND")))
    run_id = api.post("/recordings", role="operator", content=text.encode()).json()["id"]
    [created] = analysed(api, run_id, json={"null_sims": 10})
    assert created["model"] == "attitude_free" and created["serial"] == "SN-HAND"
    assert api.get(f"/analyses/{created['id']}", role="viewer").json() == created
    page = api.get(f"/analyses/{created['id']}/report", role="viewer")
    assert page.status_code == 200 and "attitude_free" in page.text
    self_contained(page.text)


def test_api_analysis_uses_the_run_calibration_or_the_one_asked(api, fake):
    run_id = upload(api, "SN-CAL")
    app_ = api.client.app
    with app_.state.sessions() as s:
        run = s.get(Run, run_id)
        cal = store_calibration(s, run, 0, "SN-CAL", fit(simulated("SN-CAL"), "joint").to_json())
        other = store_calibration(s, run, 0, "SN-CAL", fit(simulated("SN-CAL", seed=5), "ellipsoid").to_json())
        s.commit()
        ids = cal.id, other.id
    # no body at all: every slot, the run's own (newest) calibration of the unit
    [a] = analysed(api, run_id)
    assert a["calibration_id"] == ids[1] and fake.calls[-1]["calibration"].method == "ellipsoid"
    [a] = analysed(api, run_id, json={"slot": 0, "calibration_id": ids[0]})
    assert a["calibration_id"] == ids[0]
    assert fake.calls[-1]["calibration"].method == "joint"
    assert len(api.get(f"/runs/{run_id}/analyses", role="viewer").json()) == 2
    # a later run of the unit without a calibration of its own: the unit's current calibration
    later = upload(api, "SN-CAL", seed=7)
    current = api.get("/devices/SN-CAL/calibrations/current", role="viewer").json()["id"]
    [a] = analysed(api, later)
    assert a["calibration_id"] == current
    # a unit never calibrated: none (the analyser's own fit is the nominal model)
    [a] = analysed(api, upload(api, 'SN-NEW'))
    assert a["calibration_id"] is None
    assert fake.calls[-1]["calibration"] is None
    # another unit's calibration is refused: every difference between two units would be a "parameter shift"
    r = api.post(f"/runs/{later}/analysis", role="operator", json={"calibration_id": api.get(
        "/devices/SN-CAL/calibrations/current", role="viewer").json()["id"]})
    assert r.status_code == 202
    r = api.post(f"/runs/{upload(api, 'SN-OTHER')}/analysis", role="operator", json={"calibration_id": current})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.calibration_id", r.text
    assert f"calibration {current} is of unit SN-CAL, not of the unit of run" in r.text and "(SN-OTHER)" in r.text


def test_api_analysis_roles_and_errors(api, fake):
    run_id = upload(api)
    assert api.post(f"/runs/{run_id}/analysis", role=None).status_code == 401
    r = api.post(f"/runs/{run_id}/analysis", role="viewer")
    assert r.status_code == 403 and "operator" in r.json()["detail"]
    assert api.post("/runs/9999/analysis", role="operator").status_code == 404
    assert api.get("/runs/9999/analyses", role="viewer").status_code == 404
    assert api.get("/analyses/9999", role="viewer").status_code == 404
    assert api.get("/analyses/9999/report", role="viewer").status_code == 404
    assert api.get("/analyses/1", role=None).status_code == 401
    for body, field in (({"slot": -1}, "body.slot"), ({"null_sims": "many"}, "body.null_sims"),
                        ({"null_sims": 10**6}, "body.null_sims"), ({"calibration_id": 12345}, "body.calibration_id"),
                        ({"slots": 0}, "body.slots"), ([1, 2], "body")):
        r = api.post(f"/runs/{run_id}/analysis", role="operator", json=body)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == field, (body, r.text)
    # a slot without samples is the body's mistake (it was a 409 naming no field)
    r = api.post(f"/runs/{run_id}/analysis", role="operator", json={"slot": 3})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.slot", r.text
    assert "slot 3" in r.text and "slots with samples: 0" in r.text, r.text
    # too few samples for any analysis: refused at once, not queued to fail (a 3-sample upload was)
    short = simulated("SN-SHORT", 1).select(slice(0, 3))
    r = api.post("/recordings", role="operator", content=format_recording(short).encode())
    assert r.status_code == 201, r.text
    short_id = r.json()["id"]
    r = api.post(f"/runs/{short_id}/analysis", role="operator")
    assert r.status_code == 409 and "slot 0: 3 samples, the analysis needs at least 200" in r.text, r.text
    r = api.post(f"/runs/{short_id}/analysis", role="operator", json={"slot": 0})
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body.slot" and "3 samples" in r.text, r.text
    with api.client.app.state.sessions() as s:
        empty = Run(procedure="import", procedure_version="1", parameters={}, status="completed", operator="t",
                    serials={"0": "SN-E"}, software_version="test")
        active = Run(procedure="calibrate", procedure_version="2", parameters={}, status="running", operator="t",
                     serials={"0": "SN-R"}, software_version="test")
        s.add_all([empty, active])
        s.commit()
        empty_id, active_id = empty.id, active.id
    r = api.post(f"/runs/{empty_id}/analysis", role="operator")
    assert r.status_code == 409 and "no samples" in r.json()["detail"]
    r = api.post(f"/runs/{active_id}/analysis", role="operator")
    assert r.status_code == 409 and "running" in r.json()["detail"]
    assert not fake.calls and not audited(api, "analysis.create")


@pytest.fixture
def gated(fake: Any, monkeypatch: pytest.MonkeyPatch) -> Any:
    """The fake analyser, held after its first progress report until ``gated.open.set()``."""
    import threading

    import physics.discrepancy as mod

    gate = threading.Event()

    def held(rec: Recording, calibration: Any = None, **kw: Any) -> FakeAnalysis:
        if kw.get("progress"):
            kw["progress"]("compare", 0.25)
        assert gate.wait(60), "the test never opened the gate"
        return fake_analyze(rec, calibration, **kw)
    monkeypatch.setattr(mod, "analyze", held)
    held.open = gate  # type: ignore[attr-defined]
    return held


def test_api_analysis_answers_at_once_and_its_progress_is_pollable_and_streamable(api, gated):
    """POST answers 202 before the analysis has ended; the analysis is pollable (running, with its
    stage) and streamable (a state event per change, Last-Event-ID resumes); its report is 409
    until it has completed; then every view agrees."""
    from conftest import parse_sse

    run_id = upload(api, "SN-JOB")
    t0 = time.monotonic()
    r = api.post(f"/runs/{run_id}/analysis", role="operator", json={"null_sims": 5})
    assert r.status_code == 202 and time.monotonic() - t0 < 5.0, r.text
    [queued] = r.json()["analyses"]
    assert queued["status"] in ("queued", "running") and queued["serial"] == "SN-JOB" and queued["null_sims"] == 5
    assert queued["report_url"] is None and "verdict" not in queued
    deadline = time.monotonic() + 30
    while (got := api.get(queued["url"], role="viewer").json())["status"] != "running" or not got["progress"] \
            or got["progress"]["stage"] != "compare":
        assert time.monotonic() < deadline, got
        time.sleep(0.02)
    assert got["progress"]["percent"] == 25.0 and got["started_at"] is not None and got["finished_at"] is None
    r = api.get(f"/analyses/{queued['id']}/report", role="viewer")
    assert r.status_code == 409 and "running" in r.json()["detail"]
    [line] = api.get(f"/runs/{run_id}/analyses", role="viewer").json()
    assert line["status"] == "running" and line["verdict"] is None and line["report_url"] is None
    # the same analysis asked again while it runs is that one (a retry queued four of one run and slot)
    again = api.post(f"/runs/{run_id}/analysis", role="operator", json={"null_sims": 5})
    assert again.status_code == 202 and [a["id"] for a in again.json()["analyses"]] == [queued["id"]], again.text
    assert len(api.get(f"/runs/{run_id}/analyses", role="viewer").json()) == 1
    gated.open.set()
    with api.client.stream("GET", queued["events_url"], headers={"X-API-Key": api.keys["viewer"]}) as s:
        assert s.status_code == 200 and s.headers["content-type"].startswith("text/event-stream")
        events = parse_sse(s.iter_lines())
    states = [d["status"] for _, kind, d in events if kind == "state"]
    assert states[-1] == "completed" and events[-1][2]["verdict"] == "discrepancy"
    ids = [i for i, _, _ in events]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    done = api.get(queued["url"], role="viewer").json()
    assert done["status"] == "completed" and done["verdict"] == "discrepancy" and done["progress"]["percent"] == 100.0
    # Last-Event-ID: only what came after
    with api.client.stream("GET", queued["events_url"], headers={"X-API-Key": api.keys["viewer"],
                                                                 "Last-Event-ID": str(ids[-1] - 1)}) as s:
        again = parse_sse(s.iter_lines())
    assert [i for i, _, _ in again] == [ids[-1]]
    assert api.get(f"/analyses/{queued['id']}/report", role="viewer").status_code == 200


def test_api_analysis_of_a_recording_that_cannot_support_it_fails_saying_why(api, fake, monkeypatch):
    import physics.discrepancy as mod

    def refuse(rec: Recording, calibration: Any = None, **kw: Any) -> Any:
        raise ValueError("no static hold of 2 s or more")
    monkeypatch.setattr(mod, "analyze", refuse)
    run_id = upload(api, "SN-SHORT")
    [a] = analysed(api, run_id)
    assert a["status"] == "failed" and "cannot be analysed: no static hold" in a["reason"] and a["finished_at"]
    assert api.get(f"/analyses/{a['id']}/report", role="viewer").status_code == 409


def test_an_analysis_whose_job_was_lost_is_computed_when_the_service_starts_again(db_url, fake):
    """The service stopped between storing an analysis request and computing it (on SQLite its queue
    is in memory; on PostgreSQL its job was never queued): the next start queues it again."""
    from datetime import timedelta

    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.auth import create_key
    from service.db import Analysis, utcnow

    app = create_app(db_url)
    with TestClient(app) as client:
        with app.state.sessions() as s:
            key = create_key(s, "op", "operator")
        r = client.post("/recordings", headers={"X-API-Key": key}, content=format_recording(simulated("SN-LOST")).encode())
        run_id = r.json()["id"]
        with app.state.sessions() as s:
            row = Analysis(run_id=run_id, slot=0, status="queued", created_at=utcnow() - timedelta(minutes=1),
                           request={"null_sims": 3, "calibration_id": None, "serial": "SN-LOST"})
            s.add(row)
            s.commit()
            lost = row.id
    assert not fake.calls
    app = create_app(db_url)
    with TestClient(app) as client:
        deadline = time.monotonic() + 60
        while (got := client.get(f"/analyses/{lost}", headers={"X-API-Key": key}).json())["status"] != "completed":
            assert time.monotonic() < deadline, got
            time.sleep(0.05)
    assert got["verdict"] == "discrepancy" and got["serial"] == "SN-LOST" and len(fake.calls) == 1
