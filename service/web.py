"""The web pages under ``/ui/`` and the calibration certificates (HTML and PDF).

Server-rendered Jinja2 templates with a little vanilla JavaScript for the live parts (the run's
server-sent events, station states, the live sample plot), all served from this machine: no CDN,
no web font, plots as inline SVG drawn by matplotlib. The OpenAPI's ``/docs`` too: its Swagger UI
is vendored in static/ (THIRD_PARTY.md), so every page works on a machine without internet.

Authentication: a page accepts the ``X-API-Key`` header (scripts, tests) or the browser-session
cookie :data:`service.auth.COOKIE` that ``POST /ui/login`` sets (HttpOnly, SameSite=Strict, no
expiry). A page without either redirects to the login form; the JavaScript calls the JSON API with
the same cookie, so the API's own role checks apply to every action.
"""

from __future__ import annotations

import asyncio
import math
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import parse_qs, quote, urlencode

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from pydantic import AfterValidator, Field
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from physics.calibration import Calibration as PhysCalibration
from physics.recording import Recording
from procedures.calibrate import parameters_said
from procedures.states import ACTIVE
from service import plots
from service.auth import COOKIE, ROLES, SESSION_HOURS, Caller, caller_of, end_session, require, start_session
from service.db import Analysis, Batch, Calibration, Device, Limit, Run, RunEvent, Sample, Station
from service.identity import CHOICES, check_serial, is_serial_prompt
from service.schemas import Id, Index, Serial, no_nul
from service.runtime import NOT_RUN, VERDICTS, runs_of_serial, summary_verdict, unit_serial
from service.store import limit_result, load_recording

HERE = Path(__file__).parent
templates = Jinja2Templates(directory=str(HERE / "templates"))
# a serial prompt's answer buttons (run and batch pages; static/common.js draws the same live)
templates.env.globals.update(is_serial_prompt=is_serial_prompt, serial_choices=CHOICES)
STATIC = HERE / "static"
#: What /ui/static serves (a fixed list: nothing else under the package is reachable).
STATIC_TYPES = {".css": "text/css; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".svg": "image/svg+xml", ".ico": "image/x-icon"}
#: Swagger UI for /docs, vendored from the npm package swagger-ui-dist (Apache-2.0; see
#: static/THIRD_PARTY.md): FastAPI's default loads it from a CDN, a blank page offline.
SWAGGER_UI_VERSION = "5.35.0"
SWAGGER_JS = "swagger-ui-bundle.js"
SWAGGER_CSS = "swagger-ui.css"
#: Rows per poll of the live sample plot (a long run is fetched in pieces, never all at once).
LIVE_ROWS = 5000

router = APIRouter(include_in_schema=False)
#: What the search box takes: a serial number or a part of one (no NUL). A query longer than a serial
#: matches none and is told why in the API's words (check_serial); beyond SEARCH_MAX it is no query.
SEARCH_MAX = 1000
SerialPart = Annotated[str, AfterValidator(no_nul), Field(max_length=SEARCH_MAX)]


# ------------------------------------------------------------------------------------------ helpers

def _software_version() -> str:
    from service.runtime import SOFTWARE_VERSION
    return SOFTWARE_VERSION


def _safe_next(target: str | None) -> str:
    """Where to go after the login: a path on this site only (never ``//host`` or ``http://``)."""
    if target and target.startswith("/") and not target.startswith("//") and "\\" not in target:
        return target
    return "/ui/stations"


def _caller(request: Request) -> Caller | None:
    return caller_of(request)  # the X-API-Key header, else the web session of the cookie


def _page_caller(request: Request, role: str = "viewer") -> Caller | Response:
    """The caller of a page, or the response to send instead: a redirect to the login form
    without a valid key (303, keeping where they wanted to go), a 403 page with too low a role."""
    caller = _caller(request)
    if caller is None:
        target = request.url.path + (f"?{request.url.query}" if request.url.query else "")
        return RedirectResponse("/ui/login?" + urlencode({"next": target}), status_code=303)
    if ROLES.index(caller.role) < ROLES.index(role):
        return _error_page(request, caller, 403, "Not allowed",
                           f"This page needs the {role} role; the key of {caller.owner} is {caller.role}.")
    return caller


def _render(request: Request, caller: Caller | None, name: str, status_code: int = 200, **ctx: Any) -> HTMLResponse:
    base = {"caller": caller, "operator": bool(caller and ROLES.index(caller.role) >= ROLES.index("operator")),
            "version": _software_version()}
    return templates.TemplateResponse(request, name, {**base, **ctx}, status_code=status_code)


def _error_page(request: Request, caller: Caller | None, status: int, title: str, message: str) -> HTMLResponse:
    return _render(request, caller, "error.html", status_code=status, title=title, message=message, status=status)


def invalid_page(request: Request, message: str) -> HTMLResponse:
    """A page's address the pages cannot read (an id that is no number, a NUL): 422, as a page."""
    who = _page_caller(request)
    return _error_page(request, who if isinstance(who, Caller) else None, 422, "Not a page address", message)


def _when(dt: datetime | None) -> str:
    """A stored (naive UTC) time as people read it."""
    if dt is None:
        return ""
    if dt.tzinfo is not None:
        dt = dt.astimezone(timezone.utc).replace(tzinfo=None)
    return dt.strftime("%Y-%m-%d %H:%M:%S UTC")


templates.env.filters["when"] = _when


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return float("nan")
    return f


def pm(value: Any, sigma: Any, digits: int) -> str:
    """``value ± sigma`` with ``digits`` decimals; the sigma is left out when unknown."""
    v, s = _num(value), _num(sigma)
    if not math.isfinite(v):
        return "-"
    return f"{v:.{digits}f} ± {s:.{digits}f}" if math.isfinite(s) else f"{v:.{digits}f}"


#: Decimals of an acceptance figure by its limit's unit. A figure's value and its two limits share
#: them, and so does every row of a unit: the columns line up (never 0.016 next to 0.009694).
UNIT_DECIMALS = {"deg": 4, "ratio": 4, "LSB": 1}


def limit_decimals(unit: str, marginal: Any) -> int:
    """The decimals of a figure with this unit (another unit: enough for 3 digits of its marginal limit)."""
    if unit in UNIT_DECIMALS:
        return UNIT_DECIMALS[unit]
    m = abs(_num(marginal))
    return 3 if not math.isfinite(m) or m == 0 else min(6, max(0, 2 - math.floor(math.log10(m))))


def fixed(v: Any, decimals: int) -> str:
    """A number in fixed point with ``decimals`` decimals; "-" when there is none."""
    f = _num(v)
    return f"{f:.{decimals}f}" if math.isfinite(f) else "-"


# ------------------------------------------------------------------------------ calibration views

AXES = ("x_m", "y_m", "z_m")


def calibration_tables(cal: PhysCalibration) -> dict[str, Any]:
    """The paper's Table 1 (angles between sensor and body axes, deg) and Table 2 (sensitivities,
    biases, residual rms, LSB) as rows of strings with 1-sigma, plus the field and base tilt lines."""
    sig = cal.sigma
    ang = cal.mag.angles_deg
    s_ang = np.asarray(sig.get("angles_deg") if sig.get("angles_deg") is not None else np.full((3, 3), np.nan), float)
    s_k = np.asarray(sig.get("k") if sig.get("k") is not None else np.full(3, np.nan), float)
    s_b = np.asarray(sig.get("bias") if sig.get("bias") is not None else np.full(3, np.nan), float)
    rms = list((cal.quality or {}).get("residual_rms_lsb") or [None] * 3) + [None] * 3
    table1 = [[name, *(pm(ang[i, j], s_ang[i, j], 4) for j in range(3))] for i, name in enumerate(AXES)]
    table2 = [[name, pm(cal.mag.k[i], s_k[i], 3), pm(cal.mag.bias[i], s_b[i], 3),
               "-" if rms[i] is None or not np.isfinite(float(rms[i])) else f"{float(rms[i]):.2f}"]  # (nan: no model residual)
              for i, name in enumerate(AXES)]
    return {"table1": table1, "table2": table2}


def field_lines(cal: PhysCalibration, data: dict[str, Any]) -> list[str]:
    """The field (I, D) and the base tilt with their 1-sigma, as lines of text."""
    sig = cal.sigma
    tilt_sigma = data.get("base_tilt_sigma_deg") or [None, None]
    tilt = cal.base_tilt_deg
    lines = [f"Field inclination I = {pm(cal.inclination_deg, sig.get('inclination_deg'), 4)} deg",
             f"Field declination D = {pm(cal.declination_deg, sig.get('declination_deg'), 4)} deg "
             "(from the table's azimuth zero mark)",
             f"Base tilt about x = {pm(tilt[0], tilt_sigma[0], 4)} deg, about y = {pm(tilt[1], tilt_sigma[1], 4)} deg"]
    if cal.heading_model:
        lines.append(f"Heading model: {cal.heading_model.get('kind')}")
    return lines


def staged_rows(cal: PhysCalibration) -> list[list[str]]:
    """The staged heading errors the fit scored on the recording (max |error|, deg)."""
    he = (cal.quality or {}).get("heading_error_deg") or {}
    labels = {"raw": "raw", "bias": "bias removed", "sensitivity": "+ sensitivity", "full": "+ non-orthogonality (full)",
              "tilted_full": "full, pitch and roll up to ±60 deg"}
    return [[label, f"{float(he[k]):.4f}"] for k, label in labels.items() if he.get(k) is not None]


def limits_of(session: Session) -> list[Limit]:
    """The acceptance limits, by name."""
    return list(session.scalars(select(Limit).order_by(Limit.name)))


def judged_limits(session: Session, row: Calibration) -> list[Limit]:
    """The limits ``row``'s verdict was judged against (kept with it), or, for a calibration stored
    before they were kept, today's."""
    if row.limits is None:
        return limits_of(session)
    return [Limit(name=d["name"], marginal=d["marginal"], fail=d["fail"], unit=d["unit"], description=d.get("description", ""))
            for d in row.limits]


def limit_pairs(limits: list[Limit]) -> dict[str, tuple[float, float]]:
    """(marginal, fail) by limit name, for the plots."""
    return {lim.name: (lim.marginal, lim.fail) for lim in limits}


def unit_view(row: Calibration, rec: Recording | None, limits: list[Limit], curves: bool = True) -> dict[str, Any]:
    """Everything a page shows of one stored calibration: tables, field, verdict, and the curves
    as inline SVG (the staged level turn and the tilted poses, see service.plots)."""
    cal = PhysCalibration.from_json(row.data)
    view: dict[str, Any] = {
        "id": row.id, "slot": row.slot, "serial": row.device.serial, "model": row.device.model,
        "firmware": row.device.firmware, "verdict": row.verdict, "status": row.status,
        "reasons": list(row.reasons or []), "method": row.method, "created_at": row.created_at,
        **calibration_tables(cal), "field": field_lines(cal, row.data), "staged": staged_rows(cal),
        "notes": list(cal.notes), "has_recording": rec is not None, "identity": row.identity,
    }
    if curves:
        pairs = limit_pairs(limits)
        view["staged_svg"] = plots.svg(plots.staged_figure(cal, rec, pairs), "staged-curve",
                                       f"Staged heading error of {row.device.serial} over a level turn")
        view["tilted_svg"] = plots.svg(plots.tilted_figure(cal, rec, pairs), "tilted-curve",
                                       f"Heading error of {row.device.serial} at pitch and roll up to 60 deg")
        fig = plots.precision_figure((cal.quality or {}).get("precision") or {})
        if fig is not None:
            view["precision_svg"] = plots.svg(fig, "precision-curve",
                                              f"Predicted heading error of {row.device.serial} as poses were added")
    return view


def limit_rows(limits: list[Limit], figures: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Each acceptance limit with this calibration's figure and how it fared."""
    out = []
    for lim in limits:
        value = (figures or {}).get(lim.name)
        result = limit_result(value, lim) or "not judged"
        d = limit_decimals(lim.unit, lim.marginal)
        out.append({"name": lim.name, "description": lim.description or lim.name, "value": value,
                    "value_text": fixed(value, d), "marginal": lim.marginal, "marginal_text": fixed(lim.marginal, d),
                    "fail": lim.fail, "fail_text": fixed(lim.fail, d), "unit": lim.unit, "result": result})
    return out


#: How a differing serial was settled, in a few words (the certificate's line is short).
SERIAL_DECISIONS = {"trust-typed": "certified as typed (serial policy trust-typed)",
                    "typed": "certified as typed, on the operator's answer",
                    "identified": "certified as identified, on the operator's answer"}


def identity_rows(identity: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The certificate's lines on which unit it is: the serial the unit reported (or that it reported
    none) and, when it differs from the one typed, the typed one and how that was settled. None for a
    calibration stored before units were identified."""
    if not identity:
        return []
    typed, identified = identity.get("typed_serial"), identity.get("identified_serial")
    rows = [("Identified serial", identified or "not identified (the unit reported no serial number)")]
    if identified and typed and typed != identified:
        decision = identity.get("serial_decision")
        rows = [("Serial typed", typed), rows[0],
                ("Serial decision", SERIAL_DECISIONS.get(str(decision), str(decision or "-")))]
    return rows


def certificate_context(session: Session, row: Calibration) -> tuple[dict[str, Any], PhysCalibration, Recording | None, list[Limit]]:
    """The certificate's content (shared by the HTML page and the PDF), the calibration, its
    recording (None when the samples are gone) and the limits."""
    run = row.run
    cal = PhysCalibration.from_json(row.data)
    rec = load_recording(session, run, row.slot) if run is not None else None
    limits = judged_limits(session, row)
    snap = (run.station_snapshot if run is not None else None) or {}
    compasses = snap.get("compasses") or []
    slot_url = compasses[row.slot] if row.slot < len(compasses) else None
    dev = row.device
    info = [
        ("Unit serial number", dev.serial), *identity_rows(row.identity),
        ("Model", dev.model or "-"), ("Firmware", dev.firmware or "-"),
        ("Calibration date", _when(row.created_at)), ("Operator", run.operator if run else "-"),
        ("Station", snap.get("name") or ((run.meta or {}).get("station") if run else None) or "-"),
        ("Turntable (Modbus)", snap.get("modbus") or "-"),
        ("Fixture slot", f"{row.slot}" + (f" ({slot_url})" if slot_url else "")),
        ("Run", f"{run.id}, {run.status}" if run else "-"),
        *([("Resumes run", f"{resumed}: its samples up to its last checkpoint, taken over by run {run.id}")]
          if run is not None and (resumed := ((run.meta or {}).get("resume") or {}).get("run_id")) else []),
        ("Procedure", f"{run.procedure} version {run.procedure_version}" if run else "-"),
        ("Method", row.method),
        ("Software", f"compasscal {run.software_version}" if run else "-"),
        ("Certificate issued by", f"compasscal {_software_version()}"),
    ]
    cert = {
        "id": row.id, "run_id": row.run_id, "number": f"CC-{row.id:06d}", "serial": dev.serial, "model": dev.model,
        "firmware": dev.firmware, "verdict": row.verdict, "status": row.status, "reasons": list(row.reasons or []),
        "info": info, **calibration_tables(cal), "field": field_lines(cal, row.data), "staged": staged_rows(cal),
        "notes": list(cal.notes), "limits": limit_rows(limits, row.figures), "software_version": _software_version(),
        # issued when the calibration was stored: every copy of one certificate (page, PDF, a reprint) says the same
        "issued": _when(row.created_at),
        "parameters": parameters_said((run.parameters if run else {}) or {}),
        "snapshot": snap, "identity": row.identity,
    }
    return cert, cal, rec, limits


# ------------------------------------------------------------------------------------- run views

def describe_step(d: dict[str, Any]) -> str:
    """A ``step`` event as the run page's status line says it (static/run.js describeStep, same words)."""
    if d.get("warning"):
        return f"warning: {d['warning']}"
    if d.get("retry"):
        return f"retry {d['retry']}: {d.get('reason') or ''}"
    step = d.get("step")
    if not isinstance(step, dict):
        return ""

    def deg(v: Any) -> str:
        return f"{v:.1f}" if isinstance(v, (int, float)) else str(v)
    kind = step.get("kind")
    if kind == "move":
        return f"move to ψ {deg(step.get('psi'))}°, θ {deg(step.get('theta'))}°, φ {deg(step.get('phi'))}°"
    if kind == "acquire":
        return f"acquire {step.get('step') or ''} ({step.get('samples')} samples)"
    if kind == "settle":
        return f"settle {step.get('seconds')} s"
    if kind == "compute":
        pct = step.get("percent")
        how = f": {step.get('stage') or ''} {pct:.0f} %" if isinstance(pct, (int, float)) else ""
        return f"computing the {step.get('label') or ''}{how}"
    return {"prompt": "waiting for the operator", "checkpoint": "checkpoint",
            "identify": "identifying the units", "where": "reading where the table stands"}.get(str(kind), str(kind or ""))


def step_view(session: Session, run_id: int) -> tuple[str, str | None]:
    """The run's last step (checkpoints aside), described, and the label of its last acquisition
    (the step whose samples the live plot shows), from the run's event log ("" and None before any step)."""
    last, label = "", None
    # newest first; a few hundred events reach back past any retry or warning to the last steps
    rows = session.scalars(select(RunEvent.data).where(RunEvent.run_id == run_id, RunEvent.kind == "step")
                           .order_by(RunEvent.id.desc()).limit(500))
    for d in rows:
        step = d.get("step") if isinstance(d, dict) else None
        if not isinstance(step, dict):
            continue
        if not last and step.get("kind") != "checkpoint":  # a checkpoint only marks where a pause may hold
            last = describe_step(d)
        if step.get("kind") == "acquire" and step.get("step"):
            label = str(step["step"])
            break
    return last, label


def wall_seconds_left(progress: dict[str, Any], time_scale: float) -> float | None:
    """The run's estimate of the time left in wall-clock seconds: the progress event's ``left_wall_s``,
    or (an event from before that field) its table seconds ``left_s`` over the station's time scale."""
    if isinstance(progress.get("left_wall_s"), (int, float)):
        return float(progress["left_wall_s"])
    if isinstance(progress.get("left_s"), (int, float)):
        return float(progress["left_s"]) / (time_scale or 1.0)
    return None


# ------------------------------------------------------------------------------------ login/out

@router.get("/ui", response_class=HTMLResponse)
@router.get("/ui/", response_class=HTMLResponse)
def ui_root() -> Response:
    """The pages start at the stations."""
    return RedirectResponse("/ui/stations", status_code=303)


@router.get("/ui/login", response_class=HTMLResponse)
def login_form(request: Request, next: str | None = None) -> Response:
    """The login form: one API key, kept for the browser session."""
    return _render(request, _caller(request), "login.html", title="Log in", next=_safe_next(next), error=None,
                   session_hours=SESSION_HOURS)


@router.post("/ui/login", response_class=HTMLResponse)
async def login(request: Request) -> Response:
    """Check the key; on success set the session cookie and go on (303)."""
    # parsed by hand: a urlencoded form needs no python-multipart
    form = parse_qs((await request.body()).decode("utf-8", "replace"))
    key = (form.get("key") or [""])[0].strip()
    target = _safe_next((form.get("next") or [None])[0])

    def check() -> tuple[str, Caller] | None:
        with request.app.state.sessions() as session:
            return start_session(session, key)
    started = await asyncio.to_thread(check) if key else None
    if started is None:
        return _render(request, None, "login.html", status_code=401, title="Log in", next=target,
                       error="That key is not valid (unknown or revoked).", session_hours=SESSION_HOURS)
    resp = RedirectResponse(target, status_code=303)
    # the cookie carries a session token (never the key), expiring with the session; HttpOnly keeps it
    # from page scripts, Secure from plain HTTP when the service is reached over HTTPS
    https = request.url.scheme == "https" or request.headers.get("x-forwarded-proto", "").lower() == "https"
    resp.set_cookie(COOKIE, started[0], httponly=True, samesite="strict", path="/", secure=https,
                    max_age=SESSION_HOURS * 3600)
    return resp


@router.post("/ui/logout")
def logout(request: Request) -> Response:
    """End this browser's session (its token stops working at once) and forget the cookie."""
    token = request.cookies.get(COOKIE)
    if token:
        with request.app.state.sessions() as session:
            end_session(session, token)
        getattr(request.app.state, "key_cache", {}).pop(token, None)
    resp = RedirectResponse("/ui/login", status_code=303)
    resp.delete_cookie(COOKIE, path="/", httponly=True, samesite="strict")
    return resp


@router.get("/ui/static/{name}")
def static(name: str) -> Response:
    """The pages' own CSS and JavaScript (no external resources anywhere)."""
    path = STATIC / name
    kind = STATIC_TYPES.get(path.suffix)
    if "/" in name or name.startswith(".") or kind is None or not path.is_file():
        raise HTTPException(404, f"no static file {name!r}")
    return FileResponse(path, media_type=kind, headers={"Cache-Control": "no-cache"})


@router.get("/favicon.ico")
def favicon() -> Response:
    """The site's icon where browsers look for it unasked (pages without an icon link, e.g. the
    analysis report opened from the service): a 404 otherwise, in every log and console."""
    return FileResponse(STATIC / "favicon.ico", media_type=STATIC_TYPES[".ico"],
                        headers={"Cache-Control": "max-age=86400"})


@router.get("/docs", response_class=HTMLResponse)
def api_docs(request: Request) -> HTMLResponse:
    """The OpenAPI as Swagger UI, with its script and style from this package (service/static,
    swagger-ui-dist SWAGGER_UI_VERSION), never from a CDN: the page works without internet. Open,
    like /openapi.json; the calls made from it need a key (the Authorize button, X-API-Key)."""
    root = request.scope.get("root_path", "")
    return get_swagger_ui_html(
        openapi_url=root + (request.app.openapi_url or "/openapi.json"), title=f"{request.app.title} - API",
        swagger_js_url=f"{root}/ui/static/{SWAGGER_JS}", swagger_css_url=f"{root}/ui/static/{SWAGGER_CSS}",
        swagger_favicon_url=f"{root}/ui/static/favicon.svg",
        # no spec validator badge: Swagger UI would fetch it from validator.swagger.io
        swagger_ui_parameters={"validatorUrl": None})


# ---------------------------------------------------------------------------------------- pages

@router.get("/ui/search", response_class=HTMLResponse)
def search(request: Request, serial: SerialPart = "") -> Response:
    """A serial number: its device page; a part of one: the matches (straight there when one)."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    q = serial.strip()
    if not q:
        return RedirectResponse("/ui/stations", status_code=303)
    with request.app.state.sessions() as s:
        if s.scalar(select(Device.id).where(Device.serial == q)) is None:
            needle = q.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
            found = list(s.scalars(select(Device.serial).where(func.lower(Device.serial).like(f"%{needle.lower()}%", escape="\\"))
                                   .order_by(Device.serial).limit(100)))
            if len(found) == 1:
                q = found[0]
            elif found:
                return _render(request, who, "search.html", title=f"Search {q}", query=q, found=found)
            else:
                try:
                    check_serial(q)
                except ValueError as e:  # no device page could hold it (a '/' would not even reach one)
                    return _render(request, who, "search.html", title=f"Search {q}", query=q, found=[],
                                   problem=str(e))
    return RedirectResponse(f"/ui/devices/{quote(q, safe='')}", status_code=303)


@router.get("/ui/stations", response_class=HTMLResponse)
def stations_page(request: Request) -> Response:
    """Every station with its live state and current run; operators can start a run."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    from procedures.calibrate import BATCH, PROCEDURES
    from service.runtime import run_json

    with request.app.state.sessions() as s:
        rows = s.scalars(select(Station).order_by(Station.name)).all()
        stations = [{"name": r.name, "state": r.state, "run_id": r.run_id, "batch_id": r.batch_id,
                     "fault": r.reason, "slots": len(r.compasses or []), "modbus": r.modbus} for r in rows]
        runs = [run_json(r) for r in s.scalars(select(Run).order_by(Run.created_at.desc(), Run.id.desc()).limit(20))]
    # the form sends the samples only: a procedure that needs more (evaluate's calibrations) is started over the
    # API, not offered here to fail with "body.parameters.calibrations: Field required"
    procs = [{"name": p.name, "description": p.doc} for name, p in PROCEDURES.items()
             if name != BATCH and not any(f.is_required() for f in p.params.model_fields.values())]
    return _render(request, who, "stations.html", title="Stations", stations=stations, runs=runs, procedures=procs)


@router.get("/ui/runs/{run_id}", response_class=HTMLResponse)
def run_page(request: Request, run_id: Id) -> Response:
    """A run: live progress while it runs, then each unit's tables, curves and verdict."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    from service.runtime import run_json

    with request.app.state.sessions() as s:
        row = s.get(Run, run_id)
        if row is None:
            return _error_page(request, who, 404, "No such run", f"There is no run {run_id}.")
        run = run_json(row)
        active = run["status"] in ACTIVE
        units: list[dict[str, Any]] = []
        errors: list[dict[str, Any]] = []
        evaluations: list[dict[str, Any]] = []
        if not active:
            cals = s.scalars(select(Calibration).where(Calibration.run_id == run_id).order_by(Calibration.slot)).all()
            for c in cals:
                units.append(unit_view(c, load_recording(s, row, c.slot), judged_limits(s, c)))
            stored = {str(c.slot) for c in cals}
            for slot, entry in sorted(((run["result"] or {}).get("units") or {}).items()):
                if slot not in stored and isinstance(entry, dict) and "calibration_id" not in entry:
                    said = (entry.get("result") or {}) if "error" not in entry else {}
                    if "level_max_deg" in said:  # an evaluation: its figures (the page said "no calibration")
                        evaluations.append({"slot": slot, "serial": entry.get("serial", ""), **said,
                                            "warning": entry.get("warning")})
                        continue
                    # a unit not certified goes by the serial it reported (its samples do), the typed one beside it
                    errors.append({"slot": slot, "serial": entry.get("serial", ""),
                                   "identified": entry.get("identified_serial") or "",
                                   "error": entry.get("error") or "no calibration from this slot"})
        # what each unit reported, by slot, shown next to the serial typed; a run that ended without results (aborted
        # at its serial prompt) keeps its units' identities alone, and its page showed none
        result = run["result"] or {}
        identities = {str(k): e for k, e in {**(result.get("identities") or {}), **(result.get("units") or {})}.items()
                      if isinstance(e, dict) and "identification" in e}
        progress = run["progress"] or {}
        if run["status"] == "completed":
            percent = 100.0
        else:
            percent = float(progress.get("percent") or 0.0)
        snap = row.station_snapshot or {}
        time_scale = float(snap.get("time_scale") or 1.0)
        last_step, live_step = step_view(s, run_id)
        # an ended run's samples, by slot: to download, and drawn where no calibration shows them (a run that
        # failed or was aborted keeps what it measured; the page showed neither)
        recorded = []
        if not active and row.samples_count:
            drawn = {u["slot"] for u in units}
            for slot in s.scalars(select(Sample.slot).where(Sample.run_id == run_id).distinct().order_by(Sample.slot)):
                rec = load_recording(s, row, slot) if slot not in drawn else None
                recorded.append({"slot": slot, "serial": unit_serial(row, slot), "samples": len(rec) if rec else None,
                                 "svg": plots.svg(plots.samples_figure(rec), "samples-plot",
                                                  f"Samples of run {run_id}, slot {slot}, against time") if rec else ""})
        from service.routes.analyses import analysis_summary
        analyses = [analysis_summary(a) for a in s.scalars(select(Analysis).where(Analysis.run_id == run_id).order_by(Analysis.id))]
    return _render(request, who, "run.html", title=f"Run {run_id}", run=run, active=active, units=units,
                   errors=errors, evaluations=evaluations, identities=identities, percent=percent, time_scale=time_scale, last_step=last_step, live_step=live_step,
                   left_wall_s=(wall_seconds_left(progress, time_scale) if active else 0.0), analyses=analyses,
                   recorded=recorded)


@router.get("/ui/runs/{run_id}/samples.json")
def live_samples(request: Request, run_id: Id, slot: Index = 0, after: int = Query(0, ge=0, le=2**63 - 1),
                 _: Caller = Depends(require("viewer"))) -> JSONResponse:
    """The samples of a run's slot stored after sample id ``after`` (at most LIVE_ROWS), for the
    live plot: ``{"last": id, "more": bool, "rows": [[step, psi_t, theta_t, phi_t, mx, my, mz], ...]}``.
    Always 200 for a known run (no samples yet is an empty list), unlike the CSV's 404."""
    with request.app.state.sessions() as s:
        if s.get(Run, run_id) is None:
            raise HTTPException(404, f"no run {run_id}")
        rows = s.execute(select(Sample.id, Sample.step, Sample.psi_t, Sample.theta_t, Sample.phi_t, Sample.mx,
                                Sample.my, Sample.mz).where(Sample.run_id == run_id, Sample.slot == slot, Sample.id > after)
                         .order_by(Sample.id).limit(LIVE_ROWS)).all()
    last = rows[-1][0] if rows else after
    return JSONResponse({"last": last, "more": len(rows) == LIVE_ROWS,
                         "rows": [[r[1], *(None if v is None else round(float(v), 4) for v in r[2:])] for r in rows]})


#: Runs a unit's page lists (newest first); GET /runs?serial= pages through all of them.
DEVICE_RUNS_LISTED = 200


@router.get("/ui/devices/{serial}", response_class=HTMLResponse)
def device_page(request: Request, serial: Serial) -> Response:
    """A unit's calibration history (newest first) and its trends, each with its certificate."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    with request.app.state.sessions() as s:
        dev = s.scalar(select(Device).where(Device.serial == serial))
        # every run that named the unit (typed, reported by it, or certified under it): a unit whose
        # calibration failed has runs and no certificate, and its page was a 404 the run pages linked to
        runs = [{"id": r.id, "created_at": r.created_at, "procedure": r.procedure, "status": r.status,
                 "reason": r.reason or "", "batch_id": r.batch_id}
                for r in s.scalars(select(Run).where(runs_of_serial(serial))
                                   .order_by(Run.created_at.desc(), Run.id.desc()).limit(DEVICE_RUNS_LISTED))]
        if dev is None and not runs:
            return _error_page(request, who, 404, "Unknown serial number",
                               f"No run of this service has named serial number {serial!r}, and no device is "
                               "certified under it.")
        rows = s.scalars(select(Calibration).where(Calibration.device_id == dev.id)
                         .order_by(Calibration.created_at.desc(), Calibration.id.desc())).all() if dev else []
        history = [{"id": c.id, "run_id": c.run_id, "created_at": c.created_at, "status": c.status,
                    "verdict": c.verdict, "reasons": list(c.reasons or []), "method": c.method,
                    "figures": c.figures or {}, "data": c.data} for c in rows]
        device = ({"serial": dev.serial, "model": dev.model, "firmware": dev.firmware, "created_at": dev.created_at}
                  if dev else {"serial": serial, "model": None, "firmware": None, "created_at": None})
        # each figure's column in one fixed-point format, the certificate's (never 0.016 above 0.009694)
        decimals = {lim.name: limit_decimals(lim.unit, lim.marginal) for lim in limits_of(s)}
    for h in history:
        h["figure_texts"] = {k: fixed(v, decimals.get(k, 4)) for k, v in h["figures"].items()}
    trends: dict[str, str] = {}
    if history:
        labels = {"sensitivity": "Sensitivities over time", "bias": "Biases over time",
                  "misalignment": "Misalignment angles over time", "heading": "Heading error over time"}
        for key, fig in plots.trend_figures(history).items():
            trends[key] = plots.svg(fig, f"trend trend-{key}", f"{labels[key]} of {serial}")
    current = next((h for h in history if h["status"] == "current"), None)
    return _render(request, who, "device.html", title=f"Device {serial}", device=device, history=history,
                   trends=trends, current=current, runs=runs, runs_listed=DEVICE_RUNS_LISTED)


#: Batches the batches page lists (newest first); older ones stay reachable by their own page.
BATCHES_LISTED = 200


def batch_rows(session: Session, limit: int = BATCHES_LISTED) -> list[dict[str, Any]]:
    """The newest batches for the list: station, status, units done of all, verdict counts."""
    rows = session.execute(select(Batch, Station.name).join(Station, Station.id == Batch.station_id, isouter=True)
                           .order_by(Batch.created_at.desc(), Batch.id.desc()).limit(limit)).all()
    out = []
    for b, station in rows:
        summary = {str(k): str(v) for k, v in (b.summary or {}).items()}
        # by the verdict a line begins with ("PASS (resumed as run 19)", "PASS (certified as SN-T)" were "other")
        counts = {v: sum(1 for r in summary.values() if summary_verdict(r) == v) for v in VERDICTS}
        out.append({"id": b.id, "station": station, "status": b.status, "operator": b.operator,
                    # done: the units whose run ended, as the batch's page counts them (not those never run)
                    "units": len(b.serials or []), "done": sum(not v.startswith(NOT_RUN) for v in summary.values()),
                    "counts": counts,
                    "other": len(summary) - sum(counts.values()), "created_at": b.created_at,
                    "finished_at": b.finished_at})
    return out


@router.get("/ui/batches", response_class=HTMLResponse)
def batches_page(request: Request) -> Response:
    """Every batch, newest first, with its progress and verdicts; operators can start one."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    with request.app.state.sessions() as s:
        batches = batch_rows(s)
        stations = [{"name": r.name, "state": r.state, "busy": bool(r.run_id or r.batch_id) or r.state == "fault"}
                    for r in s.scalars(select(Station).order_by(Station.name))]
    return _render(request, who, "batches.html", title="Batches", batches=batches, stations=stations,
                   listed=BATCHES_LISTED)


@router.get("/ui/batches/{batch_id}", response_class=HTMLResponse)
def batch_page(request: Request, batch_id: Id) -> Response:
    """A batch: its progress and one row per unit with its verdict; prompts answerable."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    from service.runtime import batch_json

    with request.app.state.sessions() as s:
        batch = s.get(Batch, batch_id)
        if batch is None:
            return _error_page(request, who, 404, "No such batch", f"There is no batch {batch_id}.")
        b = batch_json(s, batch)
    done = sum(1 for u in b["units"] if u["status"] in ("completed", "failed", "aborted"))
    return _render(request, who, "batch.html", title=f"Batch {batch_id}", batch=b, done=done,
                   active=b["status"] in ("queued", "running", "aborting"))


@router.get("/ui/calibrations/{cal_id}/certificate", response_class=HTMLResponse)
def certificate_page(request: Request, cal_id: Id) -> Response:
    """The printable calibration certificate."""
    who = _page_caller(request)
    if isinstance(who, Response):
        return who
    with request.app.state.sessions() as s:
        row = s.get(Calibration, cal_id)
        if row is None:
            return _error_page(request, who, 404, "No such calibration", f"There is no calibration {cal_id}.")
        cert, cal, rec, limits = certificate_context(s, row)
    pairs = limit_pairs(limits)
    cert["staged_svg"] = plots.svg(plots.staged_figure(cal, rec, pairs), "staged-curve",
                                   f"Staged heading error of {cert['serial']} over a level turn")
    cert["tilted_svg"] = plots.svg(plots.tilted_figure(cal, rec, pairs), "tilted-curve",
                                   f"Heading error of {cert['serial']} at pitch and roll up to 60 deg")
    return _render(request, who, "certificate.html", title=f"Certificate {cert['number']}", cert=cert)


__all__ = ["router", "calibration_tables", "certificate_context", "unit_view", "pm"]
