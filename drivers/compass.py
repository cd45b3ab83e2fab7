"""The compass driver: `$PXDC` ASCII sentences (PROTOCOLS.md) over a serial device, a pty or a TCP port
(pyserial URLs whose port has a file descriptor: ``/dev/ttyUSB0``, ``/dev/pts/N``, ``socket://host:port``).

Three layers:

- `SentenceParser`: a pure, incremental byte parser (no I/O) that turns whatever arrives on the wire
  into events (`CompassSample`, `Ack`, `NakReply`, `IdReply`, `CfgReply`, `TextLine`) and counts
  everything it had to throw away in a `CompassStats`.
- `Compass`: the async driver. pyserial opens the port (device paths, ``/dev/pts/N``,
  ``socket://host:port``); the event loop watches its descriptor and feeds the parser as bytes
  arrive. Commands are matched to their replies by command name, with a timeout and one retry.
- `SerialFixture`: several compasses (the slots of a batch-calibration fixture) driven concurrently.

Error policy, so that no received sample is ever lost: every sample is kept in the driver's history.
`Compass.read` returns exactly the samples it asked for, or raises an error whose ``samples`` attribute
holds the ones it did receive. `Compass.samples` (the async iterator) yields every sample received
before it raises.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import os
import logging
import re
import socket
import time
from collections.abc import AsyncIterator, Callable, Hashable, Mapping
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple, Union

import serial

from drivers import DriverError
from drivers.protocol import (
    AVG_RANGE,
    BAUDS,
    DEFAULT_BAUD,
    MAX_LINE,
    RATES_HZ,
    SEQ_MODULO,
    TALKER,
    Nak,
    sentence,
)

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------------

NAK_MEANING: dict[int, str] = {
    Nak.BAD_CHECKSUM: "bad checksum",
    Nak.UNKNOWN_COMMAND: "unknown command",
    Nak.BAD_ARGUMENT: "bad argument",
    Nak.BUSY: "busy",
}


class CompassError(DriverError):
    """Base of every compass error. ``samples`` holds the samples a failed read did receive."""

    def __init__(self, message: str, samples: list[CompassSample] | None = None) -> None:
        super().__init__(message)
        self.samples: list[CompassSample] = list(samples or [])


class CompassTimeout(CompassError):
    """No reply to a command (after the retry), or the stream went stale (no sample for 3 periods, at least 1 s)."""


class CompassNak(CompassError):
    """The compass refused a command: ``code`` is the NAK code, ``meaning`` its text."""

    def __init__(self, cmd: str, code: int) -> None:
        self.cmd = cmd
        self.code = code
        self.meaning = NAK_MEANING.get(code, "unknown NAK code")
        super().__init__(f"{cmd} refused: NAK {code} ({self.meaning})")


class CompassDisconnected(CompassError):
    """The port is gone (and reconnecting failed within the give-up time), or the driver was closed."""


# --------------------------------------------------------------------------------------------------
# Events
# --------------------------------------------------------------------------------------------------

#: |accel| outside this band (counts) marks a sample suspect. It is still delivered: the true scale is
#: what calibration measures. The band admits 1 g at the protocol's nominal 1 mg per count (1000) and
#: at the 16384 counts per g of the common 16-bit +-2 g parts; a dead or saturated sensor falls outside.
ACC_PLAUSIBLE_COUNTS = (500, 30000)


class CompassSample(NamedTuple):
    """One RAW sentence. Counts are raw (nominally 0.01 uT and 1 mg); ``t_host`` is time.monotonic()
    when the read that completed the line returned."""

    seq: int
    mag: tuple[int, int, int]
    acc: tuple[int, int, int]
    temp_c: float
    status: int
    t_host: float

    @property
    def acc_plausible(self) -> bool:
        """Whether |acc| is within `ACC_PLAUSIBLE_COUNTS` (1 g at any plausible scale)."""
        n2 = self.acc[0] ** 2 + self.acc[1] ** 2 + self.acc[2] ** 2
        return ACC_PLAUSIBLE_COUNTS[0] ** 2 <= n2 <= ACC_PLAUSIBLE_COUNTS[1] ** 2


class Ack(NamedTuple):
    """``$PXDC,ACK,<cmd>[,<args>]``."""

    cmd: str
    args: tuple[str, ...]


class NakReply(NamedTuple):
    """``$PXDC,NAK,<cmd>,<code>``."""

    cmd: str
    code: int


class IdReply(NamedTuple):
    """``$PXDC,ID,<model>,<serial>,<fw>``; ``serial`` is empty for a unit whose serial was never set."""

    model: str
    serial: str
    firmware: str


class CfgReply(NamedTuple):
    """``$PXDC,CFG,RATE=..,AVG=..,BAUD=..`` as a dict of ints."""

    values: dict[str, int]


class TextLine(NamedTuple):
    """A line of plain text (not a sentence): the boot banner or other unsolicited text, i.e. the
    device has reset. ``banner`` is True when it matched the boot banner's format."""

    text: str
    banner: bool


Event = Union[CompassSample, Ack, NakReply, IdReply, CfgReply, TextLine]


@dataclass
class CompassStats:
    """Counters of one link. The parser counts what it sees; the driver counts resets, timeouts,
    reconnects and unmatched replies."""

    lines: int = 0  # complete non-empty lines seen
    samples: int = 0  # RAW sentences accepted
    checksum_errors: int = 0  # bad, missing or non-hex checksum
    malformed: int = 0  # good checksum but wrong field count, empty/non-numeric field, unknown sentence
    implausible: int = 0  # RAW rejected by a range check (seq, int16 counts, temperature, status)
    broken: int = 0  # a sentence cut off by the next '$' (fused or truncated line): counted, not parsed
    overlong: int = 0  # lines over MAX_LINE bytes, dropped
    resyncs: int = 0  # times bytes were skipped to find the next '$' (garbage, opened mid-line)
    garbage_bytes: int = 0  # bytes skipped by those resyncs
    dropped_samples: int = 0  # gaps in seq (mod 65536)
    seq_jumps: int = 0  # seq went backwards or jumped by >= 32768: a restart, not counted as dropped
    acc_suspect: int = 0  # accepted samples whose |acc| is far from 1 g
    resets: int = 0  # banner or unsolicited text seen (settings re-applied)
    naks: int = 0
    timeouts: int = 0  # commands unanswered after the retry, and stale streams
    reconnects: int = 0
    unmatched_replies: int = 0  # replies nobody was waiting for (e.g. the late answer to a retried command)

    def as_dict(self) -> dict[str, int]:
        """The counters as a plain dict."""
        return asdict(self)


# --------------------------------------------------------------------------------------------------
# Parser
# --------------------------------------------------------------------------------------------------

_HEXDIGITS = b"0123456789abcdefABCDEF"
#: Two hex digits (either case) -> value. A dict lookup rejects anything int(x, 16) would tolerate
#: (signs, blanks, underscores) and is faster than parsing.
_HEX2: dict[bytes, int] = {bytes((a, b)): int(bytes((a, b)), 16) for a, b in itertools.product(_HEXDIGITS, repeat=2)}
_RAW_PREFIX = TALKER.encode() + b",RAW,"
_RAW_POS = len(_RAW_PREFIX)
_TALKER_B = TALKER.encode()
_RAW_RE = re.compile(
    rb"(\d{1,5}),(-?\d{1,6}),(-?\d{1,6}),(-?\d{1,6}),(-?\d{1,6}),(-?\d{1,6}),(-?\d{1,6}),(-?\d{1,5}),([0-9A-Fa-f]{1,4})"
)
_BANNER_RE = re.compile(rb"([A-Za-z0-9._-]+) compass fw (\S+) SN (\S+) ready")
# Text is printable ASCII with at least one letter and one space (the banner, "watchdog reset", ...);
# random garbage almost never is. Deleting the printable bytes must leave nothing.
_PRINTABLE = bytes(range(0x20, 0x7F)) + b"\t"
_LETTERS = re.compile(rb"[A-Za-z]")
_TEMP_RANGE_DC = (-550, 1500)  # 0.1 deg C: -55 .. 150 deg C
_ACC_LO2, _ACC_HI2 = ACC_PLAUSIBLE_COUNTS[0] ** 2, ACC_PLAUSIBLE_COUNTS[1] ** 2

# What to do with the bytes before the first '$' of the next line.
_PREFIX_NORMAL, _PREFIX_START, _PREFIX_OVERLONG = 0, 1, 2


def xor_checksum(body: bytes) -> int:
    """XOR of all bytes of ``body``, without a per-byte Python loop.

    Folding the whole line as one integer: after the shift by 8*w bits the low w bytes hold the XOR of
    the byte lanes; the high bits are never read again, so no masking is needed until the end.
    """
    if len(body) > 128:  # never for a valid line; the folds below cover 128 bytes
        return xor_checksum(body[:128]) ^ xor_checksum(body[128:])
    x = int.from_bytes(body, "little")
    x ^= x >> 512
    x ^= x >> 256
    x ^= x >> 128
    x ^= x >> 64
    x ^= x >> 32
    x ^= x >> 16
    x ^= x >> 8
    return x & 0xFF


def _text(b: bytes) -> str:
    # Never decode strictly: a checksum can pass with non-ASCII bytes in it.
    return b.decode("ascii", "replace")


class SentenceParser:
    """Incremental, pure parser of the compass byte stream. ``feed(bytes) -> list[Event]``.

    Line ends may be LF, CR or CRLF (split across reads or not). A ``$`` always starts a new sentence:
    whatever came before it on the same line is garbage (counted in ``resyncs``) or, if it was itself a
    sentence that lost its line end, a broken sentence (counted in ``broken``, never parsed). Lines
    longer than MAX_LINE are dropped (``overlong``). The first line after `reset_stream` is assumed to
    be cut (the port was opened mid-line): its bytes before the first ``$`` are skipped. A line without
    any ``$`` that looks like text (printable, with a letter and a space) is a `TextLine` (the device
    reset); otherwise it is garbage.

    RAW range checks (rejected and counted as ``implausible``): seq 0..65535, counts within int16,
    temperature -55..150 deg C, status <= 0xFF. A sample whose |acc| is far from 1 g (see
    `ACC_PLAUSIBLE_COUNTS`) is kept and counted in ``acc_suspect``. Seq gaps count as dropped samples;
    a jump of half the seq range or more (or a repeat) is a restart (``seq_jumps``) instead.
    """

    def __init__(self, stats: CompassStats | None = None) -> None:
        self.stats = stats if stats is not None else CompassStats()
        self._buf = b""
        self._prefix = _PREFIX_START
        self._last_seq: int | None = None

    def reset_stream(self) -> None:
        """Forget the partial line and the last seq, as after (re)opening the port mid-stream."""
        self._buf = b""
        self._prefix = _PREFIX_START
        self._last_seq = None

    def feed(self, data: bytes, t_host: float | None = None) -> list[Event]:
        """Parse ``data`` (any slice of the stream) and return the events of the lines it completed.

        ``t_host`` (default: time.monotonic() now) stamps every sample completed by this chunk.
        """
        if t_host is None:
            t_host = time.monotonic()
        if self._buf:
            data = self._buf + data
        if b"\r" in data:
            # CR, LF and CRLF all end a line; CRLF then yields an empty line, which is skipped.
            data = data.replace(b"\r", b"\n")
        lines = data.split(b"\n")
        rest = lines.pop()
        out: list[Event] = []
        for line in lines:
            if self._prefix:
                line = self._strip_prefix(line, out)
            if line:
                self._line(line, t_host, out)
        if len(rest) > MAX_LINE:
            rest = self._trim(rest, out)
        self._buf = rest
        return out

    # -- the line structure --------------------------------------------------------------------

    def _strip_prefix(self, line: bytes, out: list[Event]) -> bytes:
        """First line after a (re)open or an overlong drop: skip what precedes the first '$'."""
        mode, self._prefix = self._prefix, _PREFIX_NORMAL
        i = line.find(b"$")
        head = line if i < 0 else line[:i]
        if head and mode == _PREFIX_START:
            self.stats.resyncs += 1
            self.stats.garbage_bytes += len(head)
        return b"" if i < 0 else line[i:]

    def _line(self, line: bytes, t_host: float, out: list[Event]) -> None:
        self.stats.lines += 1
        if line[0] != 0x24:  # '$'
            i = line.find(b"$")
            if i < 0:
                self._nonsentence(line, out)
                return
            self._garbage(line[:i])
            line = line[i:]
        j = line.find(b"$", 1)
        if j >= 0:
            # Fused: a lost line end. Every part but the last ends at a '$', not a line end.
            parts = line.split(b"$")
            for part in parts[1:-1]:
                self._broken(part, out)
            line = b"$" + parts[-1]
        self._sentence(line, t_host, out)

    def _trim(self, rest: bytes, out: list[Event]) -> bytes:
        """The pending partial line has grown past MAX_LINE: settle what can be settled now."""
        if self._prefix == _PREFIX_OVERLONG:
            # Still inside a line already dropped as overlong: skip to the next '$' without recounting.
            i = rest.find(b"$")
            if i < 0:
                return b""
            rest, self._prefix = rest[i:], _PREFIX_NORMAL
        j = rest.rfind(b"$")
        if j > 0:
            head = rest[:j]
            if self._prefix:
                head = self._strip_prefix(head, out)
            elif head[0] != 0x24:
                i = head.find(b"$")
                self._garbage(head if i < 0 else head[:i])
                head = b"" if i < 0 else head[i:]
            for part in head.split(b"$")[1:]:
                self._broken(part, out)
            rest = rest[j:]
        if len(rest) > MAX_LINE:
            self.stats.overlong += 1
            self.stats.lines += 1  # counted now; its tail is dropped without counting it again
            self._prefix = _PREFIX_OVERLONG  # drop the rest of this line when its end arrives
            return b""
        return rest

    def _garbage(self, b: bytes) -> None:
        self.stats.resyncs += 1
        self.stats.garbage_bytes += len(b)

    def _broken(self, part: bytes, out: list[Event]) -> None:
        self.stats.broken += 1
        self._maybe_banner(part, out)

    def _maybe_banner(self, b: bytes, out: list[Event]) -> None:
        # A device that resets mid-line prints its banner right after the cut sentence.
        if b" ready" in b:
            m = _BANNER_RE.search(b)
            if m:
                self._emit_text(_text(m.group(0)), True, out)

    def _nonsentence(self, line: bytes, out: list[Event]) -> None:
        if not line.translate(None, _PRINTABLE) and b" " in line and _LETTERS.search(line):
            self._emit_text(_text(line.strip()), _BANNER_RE.fullmatch(line.strip()) is not None, out)
        else:
            self._garbage(line)

    def _emit_text(self, text: str, banner: bool, out: list[Event]) -> None:
        self._last_seq = None  # the device restarted: its seq restarts too
        out.append(TextLine(text, banner))

    # -- one sentence, starting with '$' -------------------------------------------------------

    def _sentence(self, line: bytes, t_host: float, out: list[Event]) -> None:
        st = self.stats
        n = len(line)
        if n > MAX_LINE:
            st.overlong += 1
            return
        star = n - 3
        if star < 1 or line[star] != 0x2A:  # '*'
            st.checksum_errors += 1  # missing, or not exactly two characters after '*'
            self._maybe_banner(line, out)
            return
        want = _HEX2.get(line[star + 1 :])
        body = line[1:star]
        if want is None or xor_checksum(body) != want:
            st.checksum_errors += 1
            return
        if body.startswith(_RAW_PREFIX):
            m = _RAW_RE.fullmatch(body, _RAW_POS)
            if m is None:
                st.malformed += 1
                return
            g = m.groups()
            seq = int(g[0])
            mx, my, mz, ax, ay, az = int(g[1]), int(g[2]), int(g[3]), int(g[4]), int(g[5]), int(g[6])
            temp = int(g[7])
            status = int(g[8], 16)
            if (
                seq >= SEQ_MODULO
                or not (-32768 <= mx <= 32767 and -32768 <= my <= 32767 and -32768 <= mz <= 32767)
                or not (-32768 <= ax <= 32767 and -32768 <= ay <= 32767 and -32768 <= az <= 32767)
                or not _TEMP_RANGE_DC[0] <= temp <= _TEMP_RANGE_DC[1]
                or status > 0xFF
            ):
                st.implausible += 1
                return
            last = self._last_seq
            if last is not None:
                gap = (seq - last - 1) & 0xFFFF
                if gap:
                    if gap < 0x8000:
                        st.dropped_samples += gap
                    else:
                        st.seq_jumps += 1
            self._last_seq = seq
            a2 = ax * ax + ay * ay + az * az
            if not _ACC_LO2 <= a2 <= _ACC_HI2:
                st.acc_suspect += 1
            st.samples += 1
            out.append(CompassSample(seq, (mx, my, mz), (ax, ay, az), temp / 10.0, status, t_host))
            return
        self._reply(body, out)

    def _reply(self, body: bytes, out: list[Event]) -> None:
        f = body.split(b",")
        kind = f[1] if len(f) > 1 else b""
        ev: Event | None = None
        if f[0] != _TALKER_B:
            ev = None
        elif kind == b"ACK" and len(f) >= 3 and f[2]:
            ev = Ack(_text(f[2]), tuple(_text(a) for a in f[3:]))
        elif kind == b"NAK" and len(f) == 4 and f[2] and f[3].isdigit():
            ev = NakReply(_text(f[2]), int(f[3]))
            self.stats.naks += 1
        elif kind == b"ID" and len(f) == 5 and f[2] and f[4]:  # an empty serial: never programmed (not identified)
            ev = IdReply(_text(f[2]), _text(f[3]), _text(f[4]))
        elif kind == b"CFG" and len(f) >= 3:
            values: dict[str, int] = {}
            for kv in f[2:]:
                k, eq, v = kv.partition(b"=")
                if not (k and eq and v.isdigit()):
                    break
                values[_text(k)] = int(v)
            else:
                ev = CfgReply(values)
        if ev is None:
            self.stats.malformed += 1
        else:
            out.append(ev)


# --------------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------------

def _close_port(ser: serial.SerialBase) -> None:
    """Close a port quickly. pyserial's ``socket://`` close() sleeps 0.3 s ("give the server some
    time"), which would stall every close and reconnect, so close its socket here."""
    sock = getattr(ser, "_socket", None)
    try:
        if sock is not None:
            ser._socket = None  # type: ignore[attr-defined]
            ser.is_open = False
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        else:
            ser.close()
    except Exception:  # closing a port that is already gone is not an error
        pass


_CLOSED, _OPEN, _RECONNECTING, _DEAD = "closed", "open", "reconnecting", "dead"
_LINK_LOST = object()  # resolves a pending command when the port goes away


class Compass:
    """Async driver of one compass on a pyserial URL (``/dev/ttyUSB0``, ``/dev/pts/3``,
    ``socket://host:port``).

    The event loop reads the port (``add_reader`` on its descriptor: everything that is there in one
    read, parsed on the spot), so there is no reader thread to hand lines over: at a simulated time
    scale of 20, eight compasses send 3200 lines a second, and reader threads handing them to the loop
    fought it and the fits for the interpreter (8 units at scale 20, paired runs: 121-124 -> 117-119 s
    of table time, 16-18 -> 11-14 s wall; benchmarks/procedure.py). If the port vanishes it reopens it with back-off
    (0.1, 0.2, 0.4 ... capped at 2 s) for up to ``give_up_s`` seconds and re-applies RATE and AVG;
    after that every call raises `CompassDisconnected`. A device reset (boot banner or other text seen)
    also re-applies RATE and AVG (the ones set through this driver; baud is not re-applied).

    Staleness: once the stream rate is known (`set_rate`, `config`), a read that sees no sample for
    ``stale_periods`` periods (at least ``stale_min_s``; counted from the read's start at the earliest)
    raises `CompassTimeout`. The period is that of
    the rate the link can carry (at 9600 baud the device caps at ~13 lines/s). The floor of 1 s is
    there because USB-serial adapters and a busy host deliver lines in bursts a few periods apart:
    a gap of 0.3 s is latency, a second of silence is a compass that stopped talking.
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = DEFAULT_BAUD,
        rate_hz: int | None = None,
        avg: int | None = None,
        cmd_timeout: float = 0.5,
        retries: int = 1,
        give_up_s: float = 5.0,
        stale_periods: float = 3.0,
        stale_min_s: float = 1.0,
        history: int = 200_000,
        name: str | None = None,
    ) -> None:
        """``rate_hz``/``avg``, if given, are applied at `open` (and re-applied after resets)."""
        self.url = url
        self.name = name or url
        self.baudrate = baudrate
        self.cmd_timeout = cmd_timeout
        self.retries = retries
        self.give_up_s = give_up_s
        self.stale_periods = stale_periods
        self.stale_min_s = stale_min_s
        self.stats = CompassStats()
        self.identity: tuple[str, str, str] | None = None
        self._want_rate = rate_hz
        self._want_avg = avg
        self._rate: int | None = None  # what we believe the device streams at (None: unknown)
        self._parser = SentenceParser(self.stats)
        self._history: collections.deque[CompassSample] = collections.deque(maxlen=history)
        self._n = 0  # samples received so far; sample i is _history[i - (_n - len(_history))]
        self._last_sample_t = 0.0
        self._stream_since = 0.0
        self._state = _CLOSED
        self._error: BaseException | None = None
        self._pending: dict[str, asyncio.Future[Any]] = {}
        self._cmd_lock = asyncio.Lock()
        self._changed = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ser: serial.SerialBase | None = None
        self._fd: int | None = None  # the descriptor the loop watches (None: not watching)
        self._tasks: set[asyncio.Task[None]] = set()
        # readers waiting for the sample count to reach a target (see _wait_until)
        self._sample_waiters: list[tuple[int, asyncio.Future[None]]] = []

    # -- life cycle ----------------------------------------------------------------------------

    def _open_port(self) -> serial.SerialBase:
        # Non-blocking: the loop reads the descriptor when it is readable, never waits in a read.
        return serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0, write_timeout=0.5)

    async def open(self) -> None:
        """Open the port (raise `CompassDisconnected` if it cannot) and apply RATE/AVG if given."""
        if self._state != _CLOSED:
            raise CompassError(f"{self.name}: already open")
        self._loop = asyncio.get_running_loop()
        try:
            ser = await asyncio.to_thread(self._open_port)
        except (serial.SerialException, OSError, ValueError) as e:
            raise CompassDisconnected(f"{self.name}: cannot open {self.url}: {e}") from e
        self._attach(ser)
        self._parser.reset_stream()
        self._state = _OPEN
        self._error = None
        self._stream_since = time.monotonic()
        try:
            if self._want_avg is not None:
                await self.set_averaging(self._want_avg)
            if self._want_rate is not None:
                await self.set_rate(self._want_rate)
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop reading (and reconnecting), close the port, fail pending commands and reads."""
        if self._state == _CLOSED and self._ser is None:
            return
        self._state = _CLOSED
        for t in list(self._tasks):
            t.cancel()
        self._detach()
        self._fail_pending()
        self._pulse()

    async def __aenter__(self) -> Compass:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        """True while the port is open (not while reconnecting)."""
        return self._state == _OPEN

    @property
    def rate_hz(self) -> int | None:
        """The stream rate the driver believes the device runs at (None: unknown)."""
        return self._rate

    # -- reading the port (on the loop) -----------------------------------------------------------

    def _attach(self, ser: serial.SerialBase) -> None:
        """Watch ``ser``'s descriptor on the loop; each readiness reads it. Raises `CompassDisconnected`
        (the port closed) for a port without a descriptor (``loop://``, ``rfc2217://``)."""
        try:
            fd = ser.fileno()
        except (AttributeError, OSError, ValueError) as e:  # io.UnsupportedOperation is both of the last
            _close_port(ser)
            raise CompassDisconnected(f"{self.name}: {self.url} has no file descriptor to read ({e}); use a "
                                      "device path, /dev/pts/N or socket://host:port") from e
        self._ser, self._fd = ser, fd
        asyncio.get_running_loop().add_reader(fd, self._on_readable)

    def _detach(self) -> None:
        """Stop watching the port and close it."""
        ser, fd, self._ser, self._fd = self._ser, self._fd, None, None
        if fd is not None and self._loop is not None and not self._loop.is_closed():
            self._loop.remove_reader(fd)
        if ser is not None:
            _close_port(ser)

    def _on_readable(self) -> None:
        """Read everything that is there (the descriptor itself: pyserial's read selects before and
        after its read, three system calls where one does, for every line), parse, handle."""
        fd = self._fd
        if fd is None:
            return
        try:
            data = os.read(fd, 65536)
        except (BlockingIOError, InterruptedError):
            return  # a spurious wake-up
        except OSError as e:  # pty: EIO once the device side is gone
            self._lost(e)
            return
        if not data:  # a closed socket or a hung-up pty
            self._lost(serial.SerialException("device reports readiness to read but returned no data"))
            return
        events = self._parser.feed(data)
        if events:
            self._on_events(events)

    def _lost(self, exc: BaseException) -> None:
        """The port went away: stop reading it and reconnect in the background."""
        self._detach()
        if self._state != _OPEN:
            return
        self._on_lost(exc)
        self._spawn(self._reconnect())

    async def _reconnect(self) -> None:
        """Reopen the port with back-off (0.1 s doubling to 2 s) for up to ``give_up_s``."""
        backoff, lost_at = 0.1, time.monotonic()
        while self._state == _RECONNECTING:
            left = self.give_up_s - (time.monotonic() - lost_at)
            if left <= 0:
                self._on_gave_up()
                return
            try:
                ser = await asyncio.to_thread(self._open_port)
                if self._state != _RECONNECTING:  # closed meanwhile
                    _close_port(ser)
                    return
                self._attach(ser)
            except (serial.SerialException, OSError, ValueError, CompassDisconnected):
                await asyncio.sleep(min(backoff, left))
                backoff = min(backoff * 2, 2.0)
                continue
            self._parser.reset_stream()  # (nothing is read before this callback returns)
            self._on_reconnected()

    # -- loop-side handlers (run in the event loop) ---------------------------------------------

    def _pulse(self) -> None:
        # Wake everyone waiting: asyncio.Event.set() resolves the current waiters; clear() re-arms.
        self._changed.set()
        self._changed.clear()
        self._wake_readers(None)

    def _wake_readers(self, n: int | None) -> None:
        """Wake the readers whose target sample count ``n`` has reached (None: all, on a change of state)."""
        if not self._sample_waiters:
            return
        waiting = []
        for target, fut in self._sample_waiters:
            if fut.done():
                continue
            if n is None or n >= target:
                fut.set_result(None)
            else:
                waiting.append((target, fut))
        self._sample_waiters = waiting

    def _resolve(self, key: str, ev: Any) -> None:
        fut = self._pending.get(key)
        if fut is not None and not fut.done():
            fut.set_result(ev)
        elif type(ev) is not CompassSample:
            self.stats.unmatched_replies += 1

    def _on_events(self, events: list[Event]) -> None:
        if self._state == _CLOSED:
            return
        got_sample = False
        for ev in events:
            t = type(ev)
            if t is CompassSample:
                self._history.append(ev)  # type: ignore[arg-type]
                self._n += 1
                self._last_sample_t = ev.t_host  # type: ignore[union-attr]
                got_sample = True
                if "Q" in self._pending:
                    self._resolve("Q", ev)
            elif t is Ack or t is NakReply:
                self._resolve(ev.cmd, ev)  # type: ignore[union-attr]
            elif t is IdReply:
                self._resolve("ID", ev)
            elif t is CfgReply:
                self._resolve("CFG", ev)
            elif t is TextLine:
                self._on_device_reset(ev)  # type: ignore[arg-type]
        if got_sample:
            # a reader wakes when its count is in, not on every line (a run of 8 units at time scale 20
            # receives 3200 lines a second; a wake-up per line per reader was most of the loop's work)
            self._wake_readers(self._n)

    def _on_device_reset(self, ev: TextLine) -> None:
        self.stats.resets += 1
        log.warning("%s: device reset (%r); re-applying settings", self.name, ev.text)
        self._rate = None  # power-on default until re-applied
        self._stream_since = time.monotonic()
        self._spawn(self._reapply())

    def _on_lost(self, exc: BaseException) -> None:
        log.warning("%s: port lost (%s); reconnecting", self.name, exc)
        self._state = _RECONNECTING
        self._error = exc
        for fut in self._pending.values():
            if not fut.done():
                fut.set_result(_LINK_LOST)
        self._pulse()

    def _on_reconnected(self) -> None:
        if self._state != _RECONNECTING:
            return
        self.stats.reconnects += 1
        self._state = _OPEN
        self._stream_since = time.monotonic()
        self._pulse()
        self._spawn(self._reapply())

    def _on_gave_up(self) -> None:
        if self._state == _CLOSED:
            return
        self._state = _DEAD
        self._fail_pending()
        self._pulse()

    def _fail_pending(self) -> None:
        for fut in self._pending.values():
            if not fut.done():
                fut.set_result(_LINK_LOST)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _reapply(self) -> None:
        """After a device reset or a reconnect: put back the settings made through this driver."""
        try:
            async with self._cmd_lock:
                if self._want_avg is not None:
                    await self._transact("AVG", (self._want_avg,))
                if self._want_rate is not None:
                    await self._transact("RATE", (self._want_rate,))
                    self._rate = self._want_rate
                    self._stream_since = time.monotonic()
        except CompassError as e:
            log.error("%s: could not re-apply settings: %s", self.name, e)

    # -- commands ------------------------------------------------------------------------------

    def _check_usable(self, samples: list[CompassSample] | None = None) -> None:
        if self._state == _CLOSED:
            raise CompassDisconnected(f"{self.name}: not open", samples)
        if self._state == _DEAD:
            raise CompassDisconnected(f"{self.name}: port gone and not back after {self.give_up_s} s ({self._error})", samples)

    def _write_sync(self, data: bytes) -> None:
        ser = self._ser
        if ser is None:
            raise serial.SerialException("port not open")
        ser.write(data)

    async def _wait_link(self, deadline: float) -> None:
        while True:
            self._check_usable()
            if self._state == _OPEN:
                return
            left = deadline - time.monotonic()
            if left <= 0:
                raise CompassDisconnected(f"{self.name}: port lost ({self._error}), still reconnecting")
            try:
                await asyncio.wait_for(self._changed.wait(), left)
            except asyncio.TimeoutError:
                pass

    async def _transact(self, cmd: str, args: tuple[object, ...], timeout: float | None = None) -> Any:
        """Send ``$PXDC,<cmd>,<args>`` and return the reply keyed by ``cmd``; retry once on a
        timeout, a lost link, or NAK 1 (bad checksum) / 4 (busy). Caller holds the command lock."""
        timeout = self.cmd_timeout if timeout is None else timeout
        line = sentence(cmd, *args)
        attempts = 1 + self.retries
        reason = "no reply"
        for attempt in range(attempts):
            await self._wait_link(time.monotonic() + max(timeout, self.give_up_s))
            fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
            self._pending[cmd] = fut
            try:
                try:
                    await asyncio.to_thread(self._write_sync, line)
                except (serial.SerialException, OSError) as e:
                    reason = f"write failed: {e}"
                    await asyncio.sleep(min(0.05, timeout))  # let the loop's read notice a lost port
                    continue
                try:
                    ev = await asyncio.wait_for(fut, timeout)
                except asyncio.TimeoutError:
                    reason = f"no reply within {timeout} s"
                    continue
            finally:
                if self._pending.get(cmd) is fut:
                    del self._pending[cmd]
            if ev is _LINK_LOST:
                reason = "port lost"
                self._check_usable()
                continue
            if type(ev) is NakReply:
                if ev.code in (Nak.BAD_CHECKSUM, Nak.BUSY) and attempt + 1 < attempts:
                    continue
                raise CompassNak(cmd, ev.code)
            return ev
        self.stats.timeouts += 1
        raise CompassTimeout(f"{self.name}: {cmd}: {reason} after {attempts} attempts")

    async def command(self, cmd: str, *args: object, timeout: float | None = None) -> Any:
        """Send any host command and return its reply event (`Ack`, `IdReply`, `CfgReply` or a
        `CompassSample` for Q). Raises `CompassNak`, `CompassTimeout`, `CompassDisconnected`."""
        self._check_usable()
        async with self._cmd_lock:
            return await self._transact(cmd, args, timeout)

    async def identify(self) -> tuple[str, str, str]:
        """``(model, serial, firmware)`` from ``$PXDC,ID``."""
        ev: IdReply = await self.command("ID")
        self.identity = (ev.model, ev.serial, ev.firmware)
        return self.identity

    async def set_rate(self, hz: int) -> None:
        """Set the stream rate (0 stops streaming); re-applied after resets and reconnects."""
        if hz not in RATES_HZ:
            raise ValueError(f"rate {hz} Hz not one of {RATES_HZ}")
        await self.command("RATE", hz)
        self._want_rate = self._rate = hz
        self._stream_since = time.monotonic()

    async def set_averaging(self, n: int) -> None:
        """Average ``n`` readings per sample; re-applied after resets and reconnects."""
        if not AVG_RANGE[0] <= n <= AVG_RANGE[1]:
            raise ValueError(f"averaging {n} outside {AVG_RANGE}")
        await self.command("AVG", n)
        self._want_avg = n

    async def set_baud(self, baud: int) -> None:
        """Switch the device's baud rate (it ACKs at the old rate), then the port's."""
        if baud not in BAUDS:
            raise ValueError(f"baud {baud} not one of {BAUDS}")
        await self.command("BAUD", baud)
        self.baudrate = baud
        ser = self._ser
        if ser is not None:
            await asyncio.to_thread(setattr, ser, "baudrate", baud)

    async def config(self) -> dict[str, int]:
        """The device's configuration from ``$PXDC,CFG``, e.g. ``{"RATE": 20, "AVG": 1, "BAUD": 115200}``."""
        ev: CfgReply = await self.command("CFG")
        if "RATE" in ev.values:
            if self._rate != ev.values["RATE"]:
                self._stream_since = time.monotonic()
            self._rate = ev.values["RATE"]
        return dict(ev.values)

    async def query(self, timeout: float | None = None) -> CompassSample:
        """One polled sample (``$PXDC,Q``). While streaming, the next sample to arrive answers it."""
        return await self.command("Q", timeout=timeout)

    # -- samples -------------------------------------------------------------------------------

    def _slice(self, start: int, stop: int) -> list[CompassSample]:
        first = self._n - len(self._history)
        start = max(start, first)  # beyond `history` samples back, they are gone
        return list(itertools.islice(self._history, start - first, stop - first))

    def _stale_at(self, since: float) -> float | None:
        """When the stream counts as stale: ``stale_periods`` periods (at least ``stale_min_s``) after
        the latest of the last sample, the start of streaming and ``since`` (the read's start, so a
        read always gives a resumed stream its three periods)."""
        if self._state != _OPEN or not self._rate:
            return None
        # The device caps its line rate at what the baud rate carries (~80 bytes of 10 bits a line).
        rate = min(self._rate, self.baudrate / 800.0)
        return max(self._last_sample_t, self._stream_since, since) + max(self.stale_periods / rate, self.stale_min_s)

    async def _wait_until(self, start: int, count: int, deadline: float, since: float) -> None:
        """Wait until ``count`` samples from index ``start`` are in, or raise with what did arrive."""
        while self._n - start < count:
            self._check_usable(self._slice(start, self._n))
            now = time.monotonic()
            stale = self._stale_at(since)
            if stale is not None and now >= stale:
                self.stats.timeouts += 1
                quiet = now - max(self._last_sample_t, self._stream_since)
                raise CompassTimeout(f"{self.name}: no sample for {quiet:.3f} s at {self._rate} Hz", self._slice(start, self._n))
            if now >= deadline:
                got = self._slice(start, self._n)
                if self._state == _RECONNECTING:
                    raise CompassDisconnected(f"{self.name}: port lost ({self._error}), still reconnecting", got)
                raise CompassTimeout(f"{self.name}: {len(got)} of {count} samples before the deadline", got)
            wake = deadline if stale is None else min(deadline, stale)
            fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            self._sample_waiters.append((start + count, fut))
            try:
                await asyncio.wait_for(fut, max(wake - now, 0.0) + 1e-4)
            except asyncio.TimeoutError:
                pass
            finally:
                self._sample_waiters = [w for w in self._sample_waiters if w[1] is not fut]

    def _default_timeout(self, n: int) -> float:
        rate = self._rate or self._want_rate or 1
        return 2.0 * n / rate + 1.0

    async def read(self, n: int, timeout: float | None = None) -> list[CompassSample]:
        """The next ``n`` samples read from the port after the call (lines the port held while the
        loop was busy count as read when the loop gets to them; the engine tells a pose's own lines
        by the compass's sample clock).

        Raises `CompassTimeout` (stale stream or deadline) or `CompassDisconnected`; the exception's
        ``samples`` holds the samples that did arrive. Default timeout: twice the time ``n`` samples
        take at the known rate, plus 1 s.
        """
        start, now = self._n, time.monotonic()
        deadline = now + (self._default_timeout(n) if timeout is None else timeout)
        await self._wait_until(start, n, deadline, now)
        return self._slice(start, start + n)

    async def samples(self, timeout: float = 1.0) -> AsyncIterator[CompassSample]:
        """Iterate samples as they arrive (from the call on). Every sample received is yielded before
        an error is raised; ``timeout`` bounds the wait for each next sample."""
        idx, since = self._n, time.monotonic()
        while True:
            if idx < self._n:
                stop = self._n  # samples arriving while we yield are picked up next round
                for s in self._slice(idx, stop):
                    yield s
                idx = stop
                continue
            await self._wait_until(idx, 1, time.monotonic() + timeout, since)

    def recent(self, n: int) -> list[CompassSample]:
        """The last ``n`` samples received (from the history), oldest first."""
        return self._slice(self._n - n, self._n)


# --------------------------------------------------------------------------------------------------
# SerialFixture: several units at once
# --------------------------------------------------------------------------------------------------


class FixtureError(CompassError):
    """Some slots failed; ``errors`` maps slot to its exception, ``results`` holds the slots that did not."""

    def __init__(self, what: str, errors: Mapping[Hashable, BaseException], results: Mapping[Hashable, Any]) -> None:
        self.errors = dict(errors)
        self.results = dict(results)
        detail = "; ".join(f"{k}: {e}" for k, e in self.errors.items())
        super().__init__(f"{what} failed on {len(self.errors)} slot(s): {detail}")


class SerialFixture:
    """The slots of a station's fixture, one `Compass` (and port) each, driven concurrently (the
    serial implementation of the `drivers.Fixture` role).

    Every ``*_all`` call runs on all slots at once and returns ``{slot: result}``; if any slot fails
    it raises `FixtureError` after all finished, carrying the per-slot errors and the other results
    (a failed read's own samples are on its exception's ``samples``).
    """

    def __init__(self, slots: Mapping[Hashable, str], **compass_kwargs: Any) -> None:
        """``slots`` maps a slot name to its URL; ``compass_kwargs`` go to every `Compass`."""
        self.compasses: dict[Hashable, Compass] = {
            slot: Compass(url, name=f"slot {slot}", **compass_kwargs) for slot, url in slots.items()
        }

    async def _all(self, what: str, fn: Callable[[Compass], Any]) -> dict[Hashable, Any]:
        slots = list(self.compasses)
        res = await asyncio.gather(*(fn(self.compasses[s]) for s in slots), return_exceptions=True)
        errors = {s: r for s, r in zip(slots, res) if isinstance(r, BaseException)}
        results = {s: r for s, r in zip(slots, res) if not isinstance(r, BaseException)}
        if errors:
            raise FixtureError(what, errors, results)
        return results

    async def open(self) -> None:
        """Open every slot; if any fails, close them all and raise `FixtureError`."""
        try:
            await self._all("open", lambda c: c.open())
        except FixtureError:
            await self.close()
            raise

    async def close(self) -> None:
        """Close every slot."""
        await asyncio.gather(*(c.close() for c in self.compasses.values()), return_exceptions=True)

    async def __aenter__(self) -> SerialFixture:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def identify_all(self) -> dict[Hashable, tuple[str, str, str]]:
        """``{slot: (model, serial, firmware)}``."""
        return await self._all("identify", lambda c: c.identify())

    async def set_rate_all(self, hz: int) -> None:
        """Set the stream rate on every slot."""
        await self._all("set_rate", lambda c: c.set_rate(hz))

    async def set_averaging_all(self, n: int) -> None:
        """Set averaging on every slot."""
        await self._all("set_averaging", lambda c: c.set_averaging(n))

    async def read_all(self, n: int, timeout: float | None = None) -> dict[Hashable, list[CompassSample]]:
        """The next ``n`` samples of every slot, read concurrently."""
        return await self._all("read", lambda c: c.read(n, timeout))
