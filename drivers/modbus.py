"""The one module that imports pymodbus: a small async Modbus client and a simulator-server adapter.

pymodbus's API moved a lot across 3.x (pinned: ``pymodbus[serial]==3.16.1``), so everything that
touches it lives here and the rest of the code sees plain Python: ``ModbusBus.read/write`` with
``list[int]`` registers and two error types, and on the server side a register handler that is an
ordinary function.

pymodbus quirks this module works around (3.16.1):

* The unit keyword is ``device_id=`` (it was ``slave=`` / ``unit=`` in older 3.x releases).
* Client defaults are a 3 s timeout and 3 retries, i.e. up to 12 s before a dead axis is noticed. We
  pass ``timeout=`` (it is both the connect and the response timeout) and ``retries=0`` and do the
  one retry here, where we know whether a retry is safe (a read is; a command write may not be).
* After ``retries + 3`` requests without an answer the client *closes the TCP connection*, which on a
  gateway would take the healthy axes down with the silent one. ``set_max_no_responses`` is raised
  so that one silent unit on a shared bus does not disconnect the others.
* ``reconnect_delay`` defaults to 0.1 s with a background reconnect task; we set it to 0 so nothing
  runs behind our back. The async client's ``execute`` is a plain function that raises
  ``ConnectionException`` synchronously when the transport is gone (it does not reconnect), so
  ``ModbusBus`` reconnects itself, once per attempt and bounded by the timeout.
* A late reply to a timed-out request is skipped by the TCP framer (transaction id mismatch) or
  logged and ignored when no request is pending.
* Server side: ``SimDevice.action`` must be an ``async def`` (checked with
  ``inspect.iscoroutinefunction``, so a ``functools.partial`` of a coroutine function is refused; we
  use a closure). It receives the *whole* register list of the device; for a read we fill the slice
  before pymodbus copies it out, for a write pymodbus stores the values after the action returns.
  Returning an ``ExcCodes`` member answers that exception.
* There is no supported way to make the server stay silent. Raising ``NoSuchIdException`` from the
  action, with the server built with ``ignore_missing_devices=True``, makes the request handler skip
  the reply. We use that to simulate a unit that does not answer on an RTU line.
* An exception raised in the action otherwise becomes exception 0x04 (device failure); a request
  for a unit id with no SimDevice (and no id 0 catch-all) also ends as 0x04 via a ``KeyError``.
* The listening socket is ``server.transport`` (an ``asyncio.Server``) once ``serve_forever(
  background=True)`` has returned; that is where the ephemeral port is read from.
* The request handler answers the request stored in ``self.last_pdu`` after the action; an action
  that awaits (sleeps) can have that overwritten by the next request on the same connection, so
  the actions here never await.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ConnectionException, ModbusException, NoSuchIdException
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from . import DriverError

log = logging.getLogger(__name__)

# pymodbus logs every timeout at ERROR level with a dump of the last frames, and the server logs
# a traceback for a request to a missing unit. Every such event reaches our callers as a typed error,
# so keep pymodbus quiet unless the application configured its logger itself.
if logging.getLogger("pymodbus").level == logging.NOTSET:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

#: Exception codes (Modbus application protocol spec) and their names, for messages.
EXCEPTION_NAMES: dict[int, str] = {
    0x01: "illegal function",
    0x02: "illegal data address",
    0x03: "illegal data value",
    0x04: "server device failure",
    0x05: "acknowledge",
    0x06: "server device busy",
    0x08: "memory parity error",
    0x0A: "gateway path unavailable",
    0x0B: "gateway target device failed to respond",
}
#: Exception replies that mean "the axis is not there" rather than "you asked something wrong".
UNREACHABLE_CODES = frozenset({0x04, 0x0A, 0x0B})

DEFAULT_TIMEOUT = 0.4  # s; a controller answers in a few ms, a gateway in well under 100 ms


# --------------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------------


class BusError(DriverError):
    """A Modbus transaction failed."""


class BusUnreachable(BusError):
    """No usable answer: timeout, connection lost, or exception 0x04 / 0x0A / 0x0B.

    ``code`` is the exception code when the cause was an exception reply, else ``None``.
    """

    def __init__(self, message: str, unit: int | None = None, code: int | None = None) -> None:
        super().__init__(message)
        self.unit = unit
        self.code = code


class BusExceptionReply(BusError):
    """The device answered a Modbus exception (a protocol error: bad address, value or function)."""

    def __init__(self, message: str, unit: int, function: int, code: int) -> None:
        super().__init__(message)
        self.unit = unit
        self.function = function
        self.code = code


def exception_text(code: int) -> str:
    """``0x02 illegal data address``."""
    return f"0x{code:02X} {EXCEPTION_NAMES.get(code, 'unknown exception')}"


# --------------------------------------------------------------------------------------------------
# Client
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BusURL:
    """A parsed bus address. Any URL may end in ``?timeout=<s>``: the answer time allowed per request
    (e.g. a slow RS-485 gateway), instead of the driver's own (0.3-0.5 s)."""

    kind: str  # "tcp", "rtu+tcp" or "serial"
    host: str = ""
    port: int = 502
    device: str = ""
    baud: int = 115200
    parity: str = "N"
    stopbits: int = 1
    timeout: float | None = None

    @classmethod
    def parse(cls, url: str) -> BusURL:
        """Parse ``tcp://h:p``, ``rtu+tcp://h:p``, ``serial:///dev/ttyX?baud=..`` or a device path."""
        if "://" not in url:  # a bare device path or COM port: RS-485 RTU at the default baud
            if re.fullmatch(r"[A-Za-z0-9.-]+:\d+", url):  # (taken for a device path, it failed "cannot connect")
                raise ValueError(f"{url!r} is a host and port without a scheme; give tcp://{url} (or rtu+tcp://{url} "
                                 "for RTU frames through a gateway)")
            return cls(kind="serial", device=url)
        parts = urlsplit(url)
        scheme = parts.scheme.lower()
        q = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
        if scheme in ("tcp", "modbus+tcp", "rtu+tcp", "rtu-over-tcp"):
            _known_keys(url, q, ("timeout",))
            if not parts.hostname:
                raise ValueError(f"no host in Modbus URL {url!r}")
            kind = "rtu+tcp" if scheme.startswith("rtu") else "tcp"
            if parts.port is None:  # (the driver tried 502 and said only "cannot connect"; the API took it)
                raise ValueError(f"no port in Modbus URL {url!r}; give {kind}://{parts.hostname}:PORT (Modbus TCP's "
                                 "usual port is 502)")
            return cls(kind=kind, host=parts.hostname, port=parts.port, timeout=_timeout(url, q))
        if scheme in ("serial", "rtu"):
            _known_keys(url, q, ("baud", "parity", "stopbits", "timeout"))
            device = parts.path or parts.netloc
            if not device:
                raise ValueError(f"no device in Modbus URL {url!r}")
            parity = q.get("parity", "N").upper()
            if parity not in ("N", "E", "O"):
                raise ValueError(f"parity in Modbus URL {url!r}: expected N, E or O, got {q['parity']!r}")
            return cls(kind="serial", device=device, baud=_whole(url, q, "baud", "115200", (1200, 4_000_000)),
                       parity=parity, stopbits=_whole(url, q, "stopbits", "1", (1, 2)), timeout=_timeout(url, q))
        raise ValueError(f"unsupported Modbus URL scheme {scheme!r} in {url!r}")


def _known_keys(url: str, query: dict[str, str], known: tuple[str, ...]) -> None:
    unknown = sorted(set(query) - set(known))
    if unknown:
        raise ValueError(f"unknown option {', '.join(unknown)} in Modbus URL {url!r} (known: {', '.join(known)})")


def _whole(url: str, query: dict[str, str], key: str, default: str, bounds: tuple[int, int]) -> int:
    text = query.get(key, default)
    if not text.isdigit() or not bounds[0] <= int(text) <= bounds[1]:
        raise ValueError(f"{key} in Modbus URL {url!r}: expected a whole number from {bounds[0]} to {bounds[1]}, got {text!r}")
    return int(text)


def _timeout(url: str, query: dict[str, str]) -> float | None:
    if "timeout" not in query:
        return None
    try:
        t = float(query["timeout"])
    except ValueError:
        t = float("nan")
    if not 0.01 <= t <= 10:  # also refuses nan
        raise ValueError(f"timeout in Modbus URL {url!r}: expected seconds between 0.01 and 10, got {query['timeout']!r}")
    return t


class ModbusBus:
    """One async Modbus client: a TCP connection (Modbus TCP or RTU framing) or an RS-485 line.

    All units on the same gateway or line share one bus; pymodbus serialises the requests.
    Reads are retried once; writes are retried once only when ``retry=True`` (the caller knows
    whether repeating the write is harmless).
    """

    def __init__(self, url: str, timeout: float = DEFAULT_TIMEOUT) -> None:
        self.url = url
        self.addr = BusURL.parse(url)
        self.timeout = timeout if self.addr.timeout is None else self.addr.timeout  # the URL's own wins
        a = self.addr
        # reconnect_delay=0: no background reconnect task; execute() reconnects on demand.
        if a.kind == "serial":
            self._client: AsyncModbusSerialClient | AsyncModbusTcpClient = AsyncModbusSerialClient(
                a.device, framer=FramerType.RTU, baudrate=a.baud, parity=a.parity,
                stopbits=a.stopbits, timeout=self.timeout, retries=0, reconnect_delay=0,
            )
        else:
            framer = FramerType.RTU if a.kind == "rtu+tcp" else FramerType.SOCKET
            self._client = AsyncModbusTcpClient(
                a.host, port=a.port, framer=framer, timeout=self.timeout, retries=0, reconnect_delay=0,
            )
        # Do not let silent units close the shared connection (see the module docstring).
        self._client.set_max_no_responses(1 << 30)

    async def connect(self) -> None:
        """Open the connection; raise ``BusUnreachable`` if that fails within the timeout."""
        try:
            ok = await asyncio.wait_for(self._client.connect(), self.timeout * 2 + 0.2)
        except (asyncio.TimeoutError, OSError) as exc:
            raise BusUnreachable(f"{self.url}: cannot connect ({exc})") from exc
        if not ok:
            raise BusUnreachable(f"{self.url}: cannot connect")

    @property
    def connected(self) -> bool:
        """Whether the transport is open."""
        return bool(self._client.connected)

    def close(self) -> None:
        """Close the connection (idempotent)."""
        self._client.close()

    async def read(self, unit: int, addr: int, count: int, retry: bool = True) -> list[int]:
        """Read ``count`` holding registers (FC03) from ``addr`` of ``unit``."""
        what = f"unit {unit}: read 0x{addr:04X}+{count}"
        pdu = await self._execute(
            what, unit, retry,
            lambda: self._client.read_holding_registers(addr, count=count, device_id=unit),
        )
        regs = list(pdu.registers)
        if len(regs) != count:
            raise BusUnreachable(f"{what}: {len(regs)} registers in the reply", unit)
        return regs

    async def write(self, unit: int, addr: int, values: Sequence[int], retry: bool = True) -> None:
        """Write registers: FC06 for one value, FC16 for several."""
        vals = [int(v) & 0xFFFF for v in values]
        what = f"unit {unit}: write 0x{addr:04X}+{len(vals)}"
        if len(vals) == 1:
            await self._execute(
                what, unit, retry,
                lambda: self._client.write_register(addr, vals[0], device_id=unit),
            )
        else:
            await self._execute(
                what, unit, retry,
                lambda: self._client.write_registers(addr, vals, device_id=unit),
            )

    async def _execute(self, what: str, unit: int, retry: bool, call: Callable) -> object:
        attempts = 2 if retry else 1
        last: BusUnreachable | None = None
        for _ in range(attempts):
            # pymodbus bounds the wait itself; the outer wait_for is a belt for the braces (e.g. a
            # reconnect attempt inside execute()). The transaction is shielded: if our caller is
            # cancelled, the request still runs to its reply or timeout while holding pymodbus's
            # lock, so its late reply cannot be taken for the next request's (RTU has no
            # transaction id to tell them apart).
            if not self._client.connected:
                # The async client does not reconnect by itself (execute() raises at once when the
                # transport is gone), so try once here, bounded by the timeout.
                try:
                    await self.connect()
                except BusUnreachable as exc:
                    last = BusUnreachable(f"{what}: {exc}", unit)
                    continue
            try:
                task = asyncio.ensure_future(asyncio.wait_for(call(), self.timeout * 3 + 0.5))
                task.add_done_callback(_consume)
                pdu = await asyncio.shield(task)
            except (ConnectionException, asyncio.TimeoutError, OSError) as exc:
                last = BusUnreachable(f"{what}: no connection ({exc})", unit)
                continue
            except ModbusException as exc:  # ModbusIOException: no (valid) reply in time
                last = BusUnreachable(f"{what}: no reply ({exc})", unit)
                continue
            if pdu.isError():
                code = int(getattr(pdu, "exception_code", 0))
                msg = f"{what}: Modbus exception {exception_text(code)}"
                if code in UNREACHABLE_CODES:
                    last = BusUnreachable(msg, unit, code)
                    continue
                raise BusExceptionReply(msg, unit, pdu.function_code & 0x7F, code)
            return pdu
        assert last is not None
        raise last


def _consume(task: asyncio.Future) -> None:
    """Retrieve a shielded transaction's outcome so asyncio does not warn when nobody awaited it."""
    if not task.cancelled():
        task.exception()


# --------------------------------------------------------------------------------------------------
# Server (simulators and tests)
# --------------------------------------------------------------------------------------------------


class ExceptionReply(Exception):
    """Raised by a register handler to answer a Modbus exception with ``code``."""

    def __init__(self, code: int) -> None:
        super().__init__(exception_text(code))
        self.code = code


class NoReply(Exception):
    """Raised by a register handler to send no reply at all (a unit that does not answer)."""


#: handler(address, count, values): a read has ``values=None`` and returns ``count`` registers;
#: a write gets the values and returns None. Raise ExceptionReply or NoReply instead of answering.
RegisterHandler = Callable[[int, int, "list[int] | None"], "list[int] | None"]


def sim_device(unit: int, blocks: Sequence[tuple[int, int, bool]], handler: RegisterHandler) -> SimDevice:
    """A simulated unit serving the holding-register ``blocks`` (address, count, read-only).

    Addresses outside the blocks, and writes to read-only blocks, are answered with exception 0x02
    by pymodbus before ``handler`` is called.
    """
    simdata = [
        SimData(address=a, count=n, datatype=DataType.REGISTERS, readonly=ro) for a, n, ro in blocks
    ]

    async def action(fc: int, start: int, address: int, count: int, registers: list[int],
                     set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        # Never await in here (see the module docstring).
        try:
            if set_values is None:
                regs = handler(address, count, None)
                assert regs is not None and len(regs) == count
                registers[address - start: address - start + count] = [r & 0xFFFF for r in regs]
            else:
                handler(address, count, [int(v) for v in set_values])
        except ExceptionReply as exc:
            return ExcCodes(exc.code)
        except NoReply:
            # With ignore_missing_devices=True the request handler sends nothing for this.
            raise NoSuchIdException(f"unit {unit} silent") from None
        return None

    return SimDevice(id=unit, simdata=simdata, action=action)


@dataclass
class ServerHandle:
    """A running simulator server and the port it listens on."""

    server: ModbusTcpServer
    port: int


async def start_server(devices: list[SimDevice], port: int = 0, framer: str = "tcp",
                       host: str = "127.0.0.1") -> ServerHandle:
    """Start a Modbus server for ``devices`` on (host, port); port 0 picks a free one.

    ``framer``: ``"tcp"`` (Modbus TCP, MBAP header) or ``"rtu"`` (RTU frames with CRC over a TCP
    socket, as a serial-device server passes them through). Must be called in a running loop.
    """
    if framer not in ("tcp", "rtu"):
        raise ValueError(f"framer must be 'tcp' or 'rtu', not {framer!r}")
    server = ModbusTcpServer(
        devices,
        framer=FramerType.RTU if framer == "rtu" else FramerType.SOCKET,
        address=(host, port),
        ignore_missing_devices=True,  # lets NoReply stay silent
    )
    await server.serve_forever(background=True)
    sockets = getattr(server.transport, "sockets", None)
    if not sockets:
        await server.shutdown()
        raise OSError(f"Modbus server did not start on {host}:{port}")
    return ServerHandle(server=server, port=int(sockets[0].getsockname()[1]))


async def stop_server(handle: ServerHandle) -> None:
    """Stop the server and drop its client connections."""
    await handle.server.shutdown()
