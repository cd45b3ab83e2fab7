"""A whole simulated station: one world, one Modbus table server, one serial device per compass slot,
a clock with a time scale, and the fault side channel (scheduled from the config or sent over the
control port; never through the device protocols).
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.sim.clock import SimClock
from drivers.sim.compass import CompassSim
from drivers.sim.config import FaultConfig, StationConfig, parse_fault
from drivers.sim.turntable import TableSim
from drivers.sim.world import Effect, SimWorld
from physics.simulate import truth_json


@dataclass
class SimStation:
    """Run with ``async with SimStation(cfg) as st:``; ``st.describe()`` says where to connect."""

    config: StationConfig
    modbus_port: int = 0
    compass_tcp_port: int | None = None
    control_port: int | None = 0
    host: str = "127.0.0.1"  # 0.0.0.0 to serve other machines (e.g. a container's network)
    #: concealed effects besides the config's ``[[effect]]`` tables: an Effect (every slot) or (slot, Effect)
    effects: list[Effect | tuple[int | None, Effect]] = field(default_factory=list)

    def __post_init__(self) -> None:
        w = self.config.world
        self.clock = SimClock(w.time_scale)
        self.physics_world = w.world()
        self.units = [u.unit() for u in self.config.unit]
        t = self.config.table
        self.table = TableSim(self.clock, tuple(t.start_deg), units=dict(t.units), homed=t.homed,  # type: ignore[arg-type]
                              enabled=t.enabled, hard_limits={k: (v[0], v[1]) for k, v in t.hard_limits_deg.items()})
        self.world = SimWorld(self.physics_world, self.units, self.table.true_angles,
                              rng=np.random.default_rng(w.seed), effects=[*self.config.effects(), *self.effects])
        self.compasses = [
            CompassSim(serial=u.serial, model=u.model, firmware=u.firmware, read=self.world.reader(slot), clock=self.clock)
            for slot, u in enumerate(self.config.unit)
        ]
        self.urls: list[str] = []
        self.port = 0
        self._tasks: list[asyncio.Task[None]] = []
        self._control: asyncio.base_events.Server | None = None

    async def start(self) -> dict[str, Any]:
        """Start every device; returns :meth:`describe`."""
        self.port = await self.table.start(self.modbus_port, framer=self.config.table.framer, host=self.host)
        for slot, (sim, u) in enumerate(zip(self.compasses, self.config.unit)):
            if self.compass_tcp_port is not None or u.transport == "tcp":
                port = 0 if not self.compass_tcp_port else self.compass_tcp_port + slot
                self.urls.append(await sim.start(transport="tcp", host=self.host, port=port))
            else:
                self.urls.append(await sim.start(transport="pty"))
        for f in self.config.fault:
            self.inject(f)
        if self.control_port is not None:
            self._control = await asyncio.start_server(self._serve_control, self.host, self.control_port)
        return self.describe()

    async def stop(self) -> None:
        """Stop every device and scheduled fault."""
        for task in self._tasks:
            task.cancel()
        if self._control is not None:
            self._control.close()
        for sim in self.compasses:
            await sim.stop()
        await self.table.stop()

    async def __aenter__(self) -> "SimStation":
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def describe(self) -> dict[str, Any]:
        """Where to connect: the `compasscal sim` JSON line."""
        scheme = "rtu+tcp" if self.config.table.framer == "rtu" else "tcp"
        where = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        d: dict[str, Any] = {
            "modbus": f"{scheme}://{where}:{self.port}",
            "units": sorted(self.config.table.units.values()),
            "compasses": [{"slot": i, "url": url, "serial": u.serial} for i, (url, u) in enumerate(zip(self.urls, self.config.unit))],
            "time_scale": self.clock.time_scale,
        }
        if self._control is not None:
            d["control"] = f"tcp://{where}:{self._control.sockets[0].getsockname()[1]}"
        return d

    def truth(self) -> list[dict[str, object]]:
        """True parameters of every mounted unit (the ``.truth.json`` format of physics), slot order,
        with the effects concealed in each (``effects``: [{"effect": id, "parameters": {...}}]; the
        geometry given is the configured one, without a concealed table_axis_error)."""
        out = []
        for slot, u in enumerate(self.units):
            d = truth_json(u, self.physics_world)
            d["effects"] = [{"effect": e.id, "parameters": e.params()} for e in self.world.effects_of(slot)]
            out.append(d)
        return out

    # ----------------------------------------------------------------------------------- faults
    def inject(self, fault: FaultConfig) -> None:
        """Apply a fault now, or at ``at_s`` simulated seconds (an axis alarm also when the axis passes
        ``at_angle_deg``)."""
        if fault.kind == "axis_alarm":
            # The table model watches times and angles itself, to its simulation step.
            self.table.alarm(fault.axis, fault.code, at_time=fault.at_s, at_angle=fault.at_angle_deg)
        elif fault.at_s is not None and fault.at_s > self.clock.now():
            self._tasks.append(asyncio.get_running_loop().create_task(self._later(fault)))
        else:
            self._apply(fault)

    async def _later(self, fault: FaultConfig) -> None:
        await self.clock.sleep_until(fault.at_s or 0.0)
        self._apply(fault)

    def _apply(self, f: FaultConfig) -> None:
        if f.kind == "axis_alarm":
            self.table.alarm(f.axis, f.code)
        elif f.kind == "axis_silent":
            self.table.silence(f.axis, True)
        elif f.kind == "stuck_encoder":
            self.table.stick_encoder(f.axis, True)
        elif f.kind == "estop":
            self.table.estop(True)
        else:
            sim = self.compasses[f.slot or 0]
            {"compass_silent": lambda: sim.go_silent(True),
             "garbage": lambda: sim.garbage(f.nbytes),
             "fused_line": sim.fuse_next,
             "truncated_line": sim.truncate_next,
             "compass_reset": sim.reset,
             "port_vanish": sim.vanish,
             "bad_readings": lambda: sim.bad_readings(f.count, f.pattern)}[f.kind]()

    def clear_faults(self) -> None:
        """Repair what an operator would: silent axes and compasses answer again, stuck encoders move, the
        E-stop is released. An axis alarm stays latched until the table's own RESET_FAULT, as on hardware."""
        for axis in ("z", "y", "x"):
            self.table.silence(axis, False)
            self.table.stick_encoder(axis, False)
        self.table.estop(False)
        for sim in self.compasses:
            sim.go_silent(False)

    async def _serve_control(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """The side channel: one JSON object per line. ``{"fault": {...}}`` injects a fault (the
        ``[[fault]]`` keys), ``{"clear": null}`` repairs the hardware (:meth:`clear_faults`), ``{"time": null}``
        asks for the simulated time. Replies one JSON line each, with the simulated time and the time scale
        (how a client learns that t is table time)."""
        try:
            while line := await reader.readline():
                try:
                    msg = json.loads(line)
                    if "fault" in msg:
                        self.inject(parse_fault(msg["fault"]))
                    if "clear" in msg:
                        self.clear_faults()
                    reply: dict[str, Any] = {"ok": True, "sim_time": self.clock.now(), "time_scale": self.clock.time_scale}
                except Exception as e:  # a bad request must not take the station down
                    reply = {"ok": False, "error": str(e)}
                writer.write((json.dumps(reply) + "\n").encode())
                await writer.drain()
        finally:
            writer.close()


async def control_request(url: str, message: dict[str, Any], timeout_s: float = 3.0) -> dict[str, Any]:
    """Send one request to a simulated station's control port (``tcp://HOST:PORT``, the ``control`` of
    :meth:`SimStation.describe`) and return its reply. Raises ``OSError`` (naming the URL) when the port
    does not answer, ``ValueError`` for a malformed URL or a refused request."""
    from urllib.parse import urlsplit

    u = urlsplit(url)
    if u.scheme != "tcp" or not u.hostname or u.port is None:
        raise ValueError(f"control URL {url!r}: expected tcp://HOST:PORT")
    try:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(u.hostname, u.port), timeout_s)
        try:
            writer.write((json.dumps(message) + "\n").encode())
            await writer.drain()
            line = await asyncio.wait_for(reader.readline(), timeout_s)
        finally:
            writer.close()
    except asyncio.TimeoutError:
        raise OSError(f"control port {url}: no answer within {timeout_s:g} s") from None
    except OSError as e:
        raise OSError(f"control port {url}: {e.strerror or e}") from None
    try:
        reply = json.loads(line)
    except ValueError:
        raise OSError(f"control port {url}: not a simulated station's reply ({line[:60]!r})") from None
    if not isinstance(reply, dict) or not reply.get("ok"):
        raise ValueError(f"control port {url} refused {message}: {reply.get('error') if isinstance(reply, dict) else reply}")
    return reply
