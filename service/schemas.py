"""What the API takes and answers: every request body and every response, as pydantic models, so
OpenAPI (``/docs``) describes each route's answer. The routes (service/routes/) build answers
from the database rows with the view functions of service/runtime.py and service/routes/*.

Response models whose documents carry open-ended physics (a calibration's JSON, an analysis's
result) declare the fields the service adds and allow the rest (``extra="allow"``)."""

from __future__ import annotations

import math
import re
from collections import Counter
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

from drivers.modbus import BusURL
from drivers.station import hardware_key
from drivers.sim.config import MAX_TIME_SCALE
from procedures.steps import request_number
from service.identity import (CHOICES, SERIAL_MAX, SERIAL_PATTERN, SERIAL_RULE, SerialPolicy as _SerialPolicy,
                              check_serial)

#: A serial policy as typed: spaces and case do not matter ("Refuse"), as an operator's answer to a serial prompt.
SerialPolicy = Annotated[_SerialPolicy, BeforeValidator(lambda v: v.strip().lower() if isinstance(v, str) else v)]

# ------------------------------------------------------------------------------------------ errors


class FieldProblem(BaseModel):
    """One bad field of a request: its path (``body.parameters.samples``) and what is wrong."""

    field: str
    problem: str


class ErrorOut(BaseModel):
    """Every refusal: ``detail`` is a sentence, or for a 422 one entry per bad field."""

    detail: str | list[FieldProblem] | dict[str, Any]


#: The refusals every route may answer, for OpenAPI.
ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut, "description": "no or unknown API key"},
    403: {"model": ErrorOut, "description": "the key's role may not do this"},
    404: {"model": ErrorOut, "description": "no such resource"},
    409: {"model": ErrorOut, "description": "the resource's state forbids it now"},
    422: {"model": ErrorOut, "description": "bad input: each field and its problem"},
}

# ------------------------------------------------------------------------ what may be stored
# Every string and number a request brings is checked here, where it enters, against the column it
# ends in (service/db.py): SQLite does not enforce String(n) and takes 64-bit integers and NUL
# characters, PostgreSQL refuses them with an exception. Checked at the edge, both answer the same
# 422 naming the field, instead of a 500, or a run accepted that loses its calibration at the end.

#: The largest id, slot or offset: PostgreSQL's ``integer`` (SQLite would take more, PostgreSQL not).
INT32_MAX = 2**31 - 1
#: Longest station, limit or other name, and step label (``samples.step``); a serial number's: service.identity.
NAME_MAX, STEP_MAX = 64, 32
#: The most compass slots a station has (and so the most serials a run types).
MAX_SLOTS = 64
STATION_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]*$"
STATION_RULE = "1 to 64 letters, digits, '.', '_' or '-', starting with a letter or digit"


def no_nul(value: str) -> str:
    """Refuse a NUL character (PostgreSQL's text cannot hold one)."""
    if "\x00" in value:
        raise ValueError("contains a NUL character (\\x00)")
    return value


def check_station_name(value: str) -> str:
    """A station's name: :data:`STATION_RULE` (it names queues and files, and appears in URLs)."""
    if not re.fullmatch(STATION_PATTERN, no_nul(value)):
        raise ValueError(f"not a station name: {STATION_RULE}")
    return value


def _not_bool(value: Any) -> Any:
    # pydantic's lax mode reads true as 1: a boolean where a number belongs is a mistake, not a number
    if isinstance(value, bool):
        raise ValueError("a number is required, not true or false")
    return value


def unstorable(value: Any) -> str | None:
    """What in a request value (free-form objects included) no database column may hold: a NUL
    character in a string or key, an infinite or NaN number (Python's JSON parser reads ``Infinity``
    and ``NaN``). None when all is well, else the problem with where it is (``at ['x'][0]``)."""
    todo: list[tuple[Any, str]] = [(value, "")]
    while todo:  # a stack, not recursion: a deeply nested body must not exhaust the stack
        v, at = todo.pop()
        where = f" at {at}" if at else ""
        if isinstance(v, str):
            if "\x00" in v:
                return f"contains a NUL character (\\x00){where}"
        elif isinstance(v, float):
            if not math.isfinite(v):
                return f"numbers must be finite, not {v}{where}"
        elif isinstance(v, dict):
            for k, x in v.items():
                if isinstance(k, str) and "\x00" in k:
                    return f"contains a NUL character (\\x00) in a key{where}"
                todo.append((x, f"{at}[{k!r}]"))
        elif isinstance(v, (list, tuple)):
            todo.extend((x, f"{at}[{i}]") for i, x in enumerate(v))
    return None


#: A unit's serial number, wherever one enters (bodies, the recording's metadata, paths, queries).
Serial = Annotated[str, AfterValidator(check_serial), Field(
    description=f"a unit's serial number: {SERIAL_RULE}; spaces at either end are dropped. In a URL, "
                "percent-encode the space (%20), '#' (%23) and, in a query, '+' (%2B)",
    json_schema_extra={"minLength": 1, "maxLength": SERIAL_MAX, "pattern": SERIAL_PATTERN})]
#: A station's name (``stations.name``), in a body, a path or a query.
StationName = Annotated[str, AfterValidator(check_station_name), Field(
    min_length=1, max_length=NAME_MAX, description=f"a station's name: {STATION_RULE}",
    json_schema_extra={"pattern": STATION_PATTERN})]
#: Any other name or key a request may bring (a limit's name, a prompt's id, a status to filter by).
Name = Annotated[str, AfterValidator(no_nul), Field(min_length=1, max_length=NAME_MAX)]
#: A database id in a path or body: 1 to 2**31-1 (a larger one cannot exist; PostgreSQL would fail on it).
Id = Annotated[int, Field(ge=1, le=INT32_MAX, description="an id: 1 to 2147483647"), BeforeValidator(_not_bool)]
#: A fixture slot, an offset: 0 to 2**31-1.
Index = Annotated[int, Field(ge=0, le=INT32_MAX), BeforeValidator(_not_bool)]
#: A number of a request body: finite, and a number (not true/false, not a string of digits).
Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]

def _search_text(value: str) -> str:
    v = value.strip(" ")
    if not v or "\x00" in v:
        raise ValueError("a serial number to look for: some text, without NUL characters")
    return v


#: A serial number looked for (``GET /runs?serial=``): what a unit reported is found too where it is no serial
#: number by :data:`Serial`'s rule ("SN B/1": its runs could not be looked up by it).
SerialSearch = Annotated[str, Field(max_length=200, description="a serial number typed, certified under or reported "
                                                                 "by a unit (any text)"), AfterValidator(_search_text)]


class In(BaseModel):
    """Base of every request body: no field, however deep (``parameters``), may carry a NUL
    character or a non-finite number; the 422 names the field and where in it. A field the body does
    not know is an error, not silently dropped (``"serial_polcy": "refuse"`` left the policy as it was)."""

    model_config = ConfigDict(extra="forbid")

    @field_validator("*", mode="after")
    @classmethod
    def _storable(cls, v: Any) -> Any:
        problem = unstorable(v)
        if problem:
            raise ValueError(problem)
        return v

# --------------------------------------------------------------------------------------- service


class HealthOut(BaseModel):
    """The service is up and its database answers."""

    status: str
    version: str
    database: str = Field(description="sqlite or postgresql")

# --------------------------------------------------------------------------------------- devices


class DeviceOut(BaseModel):
    """A unit known by its serial number."""

    serial: str
    model: str | None
    firmware: str | None
    created_at: datetime
    calibrations: int
    current_calibration_id: int | None


#: What a calibration's ``identity`` holds.
IDENTITY_SAID = ("the serial typed (typed_serial), the one the unit reported (identified_serial), how it was identified "
                 "(identification) and the decision between them (serial_decision, serial_policy, serial_note); null "
                 "for a calibration made before the check or from the command line")


class CalibrationOut(BaseModel):
    """A stored calibration: the calibration JSON of PHYSICS.md (M_o, M_k, bias, ... as further
    keys) with its id, run, time, status (current, superseded, rejected) and verdict."""

    model_config = ConfigDict(extra="allow")

    id: int
    run_id: int | None
    created_at: datetime
    status: str
    verdict: str | None
    reasons: list[Any] | None
    serial: str
    identity: dict[str, Any] | None = Field(None, description=IDENTITY_SAID)


class HistoryEntry(BaseModel):
    """One line of a unit's calibration history: the figures the acceptance limits judged."""

    id: int
    run_id: int | None
    created_at: datetime
    status: str
    verdict: str | None
    reasons: list[Any]
    method: str | None
    slot: int | None
    figures: dict[str, Any] | None
    identity: dict[str, Any] | None = Field(None, description=IDENTITY_SAID)

# ---------------------------------------------------------------------------------------- limits


class LimitIn(In):
    """An acceptance limit: above ``marginal`` MARGINAL, above ``fail`` FAIL (finite numbers: an
    infinite limit would pass every calibration)."""

    marginal: Finite = Field(ge=0)
    fail: Finite = Field(ge=0)


class LimitOut(BaseModel):
    """An acceptance limit every new calibration is judged by."""

    name: str
    marginal: float
    fail: float
    unit: str
    description: str | None = None

# ------------------------------------------------------------------------------------ recordings


class RecordingOut(BaseModel):
    """An imported recording, stored as a completed run of procedure ``import``."""

    id: int
    status: str
    procedure: str
    samples: int
    serial: str | None = Field(description="its '# serial:' line; null when it has none")

# -------------------------------------------------------------------------------------- stations


class StationConfigIn(In):
    """A station's configuration (the name is in the path)."""

    # a script that PUTs what it POSTed (or read) may carry the name: the path's, or a 422
    name: StationName | None = Field(None, description="optional: the station's name, as in the path")
    modbus: str = Field(min_length=1, max_length=256, description="e.g. tcp://10.0.0.5:502")
    compasses: list[Annotated[str, AfterValidator(no_nul), Field(max_length=256)]] = Field(
        min_length=1, max_length=MAX_SLOTS, description="the serial URL of slot 0, slot 1, ...")
    time_scale: Finite = Field(1.0, gt=0, le=MAX_TIME_SCALE, description="> 1 only for a simulated station running faster")
    serial_policy: SerialPolicy | None = Field(
        None, description="when a unit reports another serial number than the one typed: prompt (ask the operator), "
        "refuse (the unit is not calibrated) or trust-typed (certified as typed, recorded); omitted: unchanged "
        "(prompt for a new station). A run or batch may override it")

    @field_validator("modbus")
    @classmethod
    def _url(cls, v: str | None) -> str | None:
        if v is not None:  # (None: a PATCH that leaves it as it is)
            BusURL.parse(v)  # ValueError names the problem
        return v

    @field_validator("compasses")
    @classmethod
    def _urls(cls, v: list[str] | None) -> list[str] | None:
        import serial  # pyserial: the URL forms the compass driver opens (serial.serial_for_url)

        if v is None:
            return v
        if any(not u.strip() for u in v):
            raise ValueError("empty compass URL")
        for i, u in enumerate(v):  # (before: an unknown protocol was taken, and the first run put the station in fault)
            try:
                serial.serial_for_url(u, do_not_open=True)
            except (ValueError, serial.SerialException) as e:
                raise ValueError(f"slot {i}: {u!r}: {e}") from None
        twice = _repeated([hardware_key(u) for u in v])
        if twice:  # two slots cannot read one compass (however each URL spells it)
            raise ValueError(f"compass URL given for two slots: {', '.join(twice)}")
        return v


class StationPatchIn(StationConfigIn):
    """A change of some of a station's settings (PATCH): what is given changes, the rest is kept; at least one."""

    modbus: str | None = Field(None, min_length=1, max_length=256, description="e.g. tcp://10.0.0.5:502; omitted: kept")
    compasses: list[Annotated[str, AfterValidator(no_nul), Field(max_length=256)]] | None = Field(
        None, min_length=1, max_length=MAX_SLOTS, description="the serial URL of slot 0, slot 1, ...; omitted: kept")
    time_scale: Finite | None = Field(None, gt=0, le=MAX_TIME_SCALE, description="omitted: kept")

    @model_validator(mode="after")
    def _something(self) -> "StationPatchIn":
        if not self.model_fields_set - {"name"}:
            raise ValueError("nothing to change: give one or more of modbus, compasses, time_scale, serial_policy")
        return self


class StationIn(StationConfigIn):
    """A new station: its name, its table's Modbus URL and one serial URL per fixture slot."""

    name: StationName


class StationOut(BaseModel):
    """A station: configuration, state (idle, running, paused, fault), current run and its worker."""

    name: str
    modbus: str
    compasses: list[str]
    time_scale: float
    created_at: datetime
    state: str
    run_id: int | None
    fault: str | None
    batch_id: int | None
    worker: str | None = Field(description="host:pid of the worker that last served it")
    worker_alive: bool = Field(description="its worker beat within the last few heartbeats")
    heartbeat_at: datetime | None
    serial_policy: str = Field(description="prompt, refuse or trust-typed: what a run does when a unit reports "
                               "another serial number than the one typed")

# ------------------------------------------------------------------------------------------ runs


def _repeated(values: list[str]) -> list[str]:
    """The values listed more than once, sorted (counted once each: count() per value was quadratic)."""
    return sorted(v for v, n in Counter(values).items() if n > 1)


def _distinct_serials(serials: list[str]) -> list[str]:
    """``serials`` unchanged, or a ValueError naming those listed more than once (one serial is one unit)."""
    dup = _repeated(serials)
    if dup:
        raise ValueError(f"serial numbers listed twice: {', '.join(dup)}")
    alike = _repeated([s.casefold() for s in serials])
    if alike:  # SN-1 and sn-1: two devices and two certificates for what is one unit typed twice, most likely
        said = [" and ".join(s for s in serials if s.casefold() == a) for a in alike]
        raise ValueError(f"serial numbers that differ only in letter case: {'; '.join(said)}; type each unit once")
    return serials


class ProcedureOut(BaseModel):
    """A procedure a run can take: its name and version, what it does, and its parameters' JSON Schema
    (each field's type, default, range and meaning: what ``parameters`` of ``POST /runs`` accepts)."""

    name: str
    version: str
    doc: str
    parameters: dict[str, Any]


class RunIn(In):
    """A run to start."""

    station: StationName
    procedure: str | None = Field(None, min_length=1, max_length=32,
                                  description="default calibrate (with resume: the resumed run's)")
    parameters: dict[str, Any] = Field(default_factory=dict, description="the procedure's parameters (GET /procedures "
                                       "gives each one's type, default and range); omitted: its defaults")
    serials: dict[str, Serial] | None = Field(None, max_length=MAX_SLOTS, description='slot -> serial, e.g. {"0": "SN-1"}; '
                                              "omitted: the compasses' own serial numbers. A serial number: " + SERIAL_RULE)
    resume: Id | None = Field(None, description="a failed or aborted run of this station to continue from the "
                              "last checkpoint it passed (its procedure, parameters and units; its samples up to "
                              "there are taken over, the same units must be mounted)")
    serial_policy: SerialPolicy | None = Field(None, description="when a unit reports another serial number than "
                                               "the one typed: prompt, refuse or trust-typed; default the station's")

    @field_validator("serials")
    @classmethod
    def _distinct(cls, v: dict[str, str] | None) -> dict[str, str] | None:
        # two slots typed with one serial would certify two units under it, the second superseding the first
        if v is not None:
            _distinct_serials(list(v.values()))
        return v


class StateIn(In):
    """A requested state change of a run."""

    state: str = Field(pattern="^(paused|running|aborted)$")
    reason: str | None = Field(None, max_length=500)


class BatchStateIn(In):
    """Abort a running batch."""

    state: Literal["aborted"] = Field(description="aborted: the current unit's run is aborted, no further unit starts")
    reason: str | None = Field(None, max_length=500)


class AnswerIn(In):
    """The operator's answer to a prompt."""

    # required: an empty body is no answer (it dismissed a mount prompt); "" may still be given
    answer: str = Field(max_length=1000, description="a serial prompt (serial-SLOT) takes " + ", ".join(CHOICES)
                        + "; a batch's mount prompt (mount) \"done\"; any other prompt any text")


class PromptOut(BaseModel):
    """An operator prompt the run waits on."""

    id: str
    text: str


class RunOut(BaseModel):
    """A run: provenance, live status, waiting prompts, progress and result."""

    id: int
    status: str = Field(description="queued, running, paused, completed, failed or aborted")
    reason: str | None
    station: str | None
    procedure: str
    procedure_version: str
    parameters: dict[str, Any]
    serials: dict[str, Any]
    operator: str
    batch_id: int | None
    software_version: str
    station_snapshot: dict[str, Any] | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    table_seconds: float | None
    samples_count: int
    result: dict[str, Any] | None = Field(description="per unit (units.SLOT): serial, calibration_id, verdict or "
                                          "error, typed_serial, identified_serial (null: not identified), "
                                          "identification, serial_decision, serial_note")
    serial_policy: str | None = Field(description="what the run does when a unit reports another serial number "
                                      "than the one typed")
    resumed_from: int | None = Field(None, description="the run this one continues (its samples up to its last "
                                                       "checkpoint are taken over), if any")
    resumed_by: list[int] = Field(default_factory=list, description="the runs that continue this one")
    pause_requested: bool
    prompts: list[PromptOut]
    progress: dict[str, Any] | None


class StationDetail(StationOut):
    """One station with its current run."""

    run: RunOut | None


class StationResetOut(StationOut):
    """A station after its reset: the axes whose faults were reset and any still faulted, and the
    compasses (by slot) that did not answer."""

    reset_axes: list[str] = []
    still_faulted: dict[str, str] = {}
    silent_compasses: dict[str, str] = {}


class StationResetRefusedOut(ErrorOut):
    """A reset that left the station in fault (503): why (``detail``), and when the table answered, the axes
    reset, those still faulted and the compasses (by slot) that did not answer."""

    reset_axes: list[str] = []
    still_faulted: dict[str, str] = {}
    silent_compasses: dict[str, str] = {}


class RunCalibration(BaseModel):
    """A calibration a run stored."""

    id: int
    slot: int | None
    serial: str
    status: str
    verdict: str | None
    reasons: list[Any] | None
    identity: dict[str, Any] | None = Field(None, description="typed_serial, identified_serial (null: not "
                                            "identified), identification, serial_decision, serial_note")


class RunDetail(RunOut):
    """One run with the calibrations it stored."""

    calibrations: list[RunCalibration]


class RunStateOut(RunOut):
    """A run after a state request: what was asked and what it does."""

    requested: str
    action: str


class AnswerOut(BaseModel):
    """An answer the run's worker took."""

    run_id: int
    prompt: str
    answer: str

# --------------------------------------------------------------------------------------- batches


class BatchIn(In):
    """Units to calibrate in turn on slot 0 of a station."""

    station: StationName
    serials: list[Serial] = Field(min_length=1, max_length=1000, description="the units' serial numbers, each "
                                  + SERIAL_RULE)
    parameters: dict[str, Any] = Field(default_factory=dict, description="calibrate parameters for every unit")
    serial_policy: SerialPolicy | None = Field(None, description="when a unit reports another serial number than "
                                               "the one typed: prompt, refuse or trust-typed; default the station's. "
                                               "A unit that reports a serial already certified in the batch is never "
                                               "certified again")

    @field_validator("serials")
    @classmethod
    def _distinct(cls, v: list[str]) -> list[str]:
        return _distinct_serials(v)


class BatchUnit(BaseModel):
    """One unit of a batch: its run, status and verdict."""

    serial: str
    run_id: int | None
    status: str = Field(description="its run's status; pending (its run not yet made), or not run (the batch ended first)")
    verdict: str | None
    reason: str | None = None
    identified_serial: str | None = Field(None, description="the serial number the mounted unit reported (None: "
                                          "not yet asked, or it reported none)")
    identification: str | None = Field(None, description="identified, not identified, differs or duplicate")
    calibration_id: int | None = None
    calibration_status: str | None = None
    prompts: list[PromptOut] = []
    table_seconds: float | None = Field(None, description="table time of the unit's run so far (s)")
    target: str | None = Field(None, description="an adaptive calibration's outcome against its targets: "
                               "'met', or 'not met: ...' with the budget that would reach them")


class BatchPrompt(PromptOut):
    """The prompt a batch waits on, with its run."""

    run_id: int


class BatchOut(BaseModel):
    """A batch: status, one row per unit, the waiting prompt and the summary by serial."""

    id: int
    station: str | None
    status: str
    operator: str
    serials: list[str]
    created_at: datetime
    finished_at: datetime | None
    summary: dict[str, str]
    units: list[BatchUnit]
    prompt: BatchPrompt | None
    tally: dict[str, int] = Field(description="the units counted by outcome: pass, marginal, fail (their verdicts), "
                                  "uncalibrated (a failed, aborted or refused run, or not run) and pending")

# -------------------------------------------------------------------------------------- analyses


class AnalysisIn(In):
    """What to analyse; every field optional (an empty body analyses every unit of the run)."""

    slot: Annotated[Index, BeforeValidator(request_number)] | None = Field(
        None, description="the fixture slot (unit) to analyse; default: every slot with samples")
    null_sims: Annotated[int, Field(ge=0, le=5000), BeforeValidator(request_number)] = Field(
        200, description="simulated null recordings calibrating the tests' false-alarm rate")
    calibration_id: Id | None = Field(None, description="a stored calibration as the unit's nominal model (the "
                                      "recording's own fit is compared with it: shifted parameters are reported); "
                                      "default: the run's own calibration of the unit, else the unit's current one")


class AnalysisOut(BaseModel):
    """An analysis: its state and progress; once ``completed``, the analyser's result (verdict,
    findings, fit before and after, ... as further keys)."""

    model_config = ConfigDict(extra="allow")

    id: int
    run_id: int
    slot: int | None
    serial: str | None
    status: str = Field(description="queued, running, completed or failed")
    reason: str | None = Field(description="why it failed")
    progress: dict[str, Any] | None = Field(description='{"stage": ..., "percent": ...}')
    calibration_id: int | None
    null_sims: int | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    url: str
    events_url: str
    report_url: str | None


class AnalysesCreated(BaseModel):
    """The analyses a request queued, one per unit."""

    run_id: int
    analyses: list[AnalysisOut]


class AnalysisLine(BaseModel):
    """One line of a run's analyses."""

    id: int
    run_id: int
    slot: int | None
    serial: str | None
    created_at: datetime
    status: str
    reason: str | None
    progress: dict[str, Any] | None
    verdict: str | None
    model: str | None
    findings: list[str | None]
    report_url: str | None

# -------------------------------------------------------------------------- non-JSON answers


def content(media_type: str, description: str, binary: bool = False) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI description of a success answer that is not JSON (a CSV, a PDF, HTML, events)."""
    schema: dict[str, Any] = {"type": "string", **({"format": "binary"} if binary else {})}
    # refusals stay JSON: spelt out, since FastAPI would document a model under the route's media type
    errors = {code: {"description": e["description"],
                     "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}}}
              for code, e in ERRORS.items()}
    return {200: {"description": description, "content": {media_type: {"schema": schema}}}, **errors}

# ------------------------------------------------------------------------------------------- keys


class KeyIn(In):
    """A key to create."""

    owner: str = Field(min_length=1, max_length=64, description="who it belongs to (recorded with every change it makes)")
    role: str = Field(description="viewer, operator or admin")


class KeyOut(BaseModel):
    """An API key as listed (its secret is never stored, only shown once at creation)."""

    id: int
    prefix: str = Field(description="the characters the key starts with")
    owner: str
    role: str
    revoked: bool
    created_at: datetime


class KeyCreated(KeyOut):
    """A new key, with the key itself: store it now, it cannot be shown again."""

    key: str
