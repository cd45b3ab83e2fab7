"""The database: SQLAlchemy 2 models (normalised: no table per run), engine and sessions, migrations.

SQLite by default (a file under the user's data directory, WAL mode), PostgreSQL by URL
(``COMPASSCAL_DATABASE_URL``). The schema is created and changed only by the Alembic migrations in
``migrations/``; :func:`upgrade` runs them.
"""

from __future__ import annotations

import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from sqlalchemy import (JSON, BigInteger, Boolean, DateTime, Float, ForeignKey, Index, Integer, String, Text,
                        TypeDecorator, create_engine, event)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship, sessionmaker

ROOT = Path(__file__).resolve().parent.parent


def utcnow() -> datetime:
    """Timezone-aware now (stored as UTC)."""
    return datetime.now(timezone.utc)


def default_url() -> str:
    """``COMPASSCAL_DATABASE_URL``, else a SQLite file in the user's data directory."""
    url = os.environ.get("COMPASSCAL_DATABASE_URL")
    if url:
        return url
    base = Path(os.environ.get("COMPASSCAL_DATA_DIR") or Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local/share") / "compasscal")
    base.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{base / 'compasscal.db'}"


class UTCDateTime(TypeDecorator[datetime]):
    """A timestamp stored in UTC and always read back timezone-aware (SQLite forgets the zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        return value.astimezone(timezone.utc) if value is not None and value.tzinfo else value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        return value.replace(tzinfo=timezone.utc) if value is not None and value.tzinfo is None else value


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON, datetime: UTCDateTime()}


class Device(Base):
    """A compass unit, known by its serial number."""

    __tablename__ = "devices"
    id: Mapped[int] = mapped_column(primary_key=True)
    serial: Mapped[str] = mapped_column(String(64), unique=True)
    model: Mapped[str | None] = mapped_column(String(64))
    firmware: Mapped[str | None] = mapped_column(String(32))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Station(Base):
    """A calibration station: a table's Modbus URL and the serial URL of each fixture slot."""

    __tablename__ = "stations"
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    modbus: Mapped[str] = mapped_column(String(256))
    compasses: Mapped[list[Any]] = mapped_column(JSON)
    time_scale: Mapped[float] = mapped_column(Float, default=1.0)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    # what its worker reports (the worker owns the hardware; the API only reads these)
    state: Mapped[str] = mapped_column(String(16), default="idle")  # idle | running | paused | fault
    reason: Mapped[str | None] = mapped_column(Text)  # the fault's
    run_id: Mapped[int | None] = mapped_column(Integer)  # the run holding the station (claimed on start)
    batch_id: Mapped[int | None] = mapped_column(Integer)  # a batch holds the station between its units
    worker: Mapped[str | None] = mapped_column(String(128))  # host:pid of the worker serving it
    heartbeat_at: Mapped[datetime | None]  # that worker's last sign of life
    reset: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # the last reset's outcome
    # what a run does when a unit reports another serial than the one typed (service/identity.py)
    serial_policy: Mapped[str] = mapped_column(String(16), default="prompt", server_default="prompt")


class Batch(Base):
    """Several units calibrated in turn on one station."""

    __tablename__ = "batches"
    id: Mapped[int] = mapped_column(primary_key=True)
    station_id: Mapped[int] = mapped_column(ForeignKey("stations.id"))
    serials: Mapped[list[Any]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    operator: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[datetime | None]
    summary: Mapped[dict[str, Any] | None] = mapped_column(JSON)


class Run(Base):
    """One execution of a procedure, with its provenance and outcome."""

    __tablename__ = "runs"
    id: Mapped[int] = mapped_column(primary_key=True)
    station_id: Mapped[int | None] = mapped_column(ForeignKey("stations.id"))
    batch_id: Mapped[int | None] = mapped_column(ForeignKey("batches.id"))
    procedure: Mapped[str] = mapped_column(String(32))
    procedure_version: Mapped[str] = mapped_column(String(16))
    parameters: Mapped[dict[str, Any]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    reason: Mapped[str | None] = mapped_column(Text)
    operator: Mapped[str] = mapped_column(String(64))
    station_snapshot: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    serials: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    software_version: Mapped[str] = mapped_column(String(32))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    table_seconds: Mapped[float | None]
    samples_count: Mapped[int] = mapped_column(Integer, default=0)
    meta: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    # the live view, kept by the worker from the run's events (so any API process can answer)
    pause_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    prompts: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # waiting prompts: id -> text
    progress: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    calibrations: Mapped[list["Calibration"]] = relationship(back_populates="run")


class RunEvent(Base):
    """One event of a run (state, step, progress, samples, prompt, result), as the worker published it.
    The id orders every run's events and is the server-sent events' id (``Last-Event-ID``)."""

    __tablename__ = "run_events"
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class RunCommand(Base):
    """An operator's command to a run's worker (pause, resume, abort, answer), taken in order."""

    __tablename__ = "run_commands"
    id: Mapped[int] = mapped_column(primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    taken_at: Mapped[datetime | None]


class Sample(Base):
    """One raw reading with its table angles and time (long format, bulk-inserted)."""

    __tablename__ = "samples"
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    slot: Mapped[int] = mapped_column(Integer)
    t: Mapped[float]
    step: Mapped[str] = mapped_column(String(32))
    psi_t: Mapped[float | None]  # NULL: a recording without table angles (hand-held, foreign imports)
    theta_t: Mapped[float | None]
    phi_t: Mapped[float | None]
    mx: Mapped[float]
    my: Mapped[float]
    mz: Mapped[float]
    ax: Mapped[float | None]
    ay: Mapped[float | None]
    az: Mapped[float | None]
    temp_c: Mapped[float | None]
    __table_args__ = (Index("ix_samples_run_slot", "run_id", "slot", "id"),)


class SampleExtra(Base):
    """An imported recording's extra column (RECORDING.md: kept and ignored), its values as text in
    the order of the slot's samples."""

    __tablename__ = "sample_extras"
    id: Mapped[int] = mapped_column(primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    slot: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(64))
    values: Mapped[list[Any]] = mapped_column(JSON)


class Calibration(Base):
    """A unit's calibration from one run; never overwritten (current, superseded or rejected)."""

    __tablename__ = "calibrations"
    id: Mapped[int] = mapped_column(primary_key=True)
    device_id: Mapped[int] = mapped_column(ForeignKey("devices.id"))
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"))
    slot: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16))  # current | superseded | rejected
    verdict: Mapped[str] = mapped_column(String(16))  # PASS | MARGINAL | FAIL
    reasons: Mapped[list[Any]] = mapped_column(JSON, default=list)
    method: Mapped[str] = mapped_column(String(32))
    data: Mapped[dict[str, Any]] = mapped_column(JSON)  # the physics calibration JSON
    figures: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # what the limits judge (store.figures)
    # typed and identified serial numbers and how they were settled (service.identity.Identity.to_json)
    identity: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    # the acceptance limits the verdict was judged against (name, marginal, fail, unit, description);
    # None for a calibration stored before they were kept
    limits: Mapped[list[Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    run: Mapped[Run] = relationship(back_populates="calibrations")
    device: Mapped[Device] = relationship()
    __table_args__ = (Index("ix_calibrations_device_created", "device_id", "created_at"),)


class Analysis(Base):
    """A discrepancy analysis of one unit (slot) of a run: a job (``queued``, ``running``, then
    ``completed`` with the analyser's result in ``report``, or ``failed`` with the reason)."""

    __tablename__ = "analyses"
    id: Mapped[int] = mapped_column(primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id"), index=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    report: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16), default="completed")
    slot: Mapped[int | None] = mapped_column(Integer)
    request: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # null_sims, calibration_id, operator
    progress: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # {"stage": ..., "percent": ...}
    reason: Mapped[str | None] = mapped_column(Text)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    version: Mapped[int] = mapped_column(Integer, default=0)  # bumped at each change: the stream's event id


class ApiKey(Base):
    """An API key, stored as its SHA-256 hash, with an owner and a role."""

    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(primary_key=True)
    owner: Mapped[str] = mapped_column(String(64))
    role: Mapped[str] = mapped_column(String(16))  # viewer | operator | admin
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(12))
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Limit(Base):
    """One acceptance limit: above ``marginal`` a calibration is MARGINAL, above ``fail`` it FAILs."""

    __tablename__ = "limits"
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    marginal: Mapped[float]
    fail: Mapped[float]
    unit: Mapped[str] = mapped_column(String(16))
    description: Mapped[str] = mapped_column(Text)


class WebSession(Base):
    """A browser session of the web pages: the cookie carries a random token, stored here only as
    its hash, tied to the key that logged in and ending at ``expires_at`` (or at logout, or when
    that key is revoked)."""

    __tablename__ = "web_sessions"
    token_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    key_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime]


class AuditLog(Base):
    """Every state-changing call, with the key's owner."""

    __tablename__ = "audit_log"
    id: Mapped[int] = mapped_column(primary_key=True)
    at: Mapped[datetime] = mapped_column(default=utcnow)
    owner: Mapped[str] = mapped_column(String(64))
    action: Mapped[str] = mapped_column(String(64))
    target: Mapped[str] = mapped_column(String(128))
    detail: Mapped[dict[str, Any] | None] = mapped_column(JSON)


def make_engine(url: str | None = None) -> Engine:
    """An engine for ``url`` (default :func:`default_url`); SQLite gets WAL mode and foreign keys."""
    url = url or default_url()
    if url.startswith("postgresql://"):
        url = "postgresql+psycopg://" + url.removeprefix("postgresql://")
    kw: dict[str, Any] = {}
    if url.startswith("sqlite"):
        kw["connect_args"] = {"check_same_thread": False, "timeout": 30}
    else:
        # pre-ping: a pooled connection cut by a database restart is replaced, not handed out;
        # connect_timeout: a database that does not answer is an error in seconds, not a hang
        kw.update(pool_size=20, max_overflow=40, pool_pre_ping=True, connect_args={"connect_timeout": 5})
    engine = create_engine(url, **kw)
    if url.startswith("sqlite"):
        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_conn: Any, _: Any) -> None:
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()
    return engine


def upgrade(engine: Engine) -> None:
    """Bring the schema to the newest migration (Alembic ``upgrade head``)."""
    from alembic import command
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(ROOT / "migrations"))
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, "head")


def sessions(engine: Engine) -> sessionmaker:
    """A session factory bound to ``engine``."""
    return sessionmaker(engine, expire_on_commit=False)
