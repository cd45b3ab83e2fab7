"""A simulated `$PXDC` compass: the device's protocol logic (`CompassDevice`, no I/O) behind a pty pair or
a TCP port (`CompassSim`), streaming in simulated time, with a fault-injection side channel.

Device behaviour (PROTOCOLS.md), and the choices this simulator makes where the protocol is silent:

- Power-on defaults: RATE 20 Hz, AVG 1, 115200 baud, seq 0; the boot banner is printed at start
  (lost if nobody is connected yet, as on a real port).
- RAW lines are due every 1/rate simulated seconds (wall interval 1/(rate*time_scale)) and each is
  measured at its due time (the table's true angles then, from its history), so ``seq`` is a steady
  sample clock, as on a device. A loop late on a busy host catches up with the missed lines, which
  then reach the host late, as behind a busy host's serial stack; the station places each line on
  the sample clock and leaves out of a pose the lines measured before its acquisition began. A loop
  more than a second of simulated time behind skips the missed lines, and ``seq`` counts them (the
  host sees dropped samples). The line rate is capped by what the baud rate carries (baud/720
  lines/s, ~13 at 9600).
- AVG n: the world's ``read(t)`` is called n times at the sample's time (its noise makes them differ)
  and the mean is rounded to the nearest integer (half to even), temperature to 0.1 deg C.
  Counts at +-32767 set the saturation bits (b0 mag, b1 accel).
- Every command is answered: Q -> one RAW line, RATE/AVG/BAUD/RST -> ``ACK,<cmd>,<args>``, ID, CFG;
  NAK 1 for a missing/bad checksum, 2 for an unknown command, 3 for a bad argument. BAUD ACKs at the old
  rate and then switches. RST ACKs, prints the banner and restores the defaults (so does `reset`).
- Output never blocks: when the transport's buffer is full, whole lines are dropped.
"""

from __future__ import annotations

import asyncio
import logging
import os
import random
import tty
from collections.abc import Callable, Sequence

from drivers.protocol import AVG_RANGE, BAUDS, DEFAULT_BAUD, MAX_LINE, RATES_HZ, TALKER, Nak, banner, checksum, sentence
from drivers.sim.clock import SimClock
from physics.simulate import BITFLIP_BITS, flip_bit

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 20
DEFAULT_AVG = 1
#: Bytes a RAW line takes on the wire, in bits per byte (8N1): the line-rate cap is baud / LINE_BITS.
LINE_BITS = 72 * 10
#: Output queued beyond this (bytes) is dropped instead of blocking the simulator.
OUT_CAP = 16384

ReadFn = Callable[[float], tuple[Sequence[int], Sequence[int], float]]


class CompassDevice:
    """The compass's protocol logic: commands in, lines out through ``emit``. No I/O, no clock waits.

    ``read(t_sim) -> (mag, acc, temp_c)`` comes from the simulated world (with noise and quantisation).
    """

    def __init__(self, read: ReadFn, emit: Callable[[bytes], None], *, model: str, serial: str, firmware: str) -> None:
        self.read = read
        self.emit = emit
        self.model, self.serial, self.firmware = model, serial, firmware
        self.rate_hz = DEFAULT_RATE_HZ
        self.avg = DEFAULT_AVG
        self.baud = DEFAULT_BAUD
        self.seq = 0
        #: patterns of the next RAW lines to corrupt (fault ``bad_readings``): "zeros", "random" or "bitflip"
        self.bad: list[str] = []
        self._bad_rng = random.Random(serial)
        self._inbuf = b""

    def power_on(self) -> None:
        """Defaults restored, seq from 0, banner printed."""
        self.rate_hz, self.avg, self.baud, self.seq = DEFAULT_RATE_HZ, DEFAULT_AVG, DEFAULT_BAUD, 0
        self.emit(banner(self.model, self.firmware, self.serial))

    def line_rate(self) -> float:
        """RAW lines per simulated second: the configured rate, capped by what the baud rate carries."""
        return min(float(self.rate_hz), self.baud / LINE_BITS)

    def raw_line(self, t_sim: float) -> bytes:
        """One RAW sentence for simulated time ``t_sim`` (advances seq)."""
        n = self.avg
        if n == 1:
            m, a, temp = self.read(t_sim)
            mag, acc = [int(v) for v in m], [int(v) for v in a]
        else:
            sm, sa, st = [0, 0, 0], [0, 0, 0], 0.0
            for _ in range(n):
                m, a, temp = self.read(t_sim)
                for i in range(3):
                    sm[i] += m[i]
                    sa[i] += a[i]
                st += temp
            mag, acc, temp = [round(v / n) for v in sm], [round(v / n) for v in sa], st / n
        if self.bad:  # a checksummed but wrong reading: a brown-out's zeros, a corrupted value, a flipped bit
            pattern = self.bad.pop(0)
            if pattern == "zeros":
                mag = [0, 0, 0]
            elif pattern == "bitflip":  # one bit of one axis's int16 count (as physics.simulate.garble)
                axis = self._bad_rng.randrange(3)
                mag[axis] = int(flip_bit(mag[axis], self._bad_rng.randrange(*BITFLIP_BITS)))
            else:
                mag = [self._bad_rng.randint(-32767, 32767) for _ in range(3)]
        status = 0
        mag = [max(-32767, min(32767, v)) for v in mag]
        acc = [max(-32767, min(32767, v)) for v in acc]
        if any(abs(v) >= 32767 for v in mag):
            status |= 1
        if any(abs(v) >= 32767 for v in acc):
            status |= 2
        seq, self.seq = self.seq, (self.seq + 1) & 0xFFFF
        t10 = max(-550, min(1500, round(temp * 10)))
        return sentence("RAW", seq, *mag, *acc, t10, f"{status:X}")

    # -- host input ------------------------------------------------------------------------------

    def feed(self, data: bytes, t_sim: float) -> None:
        """Bytes from the host; complete lines are executed as commands."""
        buf = (self._inbuf + data).replace(b"\r", b"\n")
        *lines, rest = buf.split(b"\n")
        self._inbuf = rest if len(rest) <= MAX_LINE else b""  # an overlong input line is dropped
        for line in lines:
            if line and len(line) <= MAX_LINE:
                self._command(line, t_sim)

    def _command(self, line: bytes, t_sim: float) -> None:
        i = line.rfind(b"$")
        if i < 0:
            return  # not a sentence: a real device ignores line noise
        line = line[i:]
        star = line.rfind(b"*")
        body = line[1:star] if star > 0 else line[1:]
        f = body.split(b",")
        cmd = f[1].decode("ascii", "replace") if len(f) > 1 else "?"
        hh = line[star + 1 :] if star > 0 else b""
        try:
            ok = len(hh) == 2 and int(hh, 16) == checksum(body) and hh.isalnum()
        except ValueError:
            ok = False
        if not ok:
            self.emit(sentence("NAK", cmd, int(Nak.BAD_CHECKSUM)))
            return
        if f[0] != TALKER.encode() or len(f) < 2:
            self.emit(sentence("NAK", cmd, int(Nak.UNKNOWN_COMMAND)))
            return
        args = [a.decode("ascii", "replace") for a in f[2:]]
        handler = {
            "Q": self._q, "RATE": self._rate, "AVG": self._avg, "ID": self._id,
            "CFG": self._cfg, "BAUD": self._baud, "RST": self._rst,
        }.get(cmd)
        if handler is None:
            self.emit(sentence("NAK", cmd, int(Nak.UNKNOWN_COMMAND)))
        elif not handler(args, t_sim):
            self.emit(sentence("NAK", cmd, int(Nak.BAD_ARGUMENT)))

    @staticmethod
    def _int_arg(args: list[str], allowed: Callable[[int], bool]) -> int | None:
        if len(args) != 1 or not args[0].isdigit():
            return None
        v = int(args[0])
        return v if allowed(v) else None

    def _q(self, args: list[str], t: float) -> bool:
        if args:
            return False
        self.emit(self.raw_line(t))
        return True

    def _rate(self, args: list[str], t: float) -> bool:
        v = self._int_arg(args, lambda x: x in RATES_HZ)
        if v is None:
            return False
        self.rate_hz = v
        self.emit(sentence("ACK", "RATE", v))
        return True

    def _avg(self, args: list[str], t: float) -> bool:
        v = self._int_arg(args, lambda x: AVG_RANGE[0] <= x <= AVG_RANGE[1])
        if v is None:
            return False
        self.avg = v
        self.emit(sentence("ACK", "AVG", v))
        return True

    def _id(self, args: list[str], t: float) -> bool:
        if args:
            return False
        self.emit(sentence("ID", self.model, self.serial, self.firmware))
        return True

    def _cfg(self, args: list[str], t: float) -> bool:
        if args:
            return False
        self.emit(sentence("CFG", f"RATE={self.rate_hz}", f"AVG={self.avg}", f"BAUD={self.baud}"))
        return True

    def _baud(self, args: list[str], t: float) -> bool:
        v = self._int_arg(args, lambda x: x in BAUDS)
        if v is None:
            return False
        self.emit(sentence("ACK", "BAUD", v))  # at the old rate, then switch
        self.baud = v
        return True

    def _rst(self, args: list[str], t: float) -> bool:
        if args:
            return False
        self.emit(sentence("ACK", "RST"))
        self.power_on()
        return True


# --------------------------------------------------------------------------------------------------
# Transports
# --------------------------------------------------------------------------------------------------


class _PtyTransport:
    """A pty pair; the driver opens the slave's name. The slave fd stays open here (reading the master
    raises EIO when no slave is open) and is raw (no echo, no LF -> CRLF)."""

    def __init__(self, on_data: Callable[[bytes], None]) -> None:
        self.on_data = on_data
        self.master = self.slave = -1
        self._pending = bytearray()
        self._writing = False
        self.dropped = 0

    async def open(self) -> str:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        asyncio.get_running_loop().add_reader(self.master, self._readable)
        return os.ttyname(self.slave)

    def _readable(self) -> None:
        try:
            data = os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return  # EIO: no slave open (cannot happen while we hold it)
        if data:
            self.on_data(data)

    def write(self, data: bytes) -> bool:
        if self.master < 0 or len(self._pending) + len(data) > OUT_CAP:
            self.dropped += 1
            return False
        self._pending += data
        self._flush()
        return True

    def _flush(self) -> None:
        if self.master < 0:
            return
        try:
            n = os.write(self.master, self._pending)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:
            n = len(self._pending)  # nobody can read it
        del self._pending[:n]
        loop = asyncio.get_running_loop()
        if self._pending and not self._writing:
            loop.add_writer(self.master, self._flush)
            self._writing = True
        elif not self._pending and self._writing:
            loop.remove_writer(self.master)
            self._writing = False

    def close(self) -> None:
        if self.master < 0:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(self.master)
        if self._writing:
            loop.remove_writer(self.master)
            self._writing = False
        self._pending.clear()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self.master = self.slave = -1


class _TcpTransport:
    """A TCP server on ``host:port`` (0: ephemeral), the way a serial-device server presents a port.
    Output goes to every connected client; input from any client is executed."""

    def __init__(self, on_data: Callable[[bytes], None], host: str, port: int) -> None:
        self.on_data = on_data
        self.host, self.port = host, port
        self._server: asyncio.base_events.Server | None = None
        self._clients: set[asyncio.StreamWriter] = set()
        self.dropped = 0

    async def open(self) -> str:
        self._server = await asyncio.start_server(self._serve, self.host, self.port, reuse_address=True)
        self.port = self._server.sockets[0].getsockname()[1]  # keep it: reappear binds the same port
        return f"socket://{self.host}:{self.port}"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._clients.add(writer)
        try:
            while data := await reader.read(4096):
                self.on_data(data)
        except (ConnectionError, OSError):
            pass
        finally:
            self._clients.discard(writer)
            writer.transport.abort()

    def write(self, data: bytes) -> bool:
        sent = False
        for w in list(self._clients):
            if w.transport.is_closing() or w.transport.get_write_buffer_size() > OUT_CAP:
                continue
            w.write(data)
            sent = True
        if not sent:
            self.dropped += 1
        return sent

    def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for w in list(self._clients):
            w.transport.abort()  # the driver must see the port go, not a half-open socket
        self._clients.clear()


# --------------------------------------------------------------------------------------------------
# The simulated device
# --------------------------------------------------------------------------------------------------


class CompassSim:
    """One simulated compass on a pty (``/dev/pts/N``) or TCP (``socket://127.0.0.1:PORT``) port.

    Run inside an asyncio loop: ``url = await sim.start("pty")`` ... ``await sim.stop()``. Fault
    injection (`go_silent`, `delay_output`, `garbage`, `fuse_next`, `truncate_next`, `reset`, `vanish`,
    `reappear`) is a side channel, never part of the protocol.
    """

    def __init__(
        self,
        read: ReadFn,
        clock: SimClock,
        *,
        model: str = "XDC-3",
        serial: str = "10234",
        firmware: str = "1.2.0",
        seed: int | None = None,
    ) -> None:
        self.clock = clock
        self.device = CompassDevice(read, self._out, model=model, serial=serial, firmware=firmware)
        self.url: str | None = None
        self.lines_sent = 0
        self._rng = random.Random(seed)
        self._transport: _PtyTransport | _TcpTransport | None = None
        self._kind = "pty"
        self._host, self._port = "127.0.0.1", 0
        self._task: asyncio.Task[None] | None = None
        self._silent = False
        self._fuse = False
        self._truncate = False
        self._held: list[bytes] | None = None  # lines held back by `delay_output`

    # -- life cycle ----------------------------------------------------------------------------

    async def start(self, transport: str = "pty", host: str = "127.0.0.1", port: int = 0) -> str:
        """Open the port (``"pty"`` or ``"tcp"``), power on (banner), start streaming; returns the URL."""
        if transport not in ("pty", "tcp"):
            raise ValueError(f"transport must be 'pty' or 'tcp', not {transport!r}")
        self._kind, self._host, self._port = transport, host, port
        self.url = await self._open_transport()
        self.device.power_on()
        self._task = asyncio.get_running_loop().create_task(self._stream(), name=f"compass sim {self.device.serial}")
        return self.url

    async def _open_transport(self) -> str:
        t: _PtyTransport | _TcpTransport
        if self._kind == "pty":
            t = _PtyTransport(self._on_input)
        else:
            t = _TcpTransport(self._on_input, self._host, self._port)
        url = await t.open()
        if isinstance(t, _TcpTransport):
            self._port = t.port
        self._transport = t
        return url

    async def stop(self) -> None:
        """Stop streaming and close the port."""
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    async def __aenter__(self) -> CompassSim:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # -- state, for tests and the station ------------------------------------------------------

    @property
    def rate_hz(self) -> int:
        """Configured RATE."""
        return self.device.rate_hz

    @property
    def avg(self) -> int:
        """Configured AVG."""
        return self.device.avg

    @property
    def baud(self) -> int:
        """Configured BAUD."""
        return self.device.baud

    @property
    def lines_dropped(self) -> int:
        """Writes dropped because the port's buffer was full or nobody was connected."""
        return self._transport.dropped if self._transport is not None else 0

    # -- streaming -----------------------------------------------------------------------------

    async def _stream(self) -> None:
        """Emit RAW lines on the simulated-time grid of the current rate."""
        next_t: float | None = None
        rate_used = 0.0
        while True:
            rate = self.device.line_rate()
            if rate <= 0:
                next_t = None
                await asyncio.sleep(0.02)
                continue
            now = self.clock.now()
            period = 1.0 / rate
            if next_t is None or rate != rate_used:
                next_t, rate_used = now + period, rate  # (re)start the grid: no burst of stale lines
            elif now - next_t > max(1.0, period):
                missed = int((now - next_t) / period)  # skipped, and counted by seq as dropped lines
                self.device.seq = (self.device.seq + missed) & 0xFFFF
                next_t += missed * period
            while next_t <= now:
                self._out(self.device.raw_line(next_t))
                next_t += period
                if self.device.line_rate() != rate_used:
                    break  # a reset inside the loop changed the rate
            await asyncio.sleep(min(self.clock.wall(next_t - self.clock.now()), 0.05))

    def _on_input(self, data: bytes) -> None:
        if self._silent:
            return  # a dead device hears nothing either
        self.device.feed(data, self.clock.now())

    def _out(self, line: bytes) -> None:
        """Every line the device prints passes here: the output-side faults act on it."""
        if self._silent or self._transport is None:
            return
        if self._fuse:
            self._fuse = False
            line = line.rstrip(b"\r\n")
        if self._truncate:
            self._truncate = False
            line = line[: max(1, len(line) // 2)]
        if self._held is not None:
            self._held.append(line)
            return
        if self._transport.write(line):
            self.lines_sent += 1

    # -- fault injection (side channel) --------------------------------------------------------

    def go_silent(self, on: bool = True) -> None:
        """Stop (or resume) all output and ignore input; the sample clock keeps running, so seq jumps."""
        self._silent = on

    def delay_output(self, seconds: float) -> None:
        """Hold every line back for ``seconds`` (wall), then deliver them in one burst: each is measured
        and numbered on time, as a device does, but reaches the host late, as behind a busy host or a
        USB adapter's latency timer."""
        if self._held is not None:
            return
        self._held = []

        def release() -> None:
            held, self._held = self._held or [], None
            for line in held:
                self._out(line)

        asyncio.get_running_loop().call_later(seconds, release)

    def garbage(self, nbytes: int = 64) -> None:
        """Inject ``nbytes`` random bytes (non-ASCII included) between two lines."""
        if self._transport is not None and not self._silent:
            self._transport.write(self._rng.randbytes(nbytes))

    def bad_readings(self, count: int, pattern: str = "zeros") -> None:
        """The next ``count`` RAW lines carry a wrong magnetometer reading with a valid checksum: all
        zeros (a brown-out), random int16 values (``pattern="random"``) or one bit of one axis flipped
        (``pattern="bitflip"``, a bit from 6 to 14: 64-16384 LSB)."""
        self.device.bad.extend([pattern] * count)

    def fuse_next(self) -> None:
        """The next line loses its CRLF, so it fuses with the one after."""
        self._fuse = True

    def truncate_next(self) -> None:
        """The next line is cut in half and has no line end."""
        self._truncate = True

    def reset(self) -> None:
        """A spontaneous reset: banner mid-stream, power-on defaults (20 Hz, AVG 1, 115200, seq 0)."""
        self.device.power_on()

    def vanish(self) -> None:
        """The port disappears: the pty pair or the TCP listener and its connections are closed."""
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    async def reappear(self) -> str:
        """Bring the port back. TCP: the same port, so the URL is unchanged; pty: a new /dev/pts name."""
        if self._transport is None:
            self.url = await self._open_transport()
        assert self.url is not None
        return self.url
