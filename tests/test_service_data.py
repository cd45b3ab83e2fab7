"""The service's data side on SQLite and PostgreSQL: auth, uploads, calibration history with verdicts
and superseding, acceptance limits, the audit log, the migrations."""

from __future__ import annotations

import numpy as np
from sqlalchemy import select

from physics.fit import fit
from physics.recording import format_recording, parse_recording
from physics.sensor import reference_unit
from physics.simulate import World, simulate_recording
from procedures.calibrate import calibration_poses, CalibrateParams
from service.db import AuditLog, Run
from service.store import store_calibration


def recording_text(serial: str = "SN-UP", seed: int = 1, noise: float = 3.0) -> str:
    rec = simulate_recording(reference_unit(noise, 4.0, serial=serial), calibration_poses(CalibrateParams(samples=20)),
                             World(), rng=np.random.default_rng(seed))
    return format_recording(rec)


def test_health_needs_no_key_and_everything_else_does(api):
    r = api.get("/health", role=None)
    assert r.status_code == 200 and r.json()["status"] == "ok"
    assert api.get("/limits", role=None).status_code == 401
    assert api.get("/limits", role=None, headers={"X-API-Key": "cc_wrong"}).status_code == 401
    assert api.get("/limits", role="viewer").status_code == 200
    r = api.put("/limits/bias_lsb", role="operator", json={"marginal": 1, "fail": 2})
    assert r.status_code == 403 and "admin" in r.json()["detail"]


def test_upload_a_foreign_recording_as_an_import_run(api):
    text = recording_text()
    r = api.post("/recordings", role="operator", content=text.encode(), headers={"Content-Type": "text/csv"})
    assert r.status_code == 201, r.text
    run = r.json()
    assert run["procedure"] == "import" and run["serial"] == "SN-UP" and run["samples"] == 18 * 20
    # an import starts and ends as it is stored (both were null)
    got = api.get(f"/runs/{run['id']}", role="viewer").json()
    assert got["started_at"] and got["finished_at"] and got["started_at"] <= got["finished_at"], got
    csv = api.get(f"/runs/{run['id']}/samples", role="viewer")
    assert csv.status_code == 200
    back = parse_recording(csv.text)
    original = parse_recording(text)
    np.testing.assert_allclose(back.mag, original.mag)
    np.testing.assert_allclose(back.psi_t, original.psi_t)
    assert back.serial == "SN-UP"
    assert api.get("/recordings", role="viewer").status_code in (404, 405)
    # without a serial: none said, neither an empty "# serial:" line in the export nor "" in an analysis
    anon = api.post("/recordings", role="operator", content="\n".join(
        line for line in text.splitlines() if not line.startswith("# serial:")).encode()).json()
    assert anon["serial"] is None
    exported = api.get(f"/runs/{anon['id']}/samples", role="viewer").text
    assert "# serial:" not in exported and parse_recording(exported).serial is None
    analysis = api.post(f"/runs/{anon['id']}/analysis", role="operator", json={"null_sims": 0})
    assert analysis.status_code == 202 and analysis.json()["analyses"][0]["serial"] is None, analysis.text


def test_an_imports_export_says_its_own_run_and_keeps_what_the_file_said(api):
    """The run a recording became is the export's run, procedure, operator and slot, whatever the file's
    own lines said (an export said "run_id: 999", "operator: mallory"; re-imported, an export of run 1
    said run 1); the file's differing words are kept as imported_<key>."""
    text = recording_text().replace("# serial:", "# operator: mallory\n# run_id: 999\n# procedure: calibrate\n# serial:", 1)
    r = api.post("/recordings", role="operator", content=text.encode())
    assert r.status_code == 201, r.text
    rid = r.json()["id"]
    meta = parse_recording(api.get(f"/runs/{rid}/samples", role="viewer").text).meta
    run = api.get(f"/runs/{rid}", role="viewer").json()
    assert (meta["run_id"], meta["procedure"], meta["operator"], meta["slot"]) == (str(rid), "import", run["operator"], "0")
    assert run["operator"] != "mallory" and meta["serial"] == "SN-UP", meta
    assert (meta["imported_run_id"], meta["imported_procedure"], meta["imported_operator"]) == ("999", "calibrate", "mallory")
    again = api.post("/recordings", role="operator", content=api.get(f"/runs/{rid}/samples", role="viewer").content)
    meta2 = parse_recording(api.get(f"/runs/{again.json()['id']}/samples", role="viewer").text).meta
    assert meta2["run_id"] == str(again.json()["id"]) and meta2["imported_run_id"] == str(rid), meta2


def test_a_bad_upload_names_the_line_and_an_oversized_one_is_refused(api, monkeypatch):
    bad = recording_text().replace("\n", "\nnot,a,row\n", 1)
    r = api.post("/recordings", role="operator", content=bad.encode())
    assert r.status_code == 422 and "line" in r.text
    # table angles in radians are refused as `compasscal fit` refuses them, before anything is stored
    # (the upload took them, and only an analysis failed later)
    rec = parse_recording(recording_text())
    rec.psi_t, rec.theta_t, rec.phi_t = (np.radians(a) for a in (rec.psi_t, rec.theta_t, rec.phi_t))
    runs = len(api.get("/runs", role="viewer").json())
    r = api.post("/recordings", role="operator", content=format_recording(rec).encode())
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "body" and "look like radians" in r.text, r.text
    assert len(api.get("/runs", role="viewer").json()) == runs
    import service.routes.recordings
    monkeypatch.setattr(service.routes.recordings, "MAX_UPLOAD_BYTES", 1000)
    r = api.post("/recordings", role="operator", content=recording_text().encode())
    assert r.status_code == 413


def test_history_keeps_every_calibration_newest_first(api):
    """Stored through the same path a run takes: a passing calibration becomes current and
    supersedes the old; a failing one is kept as rejected and changes nothing."""
    app = api.client.app
    cals = []
    for seed in (1, 2, 3):
        rec = parse_recording(recording_text(serial="SN-H", seed=seed))
        cals.append(fit(rec, "joint").to_json())
    cals[2]["magnetometer"]["bias"] = [5000.0, 0.0, 0.0]  # beyond the 4000 LSB fail limit
    with app.state.sessions() as session:
        run = Run(procedure="calibrate", procedure_version="2", parameters={}, status="completed", operator="t",
                  serials={"0": "SN-H"}, software_version="test")
        session.add(run)
        session.flush()
        rows = [store_calibration(session, run, 0, "SN-H", c, model="XDC-3") for c in cals]
        session.commit()
        verdicts = [r.verdict for r in rows]
    assert verdicts[0] in ("PASS", "MARGINAL") and verdicts[1] in ("PASS", "MARGINAL") and verdicts[2] == "FAIL"
    hist = api.get("/devices/SN-H/calibrations", role="viewer").json()
    assert [h["status"] for h in hist] == ["rejected", "current", "superseded"]
    assert any("bias_lsb" in reason and "fail" in reason for reason in hist[0]["reasons"])
    cur = api.get("/devices/SN-H/calibrations/current", role="viewer").json()
    assert cur["id"] == rows[1].id and cur["format"] == "compasscal-calibration/1" and cur["verdict"] == verdicts[1]
    dev = api.get("/devices/SN-H", role="viewer").json()
    assert dev["calibrations"] == 3 and dev["current_calibration_id"] == rows[1].id and dev["model"] == "XDC-3"
    assert api.get("/devices/NOPE", role="viewer").status_code == 404
    assert api.get(f"/calibrations/{rows[0].id}", role="viewer").json()["status"] == "superseded"


def test_limits_are_data_and_changes_are_audited(api):
    limits = {lim["name"]: lim for lim in api.get("/limits", role="viewer").json()}
    assert {"residual_rms_lsb", "heading_error_level_deg", "heading_error_tilted_deg", "misalignment_deg",
            "sensitivity_mismatch", "bias_lsb"} <= set(limits)
    r = api.put("/limits/bias_lsb", role="admin", json={"marginal": 10.0, "fail": 20.0})
    assert r.status_code == 200 and r.json()["description"] == limits["bias_lsb"]["description"]  # (was null)
    assert {lim["name"]: lim for lim in api.get("/limits").json()}["bias_lsb"]["fail"] == 20.0
    bad = api.put("/limits/bias_lsb", json={"marginal": "lots", "fail": 20})
    assert bad.status_code == 422 and bad.json()["detail"][0]["field"] == "body.marginal"
    assert api.put("/limits/bias_lsb", json={"marginal": 30, "fail": 20}).status_code == 422
    assert api.put("/limits/nonsense", json={"marginal": 1, "fail": 2}).status_code == 404
    with api.client.app.state.sessions() as session:
        log = session.scalars(select(AuditLog).where(AuditLog.action == "limit.update")).all()
    assert len(log) == 1 and log[0].owner == "admin-user" and log[0].detail["new"]["fail"] == 20.0


def test_the_service_upgrades_an_existing_database_without_losing_data(db_url):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.auth import create_key
    app = create_app(db_url)
    with TestClient(app) as client:
        with app.state.sessions() as session:
            key = create_key(session, "x", "admin")
        client.put("/limits/bias_lsb", headers={"X-API-Key": key}, json={"marginal": 5, "fail": 6})
    app = create_app(db_url)  # a second start: migrations already applied
    with TestClient(app) as client:
        lim = {x["name"]: x for x in client.get("/limits", headers={"X-API-Key": key}).json()}
    assert lim["bias_lsb"]["fail"] == 6


def test_openapi_describes_every_answer(api):
    """Every API route declares its success answer: a JSON schema (a response model), or the media
    type of what it sends instead (CSV, PDF, HTML, server-sent events); its refusals too."""
    spec = api.get("/openapi.json", role=None).json()
    seen = 0
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            ok = [c for c in op["responses"] if c.startswith("2")]
            assert len(ok) == 1, (method, path)
            body = op["responses"][ok[0]].get("content") or {}
            assert body, (method, path, "no content described")
            for media, desc in body.items():
                schema = desc.get("schema") or {}
                if media == "application/json":
                    assert schema and schema != {}, (method, path, "JSON without a schema")
                    assert "$ref" in schema or "items" in schema, (method, path, schema)
                else:
                    assert schema.get("type") == "string", (method, path, media)
            if path != "/health":
                assert {"404", "422"} <= set(op["responses"]), (method, path)
            seen += 1
    assert seen >= 28
    pdf = spec["paths"]["/calibrations/{cal_id}/certificate.pdf"]["get"]["responses"]["200"]["content"]
    assert pdf["application/pdf"]["schema"]["format"] == "binary"


def test_admins_list_create_and_revoke_keys_over_the_api(api):
    """``/keys`` (admin): a list without secrets, a new key shown once, a revocation that takes
    effect at once in this process, audited; the last admin key cannot be revoked."""
    assert api.get("/keys", role="operator").status_code == 403
    listed = api.get("/keys").json()
    assert {k["owner"] for k in listed} == {"viewer-user", "operator-user", "admin-user"}
    assert all(set(k) == {"id", "prefix", "owner", "role", "revoked", "created_at"} for k in listed)
    r = api.post("/keys", json={"owner": "carol", "role": "viewer"})
    assert r.status_code == 201 and r.json()["key"].startswith(r.json()["prefix"])
    carol = r.json()
    assert api.client.get("/limits", headers={"X-API-Key": carol["key"]}).status_code == 200
    r = api.delete(f"/keys/{carol['id']}")
    assert r.status_code == 200 and r.json()["revoked"] is True
    assert api.client.get("/limits", headers={"X-API-Key": carol["key"]}).status_code == 401
    assert api.post("/keys", json={"owner": "dave", "role": "boss"}).json()["detail"][0]["field"] == "body.role"
    assert api.delete("/keys/9999").status_code == 404
    admin = next(k for k in listed if k["role"] == "admin")
    r = api.delete(f"/keys/{admin['id']}")
    assert r.status_code == 409 and "last admin key" in r.json()["detail"]
    from sqlalchemy import select

    from service.db import AuditLog
    with api.client.app.state.sessions() as s:
        actions = [a.action for a in s.scalars(select(AuditLog).where(AuditLog.action.like("key.%")))]
    assert actions == ["key.create", "key.revoke"]


def test_an_import_is_exported_as_it_came_extra_columns_and_every_digit(api):
    """RECORDING.md: extra columns are kept; an export is what was stored, at full precision."""
    text = ("# compasscal-recording: 1\n# serial: SN-X\nt,step,psi_t,theta_t,phi_t,mx,my,mz,ax,ay,az,temp_c,lux,note\n"
            + "".join(f"{i * 0.0501234567:.10f},level,{i * 1.000001},0,0,{1000.123456789 + i},-2000.5,300.25,,,,"
                      f"21.123456,{i * 7},n{i}\n" for i in range(30)))
    r = api.post("/recordings", role="operator", content=text.encode())
    assert r.status_code == 201, r.text
    back = api.get(f"/runs/{r.json()['id']}/samples", role="viewer").text
    from physics.recording import parse_recording
    a, b = parse_recording(text), parse_recording(back)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.mag, b.mag) and np.array_equal(a.psi_t, b.psi_t)
    assert np.array_equal(a.temp_c, b.temp_c)
    assert b.extra == {"lux": [str(i * 7) for i in range(30)], "note": [f"n{i}" for i in range(30)]}


def test_a_limit_without_its_figure_is_said_beside_the_verdict() -> None:
    """A calibration that gives no figure for a limit (the twelve-position method's tilted heading) was
    certified PASS with "every figure within its marginal limit" beside that limit "not judged": the
    reasons say which limit the verdict does not cover, and the verdict stands on the others."""
    from service.db import Limit
    from service.store import judge

    limits = [Limit(name="heading_error_level_deg", marginal=0.02, fail=0.05, unit="deg"),
              Limit(name="heading_error_tilted_deg", marginal=0.05, fail=0.1, unit="deg")]
    verdict, reasons = judge({"heading_error_level_deg": 0.01, "heading_error_tilted_deg": None}, limits)
    assert verdict == "PASS" and reasons == ["heading_error_tilted_deg not judged: this calibration gives no figure for it "
                                             "(the verdict covers the other limits)"]
    assert judge({"heading_error_level_deg": 0.03, "heading_error_tilted_deg": 0.01}, limits) == (
        "MARGINAL", ["heading_error_level_deg 0.03 deg above the marginal limit 0.02"])
