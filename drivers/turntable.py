"""The three-axis turntable driver: one Modbus axis controller per axis (PROTOCOLS.md).

``Axis`` talks to one unit: identity check, commands with the CMD_COUNT handshake, status polling.
``Turntable`` groups three axes (z outer = psi, y middle = theta, x inner = phi) and moves them
together. Everything is async and every wait has a deadline: a dead axis is reported within about a
second, a move that does not finish within its trapezoid time plus a margin raises ``MoveTimeout``.

Example::

    table = Turntable("tcp://127.0.0.1:5020")
    await table.connect()
    await table.enable_all()
    await table.home_all()
    await table.move_to(90, 30, -45)
    print(await table.positions())
    await table.close()
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from drivers import DriverError
from drivers.modbus import BusExceptionReply, BusUnreachable, ModbusBus
from drivers.protocol import (
    AXIS_UNITS,
    CMD_RESULT_TEXT,
    COUNTS_PER_DEG,
    CmdResult,
    FAULTS,
    PROTOCOL_VERSION,
    Command,
    Reg,
    Status,
    fault_name,
    from_words,
    status_names,
    to_i16,
    to_words,
    with_advice,
)

POLL_INTERVAL = 0.005  # s wall between status polls while waiting (a poll itself takes ~1 ms)
SETTLE_MARGIN = 2.0  # s added to every computed move time (servo settling, bus latency)
SCAN_POLL_INTERVAL = 0.002  # s wall between encoder polls while scanning (positions are interpolated between them)


# --------------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------------


class AxisError(DriverError):
    """An error on one axis; ``axis`` is its name."""

    def __init__(self, axis: str, message: str) -> None:
        super().__init__(f"axis {axis}: {message}")
        self.axis = axis


class AxisUnreachable(AxisError):
    """No answer from the axis (timeout, connection lost, exception 0x04/0x0B)."""


class AxisFault(AxisError):
    """The controller reports a fault: ``code`` and its ``name`` from protocol.FAULTS."""

    def __init__(self, axis: str, code: int) -> None:
        self.code = code
        self.name = FAULTS.get(code, "unknown fault")
        super().__init__(axis, with_advice(f"fault 0x{code:02X} {self.name}", code))


class MoveTimeout(AxisError):
    """The axis did not reach its target in time."""


class CommandRefused(AxisError):
    """The controller did not accept a command; ``reason`` is the LAST_CMD_RESULT text."""

    def __init__(self, axis: str, command: str, result: int | None, reason: str) -> None:
        self.command = command
        self.result = result
        self.reason = reason
        super().__init__(axis, f"{command} refused: {reason}")


class ProtocolMismatch(AxisError):
    """The device at this address is not a controller speaking our protocol version."""


class AxisProtocolError(AxisError):
    """The controller answered a Modbus exception for a protocol error (bad address or value)."""

    def __init__(self, axis: str, message: str, code: int) -> None:
        super().__init__(axis, message)
        self.code = code


# --------------------------------------------------------------------------------------------------
# Status
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisStatus:
    """One decoded poll of the status block 0x0010-0x001F."""

    axis: str
    status: int
    flags: tuple[str, ...]  # names of the STATUS bits that are set
    fault_code: int
    fault_name: str  # "" when no fault
    position_deg: float
    velocity_dps: float
    demand_deg: float
    following_error_deg: float
    cmd_count: int
    last_result: int
    last_result_text: str
    warning_code: int
    temperature_c: float
    position_mod_deg: float

    @classmethod
    def decode(cls, axis: str, regs: Sequence[int], low_word_first: bool = False) -> AxisStatus:
        """Decode the 16 registers read from 0x0010."""
        if len(regs) != 16:
            raise ValueError(f"status block needs 16 registers, got {len(regs)}")

        def wide(reg: int, signed: bool = True) -> int:
            i = reg - Reg.STATUS
            return from_words(regs[i:i + 2], signed, low_word_first)

        def word(reg: int) -> int:
            return regs[reg - Reg.STATUS]

        fault = word(Reg.FAULT_CODE)
        result = word(Reg.LAST_CMD_RESULT)
        return cls(
            axis=axis,
            status=word(Reg.STATUS),
            flags=tuple(status_names(word(Reg.STATUS))),
            fault_code=fault,
            fault_name=FAULTS.get(fault, "unknown fault") if fault else "",
            position_deg=wide(Reg.ACTUAL_POS) / COUNTS_PER_DEG,
            velocity_dps=wide(Reg.ACTUAL_VEL) / COUNTS_PER_DEG,
            demand_deg=wide(Reg.DEMAND_POS) / COUNTS_PER_DEG,
            following_error_deg=wide(Reg.FOLLOWING_ERR) / COUNTS_PER_DEG,
            cmd_count=word(Reg.CMD_COUNT),
            last_result=result,
            last_result_text=CMD_RESULT_TEXT.get(result, f"result {result}"),
            warning_code=word(Reg.WARNING_CODE),
            temperature_c=to_i16(word(Reg.TEMPERATURE)) / 10.0,
            position_mod_deg=wide(Reg.ACTUAL_POS_MOD, signed=False) / COUNTS_PER_DEG,
        )

    def has(self, bit: Status) -> bool:
        """Whether a STATUS bit is set."""
        return bool(self.status & bit)

    @property
    def enabled(self) -> bool:
        return self.has(Status.ENABLED)

    @property
    def moving(self) -> bool:
        """Any motion in progress (move, homing, jog or stop ramp)."""
        return bool(self.status & (Status.MOVING | Status.HOMING | Status.JOGGING | Status.STOPPING))

    @property
    def in_position(self) -> bool:
        return self.has(Status.IN_POSITION)

    @property
    def homed(self) -> bool:
        return self.has(Status.HOMED)

    @property
    def fault(self) -> bool:
        return self.has(Status.FAULT)

    @property
    def estop(self) -> bool:
        return self.has(Status.ESTOP)


@dataclass(frozen=True)
class AxisIdentity:
    """The identity block."""

    product_id: int
    fw_version: str
    serial_no: int
    axis_index: int
    counts_per_deg: int
    protocol_version: int


def _mdeg(deg: float) -> int:
    return int(round(deg * COUNTS_PER_DEG))


def _rate(value: float, what: str) -> int:
    """A velocity or acceleration in mdeg units; must be positive (the controller rejects 0)."""
    v = int(round(value * COUNTS_PER_DEG))
    if v <= 0:
        raise ValueError(f"{what} must be > 0, got {value}")
    return v


def trapezoid_time(distance: float, vel: float, acc: float, dec: float | None = None) -> float:
    """Time (s) a trapezoidal (or triangular) profile needs to travel ``distance``."""
    dec = acc if dec is None else dec
    d = abs(distance)
    if d == 0:
        return 0.0
    d_ramps = vel * vel / (2 * acc) + vel * vel / (2 * dec)
    if d >= d_ramps:
        return vel / acc + vel / dec + (d - d_ramps) / vel
    vp = math.sqrt(2 * d * acc * dec / (acc + dec))
    return vp / acc + vp / dec


# --------------------------------------------------------------------------------------------------
# Axis
# --------------------------------------------------------------------------------------------------


class Axis:
    """One axis controller (one Modbus unit) on a bus that may be shared with other axes."""

    def __init__(self, name: str, unit: int, bus: ModbusBus, *, low_word_first: bool = False,
                 poll_interval: float = POLL_INTERVAL) -> None:
        self.name = name
        self.unit = unit
        self.bus = bus
        self.low_word_first = low_word_first
        self.poll_interval = poll_interval
        self.identity: AxisIdentity | None = None

    def __repr__(self) -> str:
        return f"Axis({self.name!r}, unit={self.unit}, bus={self.bus.url!r})"

    # --- register access (errors translated to axis errors) --------------------------------------

    async def _read(self, addr: int, count: int) -> list[int]:
        try:
            return await self.bus.read(self.unit, addr, count)
        except BusUnreachable as exc:
            raise AxisUnreachable(self.name, str(exc)) from exc
        except BusExceptionReply as exc:
            raise AxisProtocolError(self.name, str(exc), exc.code) from exc

    async def _write(self, addr: int, values: Sequence[int], retry: bool = True) -> None:
        try:
            await self.bus.write(self.unit, addr, values, retry=retry)
        except BusUnreachable as exc:
            raise AxisUnreachable(self.name, str(exc)) from exc
        except BusExceptionReply as exc:
            raise AxisProtocolError(self.name, str(exc), exc.code) from exc

    def _words(self, value: int, signed: bool) -> list[int]:
        return to_words(value, signed, self.low_word_first)

    async def read_value(self, reg: Reg, signed: bool = True, wide: bool = True) -> int:
        """Read one register (or 32-bit pair when ``wide``)."""
        if wide:
            return from_words(await self._read(reg, 2), signed, self.low_word_first)
        v = (await self._read(reg, 1))[0]
        return to_i16(v) if signed else v

    async def write_value(self, reg: Reg, value: int, signed: bool = True, wide: bool = True) -> None:
        """Write one configuration register (or 32-bit pair when ``wide``)."""
        await self._write(reg, self._words(value, signed) if wide else [value & 0xFFFF])

    # --- identity and status ---------------------------------------------------------------------

    async def connect(self) -> AxisIdentity:
        """Read the identity block and check COUNTS_PER_DEG and PROTOCOL_VERSION."""
        r = await self._read(Reg.PRODUCT_ID, 7)
        ident = AxisIdentity(
            product_id=r[0],
            fw_version=f"{r[1] >> 8}.{r[1] & 0xFF}",
            serial_no=from_words(r[2:4], False, self.low_word_first),
            axis_index=r[4],
            counts_per_deg=r[5],
            protocol_version=r[6],
        )
        if ident.counts_per_deg != COUNTS_PER_DEG:
            raise ProtocolMismatch(self.name, f"COUNTS_PER_DEG is {ident.counts_per_deg}, expected {COUNTS_PER_DEG}")
        if ident.protocol_version != PROTOCOL_VERSION:
            raise ProtocolMismatch(
                self.name, f"PROTOCOL_VERSION is {ident.protocol_version}, expected {PROTOCOL_VERSION}")
        self.identity = ident
        return ident

    async def status(self) -> AxisStatus:
        """One 16-register poll of the status block."""
        return AxisStatus.decode(self.name, await self._read(Reg.STATUS, 16), self.low_word_first)

    async def position(self) -> float:
        """The encoder position (ACTUAL_POS) in degrees."""
        return from_words(await self._read(Reg.ACTUAL_POS, 2), True, self.low_word_first) / COUNTS_PER_DEG

    # --- commands --------------------------------------------------------------------------------

    async def _command(self, cmd: Command, target: int | None = None, vel: int | None = None,
                       acc: int | None = None, dec: int | None = None) -> AxisStatus:
        """Run ``cmd`` with the CMD_COUNT handshake; with parameters, one FC16 of 0x0020-0x0028.

        Returns the status read right after acceptance. Raises CommandRefused with the
        LAST_CMD_RESULT reason when the controller refused it.
        """
        before = (await self._read(Reg.CMD_COUNT, 1))[0]
        if target is None:
            regs: list[int] = [int(cmd)]
            addr = Reg.COMMAND
        else:
            assert vel is not None and acc is not None and dec is not None
            regs = (self._words(target, True) + self._words(vel, False) + self._words(acc, False)
                    + self._words(dec, False) + [int(cmd)])
            addr = Reg.TARGET_POS
        try:
            # No blind retry: a repeated MOVE_REL would move twice. If the reply was lost, CMD_COUNT
            # tells whether the command ran; only if it did not is the write repeated.
            await self._write(addr, regs, retry=False)
        except AxisUnreachable:
            if (await self._read(Reg.CMD_COUNT, 1))[0] == before:
                await self._write(addr, regs, retry=False)
        st = await self.status()
        if st.cmd_count == before:
            raise CommandRefused(self.name, cmd.name, None, "not acknowledged (CMD_COUNT unchanged)")
        if st.last_result != 0:
            # refused for a fault: say which (an alarm raised while the axis held was named only "fault active")
            why = st.last_result_text + (f" (fault {fault_name(st.fault_code)})"
                                         if st.last_result == CmdResult.FAULT_ACTIVE and st.fault_code else "")
            raise CommandRefused(self.name, cmd.name, st.last_result, why)
        return st

    async def enable(self) -> None:
        """Energise the servo (ENABLE)."""
        await self._command(Command.ENABLE)

    async def disable(self) -> None:
        """De-energise the servo (DISABLE)."""
        await self._command(Command.DISABLE)

    async def reset_fault(self) -> None:
        """Clear a resettable fault (RESET_FAULT)."""
        await self._command(Command.RESET_FAULT)

    async def stop(self) -> None:
        """Decelerate to rest at PROFILE_DEC (STOP; always accepted)."""
        await self._command(Command.STOP)

    async def quick_stop(self) -> None:
        """Stop as fast as the drive can (QUICK_STOP; always accepted)."""
        await self._command(Command.QUICK_STOP)

    async def set_position(self, deg: float) -> None:
        """Preset the encoder so the current position reads ``deg`` (SET_POSITION; sets HOMED)."""
        await self._write(Reg.TARGET_POS, self._words(_mdeg(deg), True))
        await self._command(Command.SET_POSITION)

    async def set_soft_limits(self, lo_deg: float, hi_deg: float, enable: bool = True) -> None:
        """Write SOFT_LIMIT_MIN/MAX and SOFT_LIMIT_ENABLE (one FC16 of 5 registers)."""
        await self._write(Reg.SOFT_LIMIT_MIN, self._words(_mdeg(lo_deg), True)
                          + self._words(_mdeg(hi_deg), True) + [1 if enable else 0])

    async def start_home(self, vel_dps: float = 10.0, acc_dps2: float = 20.0) -> AxisStatus:
        """Start homing (does not wait)."""
        v, a = _rate(vel_dps, "velocity"), _rate(acc_dps2, "acceleration")
        return await self._command(Command.HOME, 0, v, a, a)

    async def home(self, vel_dps: float = 10.0, acc_dps2: float = 20.0, timeout: float | None = None) -> AxisStatus:
        """Home the axis and wait until HOMED and in position (timeout: one turn plus margin)."""
        await self.start_home(vel_dps, acc_dps2)
        t = timeout if timeout is not None else trapezoid_time(360, vel_dps, acc_dps2) * 1.2 + SETTLE_MARGIN
        st = await self.wait_in_position(t)
        if not st.homed:
            raise MoveTimeout(self.name, "homing ended without HOMED")
        return st

    async def start_move_abs(self, deg: float, vel_dps: float = 30.0, acc_dps2: float = 60.0,
                             dec_dps2: float | None = None) -> AxisStatus:
        """Start an absolute move (does not wait). A move while moving re-targets."""
        dec = acc_dps2 if dec_dps2 is None else dec_dps2
        return await self._command(Command.MOVE_ABS, _mdeg(deg), _rate(vel_dps, "velocity"),
                                   _rate(acc_dps2, "acceleration"), _rate(dec, "deceleration"))

    async def start_move_rel(self, delta_deg: float, vel_dps: float = 30.0, acc_dps2: float = 60.0,
                             dec_dps2: float | None = None) -> AxisStatus:
        """Start a relative move (does not wait)."""
        dec = acc_dps2 if dec_dps2 is None else dec_dps2
        return await self._command(Command.MOVE_REL, _mdeg(delta_deg), _rate(vel_dps, "velocity"),
                                   _rate(acc_dps2, "acceleration"), _rate(dec, "deceleration"))

    async def move_abs(self, deg: float, vel_dps: float = 30.0, acc_dps2: float = 60.0,
                       dec_dps2: float | None = None, timeout: float | None = None) -> AxisStatus:
        """Move to ``deg`` and wait until in position (timeout from the trapezoid plus margin)."""
        st = await self.start_move_abs(deg, vel_dps, acc_dps2, dec_dps2)
        t = timeout if timeout is not None else (
            trapezoid_time(deg - st.position_deg, vel_dps, acc_dps2, dec_dps2) * 1.2 + SETTLE_MARGIN)
        return await self.wait_in_position(t)

    async def move_rel(self, delta_deg: float, vel_dps: float = 30.0, acc_dps2: float = 60.0,
                       dec_dps2: float | None = None, timeout: float | None = None) -> AxisStatus:
        """Move by ``delta_deg`` and wait until in position."""
        await self.start_move_rel(delta_deg, vel_dps, acc_dps2, dec_dps2)
        t = timeout if timeout is not None else (
            trapezoid_time(delta_deg, vel_dps, acc_dps2, dec_dps2) * 1.2 + SETTLE_MARGIN)
        return await self.wait_in_position(t)

    async def wait_in_position(self, timeout: float, trace: list[tuple[float, float, float]] | None = None,
                               poll_interval: float | None = None) -> AxisStatus:
        """Poll until MOVING = 0 and IN_POSITION = 1 (AxisFault on FAULT, MoveTimeout at the deadline).

        Call only after a command was accepted (CMD_COUNT changed): the controller clears
        IN_POSITION synchronously on acceptance, so what is read afterwards is never stale.
        With ``trace``, every poll appends (time.monotonic() before the request, after the reply,
        encoder degrees): the controller latched the position somewhere in between.
        """
        deadline = time.monotonic() + timeout
        interval = self.poll_interval if poll_interval is None else poll_interval
        while True:
            t0 = time.monotonic()
            st = await self.status()
            if trace is not None:
                trace.append((t0, time.monotonic(), st.position_deg))
            if st.fault:
                raise AxisFault(self.name, st.fault_code)
            if not st.moving and st.in_position:
                return st
            if not st.moving and not st.enabled:
                raise AxisError(self.name, "disabled while waiting for position")
            if time.monotonic() >= deadline:
                raise MoveTimeout(
                    self.name, f"not in position after {timeout:.1f} s (at {st.position_deg:.3f} deg, "
                               f"demand {st.demand_deg:.3f}, flags {'|'.join(st.flags)})")
            await asyncio.sleep(interval)


# --------------------------------------------------------------------------------------------------
# Turntable
# --------------------------------------------------------------------------------------------------

AXIS_ORDER = ("z", "y", "x")  # psi (outer), theta (middle), phi (inner)


class Turntable:
    """Three axes; ``url`` is one bus for all (gateway or RS-485 line) or a mapping axis -> URL.

    Axes whose URLs are equal share one bus (one connection, requests serialised by pymodbus).
    """

    def __init__(self, url: str | Mapping[str, str], units: Mapping[str, int] | None = None, *,
                 timeout: float = 0.3, low_word_first: bool = False,
                 poll_interval: float = POLL_INTERVAL) -> None:
        units = dict(units or AXIS_UNITS)
        urls = {name: url for name in AXIS_ORDER} if isinstance(url, str) else dict(url)
        missing = [n for n in AXIS_ORDER if n not in urls or n not in units]
        if missing:
            raise ValueError(f"no URL or unit for axis {', '.join(missing)}")
        self.buses: dict[str, ModbusBus] = {}
        for u in dict.fromkeys(urls.values()):
            self.buses[u] = ModbusBus(u, timeout=timeout)
        self.axes: dict[str, Axis] = {
            n: Axis(n, units[n], self.buses[urls[n]], low_word_first=low_word_first,
                    poll_interval=poll_interval)
            for n in AXIS_ORDER
        }

    async def __aenter__(self) -> Turntable:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def connect(self) -> dict[str, AxisIdentity]:
        """Open every bus and check every axis's identity."""
        for bus in self.buses.values():
            await bus.connect()
        return {n: await a.connect() for n, a in self.axes.items()}

    async def close(self) -> None:
        """Close the buses (does not stop the axes: call stop_all first if they move)."""
        for bus in self.buses.values():
            bus.close()

    async def _each(self, coro_fn) -> list:
        """Run ``coro_fn(axis)`` on all axes concurrently; on the first error stop all and raise."""
        tasks = [asyncio.ensure_future(coro_fn(a)) for a in self.axes.values()]
        try:
            return list(await asyncio.gather(*tasks))
        except BaseException as exc:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self._stop_after(exc)
            raise

    async def _stop_after(self, exc: BaseException) -> None:
        """Stop every axis after an error, skipping an axis that just proved unreachable (its
        timeouts would only delay reporting; a real table relies on the watchdog there)."""
        skip = exc.axis if isinstance(exc, AxisUnreachable) else None
        await self._all(lambda a: a.stop(), raise_errors=False, skip=skip)

    async def enable_all(self) -> None:
        """ENABLE every axis."""
        for a in self.axes.values():
            await a.enable()

    async def disable_all(self) -> None:
        """DISABLE every axis (tries all, raises the first error)."""
        await self._all(lambda a: a.disable())

    async def reset_faults(self) -> None:
        """RESET_FAULT on every axis that reports a fault."""
        for a in self.axes.values():
            if (await a.status()).fault:
                await a.reset_fault()

    async def home_all(self, vel_dps: float = 10.0, acc_dps2: float = 20.0, timeout: float | None = None) -> None:
        """Home all three axes at once and wait for all (timeout: one turn plus margin)."""
        t = timeout if timeout is not None else trapezoid_time(360, vel_dps, acc_dps2) * 1.2 + SETTLE_MARGIN
        await self._each(lambda a: a.home(vel_dps, acc_dps2, timeout=t))

    async def move_to(self, psi: float, theta: float, phi: float, speed_dps: float = 30.0,
                      accel_dps2: float = 60.0, timeout: float | None = None) -> tuple[float, float, float]:
        """Move z, y, x to (psi, theta, phi) degrees together; return the encoder positions.

        All three moves are started first, then all are awaited; on any error (refusal, fault,
        timeout, unreachable axis) every axis is stopped and the error is raised.
        """
        targets = dict(zip(AXIS_ORDER, (psi, theta, phi)))
        started: dict[str, AxisStatus] = {}
        try:
            for n, a in self.axes.items():
                started[n] = await a.start_move_abs(targets[n], speed_dps, accel_dps2)
        except BaseException as exc:
            await self._stop_after(exc)
            raise
        t = timeout if timeout is not None else max(
            trapezoid_time(targets[n] - st.position_deg, speed_dps, accel_dps2) for n, st in started.items()
        ) * 1.2 + SETTLE_MARGIN
        sts = await self._each(lambda a: a.wait_in_position(t))
        return tuple(s.position_deg for s in sts)  # type: ignore[return-value]

    async def scan(self, axis: str, deg: float, speed_dps: float, accel_dps2: float = 60.0,
                   trace: list[tuple[float, float, float]] | None = None, timeout: float | None = None,
                   poll_interval: float = SCAN_POLL_INTERVAL) -> float:
        """Turn one axis (``"z"``, ``"y"`` or ``"x"``) to ``deg`` at ``speed_dps`` while the others hold,
        polling its encoder as often as ``poll_interval`` allows; each poll is appended to ``trace`` as
        (time.monotonic() before the request, after the reply, degrees) as it comes, so a caller keeps
        the positions up to an error. Returns
        the final encoder position. On any error (refusal, fault, timeout, unreachable axis) every axis
        is stopped and the error is raised."""
        a = self.axes[axis]
        try:
            st = await a.start_move_abs(deg, speed_dps, accel_dps2)
            t = timeout if timeout is not None else (
                trapezoid_time(deg - st.position_deg, speed_dps, accel_dps2) * 1.2 + SETTLE_MARGIN)
            st = await a.wait_in_position(t, trace=trace, poll_interval=poll_interval)
        except BaseException as exc:
            await asyncio.shield(self._stop_after(exc))  # a second cancellation must not cut the stop short
            raise
        return st.position_deg

    async def positions(self) -> tuple[float, float, float]:
        """Encoder positions (psi, theta, phi) in degrees."""
        return tuple([await a.position() for a in self.axes.values()])  # type: ignore[return-value]

    async def status_all(self) -> dict[str, AxisStatus]:
        """One status poll per axis."""
        return {n: await a.status() for n, a in self.axes.items()}

    async def _all(self, fn, raise_errors: bool = True, skip: str | None = None) -> list[Exception]:
        """Apply ``fn`` to every axis even if some fail; collect (and optionally raise) the errors."""
        results = await asyncio.gather(
            *(fn(a) for n, a in self.axes.items() if n != skip), return_exceptions=True)
        errors = [r for r in results if isinstance(r, Exception)]
        if errors and raise_errors:
            raise errors[0]
        return errors

    async def stop_all(self, raise_errors: bool = True) -> list[Exception]:
        """STOP every axis, trying all even if one fails (used on faults and aborts)."""
        return await self._all(lambda a: a.stop(), raise_errors)

    async def quick_stop_all(self, raise_errors: bool = True) -> list[Exception]:
        """QUICK_STOP every axis, trying all even if one fails."""
        return await self._all(lambda a: a.quick_stop(), raise_errors)


__all__ = [
    "Axis", "AxisError", "AxisFault", "AxisIdentity", "AxisProtocolError", "AxisStatus",
    "AxisUnreachable", "CommandRefused", "MoveTimeout", "ProtocolMismatch", "Turntable",
    "trapezoid_time",
]
