"""The turntable driver: byte-level protocol scripts, integration against TableSim, and faults.

Plain pytest with ``asyncio.run`` (no pytest-asyncio); every test body runs under ``asyncio.wait_for``
so nothing can hang.
"""

from __future__ import annotations

import asyncio
import contextlib
import time

import pytest

from drivers.modbus import BusURL, ModbusBus
from drivers.protocol import Command, Reg, Status
from drivers.sim.clock import SimClock
from drivers.sim.turntable import AxisSim, TableSim
from drivers.turntable import (
    Axis,
    AxisFault,
    AxisProtocolError,
    AxisUnreachable,
    CommandRefused,
    ProtocolMismatch,
    Turntable,
    trapezoid_time,
)


def run(coro, timeout: float = 10.0):
    """Run a test coroutine with a hard deadline."""
    return asyncio.run(asyncio.wait_for(coro, timeout))


# ==================================================================================================
# (a) byte-level scripts
# ==================================================================================================


class ScriptServer:
    """A fake Modbus TCP device replaying an ordered script of (request bytes, reply bytes).

    A request that differs from the next expected one is recorded as an error and the connection is
    closed; a reply of ``None`` means "send nothing" (a timeout). ``check()`` fails on any error or
    on script entries that were never consumed.
    """

    def __init__(self, script: list[tuple[str, str | None]]) -> None:
        self.script = [(bytes.fromhex(q), None if r is None else bytes.fromhex(r)) for q, r in script]
        self.errors: list[str] = []
        self.pos = 0

    async def __aenter__(self) -> ScriptServer:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.server.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.server.wait_closed(), 1.0)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                head = await reader.readexactly(6)  # MBAP: tid, protocol id, length
                body = await reader.readexactly(int.from_bytes(head[4:6], "big"))
                req = head + body
                if self.pos >= len(self.script):
                    self.errors.append(f"unexpected request {req.hex(' ')} after the script ended")
                    break
                want, reply = self.script[self.pos]
                if req != want:
                    self.errors.append(f"request {self.pos}: got {req.hex(' ')}, want {want.hex(' ')}")
                    break
                self.pos += 1
                if reply is not None:
                    writer.write(reply)
                    await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    def check(self) -> None:
        assert not self.errors, self.errors
        assert self.pos == len(self.script), f"unconsumed script entries from {self.pos}"

    def axis(self, timeout: float = 0.3, **kw) -> Axis:
        return Axis("z", 1, ModbusBus(f"tcp://127.0.0.1:{self.port}", timeout=timeout), **kw)


# Identity block read (FC03, 0x0000 x 7), transaction 1, unit 1.
IDENT_REQ = "0001 0000 0006 01 03 0000 0007"
# PRODUCT_ID 0x5443, FW 1.2, SERIAL 20244417, AXIS_INDEX 1, COUNTS_PER_DEG 1000, PROTOCOL_VERSION 1
IDENT_OK = "0001 0000 0011 01 03 0E 5443 0102 0134E7C1 0001 03E8 0001"


def status_reply(tid: int, status: int, fault: int = 0, pos: int = 0, cmd_count: int = 0,
                 result: int = 0) -> str:
    """The reply to a 16-register status read, spelled out register by register."""
    regs = (f"{status:04X} {fault:04X} {pos & 0xFFFFFFFF:08X} 00000000 {pos & 0xFFFFFFFF:08X} 00000000 "
            f"{cmd_count:04X} {result:04X} 0000 00FA {pos % 360000:08X}")
    return f"{tid:04X} 0000 0023 01 03 20 {regs}"


def status_req(tid: int) -> str:
    return f"{tid:04X} 0000 0006 01 03 0010 0010"


def test_connect_reads_identity() -> None:
    async def body() -> None:
        async with ScriptServer([(IDENT_REQ, IDENT_OK)]) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            ident = await ax.connect()
            ax.bus.close()
            srv.check()
            assert ident.product_id == 0x5443 and ident.fw_version == "1.2"
            assert ident.serial_no == 20244417 and ident.counts_per_deg == 1000

    run(body())


def test_connect_refuses_wrong_scaling() -> None:
    bad = "0001 0000 0011 01 03 0E 5443 0102 0134E7C1 0001 0064 0001"  # COUNTS_PER_DEG = 100

    async def body() -> None:
        async with ScriptServer([(IDENT_REQ, bad)]) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            with pytest.raises(ProtocolMismatch, match="COUNTS_PER_DEG is 100"):
                await ax.connect()
            ax.bus.close()
            srv.check()

    run(body())


def test_status_poll_decodes_every_field() -> None:
    # STATUS READY|ENABLED|IN_POSITION|HOMED, ACTUAL_POS -12.345 deg, temperature 25.0 C.
    async def body() -> None:
        async with ScriptServer([(status_req(1), status_reply(1, 0x001B, pos=-12345, cmd_count=7))]) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            st = await ax.status()
            ax.bus.close()
            srv.check()
            assert st.flags == ("READY", "ENABLED", "IN_POSITION", "HOMED")
            assert st.position_deg == -12.345 and st.demand_deg == -12.345
            assert st.cmd_count == 7 and st.temperature_c == 25.0 and st.in_position and not st.moving

    run(body())


def test_move_abs_handshake_bytes() -> None:
    """CMD_COUNT before, one FC16 of 9 registers, CMD_COUNT changed and result 0, then poll until
    MOVING = 0 and IN_POSITION = 1."""
    script = [
        ("0001 0000 0006 01 03 001A 0001", "0001 0000 0005 01 03 02 0005"),  # CMD_COUNT = 5
        # FC16 0x0020 x9: target 90000 mdeg, vel 30000, acc 60000, dec 60000, COMMAND 1 (MOVE_ABS)
        ("0002 0000 0019 01 10 0020 0009 12 00015F90 00007530 0000EA60 0000EA60 0001",
         "0002 0000 0006 01 10 0020 0009"),
        (status_req(3), status_reply(3, 0x0017, pos=0, cmd_count=6)),  # accepted, MOVING
        (status_req(4), status_reply(4, 0x0017, pos=45000, cmd_count=6)),  # still MOVING
        (status_req(5), status_reply(5, 0x001B, pos=90000, cmd_count=6)),  # IN_POSITION
    ]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            st = await ax.move_abs(90.0, vel_dps=30, acc_dps2=60)
            ax.bus.close()
            srv.check()
            assert st.position_deg == 90.0

    run(body())


def test_refusal_raises_with_reason() -> None:
    script = [
        ("0001 0000 0006 01 03 001A 0001", "0001 0000 0005 01 03 02 0005"),
        ("0002 0000 0006 01 06 0028 0001", "0002 0000 0006 01 06 0028 0001"),  # FC06 COMMAND = MOVE_ABS
        (status_req(3), status_reply(3, 0x0013, cmd_count=6, result=1)),  # refused: not enabled
    ]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            with pytest.raises(CommandRefused, match="not enabled") as err:
                await ax._command(Command.MOVE_ABS)
            assert err.value.result == 1
            ax.bus.close()
            srv.check()

    run(body())


def test_lost_command_reply_is_not_repeated_when_cmd_count_moved() -> None:
    """A MOVE_REL whose reply is lost must not be sent again if CMD_COUNT shows it ran."""
    write = "0002 0000 0019 01 10 0020 0009 12 000003E8 00002710 00002710 00002710 0002"
    script = [
        ("0001 0000 0006 01 03 001A 0001", "0001 0000 0005 01 03 02 0009"),
        (write, None),  # reply lost: the client times out
        ("0003 0000 0006 01 03 001A 0001", "0003 0000 0005 01 03 02 000A"),  # but CMD_COUNT moved
        (status_req(4), status_reply(4, 0x0017, cmd_count=10)),
    ]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis(timeout=0.1)
            await ax.bus.connect()
            await ax.start_move_rel(1.0, vel_dps=10, acc_dps2=10)
            ax.bus.close()
            srv.check()

    run(body())


def test_exception_02_is_a_protocol_error() -> None:
    script = [("0001 0000 0006 01 03 0012 0002", "0001 0000 0003 01 83 02")]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            with pytest.raises(AxisProtocolError, match="0x02 illegal data address") as err:
                await ax.position()
            assert err.value.code == 2
            ax.bus.close()
            srv.check()

    run(body())


@pytest.mark.parametrize("code", ["04", "0B"])
def test_exception_04_0b_mean_unreachable_after_one_retry(code: str) -> None:
    script = [
        ("0001 0000 0006 01 03 0012 0002", f"0001 0000 0003 01 83 {code}"),
        ("0002 0000 0006 01 03 0012 0002", f"0002 0000 0003 01 83 {code}"),
    ]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis()
            await ax.bus.connect()
            with pytest.raises(AxisUnreachable, match=f"axis z: .*0x{code}"):
                await ax.position()
            ax.bus.close()
            srv.check()

    run(body())


def test_no_reply_is_unreachable_quickly() -> None:
    script = [("0001 0000 0006 01 03 0012 0002", None), ("0002 0000 0006 01 03 0012 0002", None)]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis(timeout=0.2)
            await ax.bus.connect()
            t = time.monotonic()
            with pytest.raises(AxisUnreachable):
                await ax.position()
            assert time.monotonic() - t < 1.0
            ax.bus.close()
            srv.check()

    run(body())


def test_a_url_allows_a_slow_gateway_its_own_answer_time() -> None:
    """``?timeout=`` on the bus URL wins over the driver's default: the same silent axis is reported
    after the URL's answer time (two attempts), and a mistyped option is refused by name."""
    script = [("0001 0000 0006 01 03 0012 0002", None), ("0002 0000 0006 01 03 0012 0002", None)]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = Axis("z", 1, ModbusBus(f"tcp://127.0.0.1:{srv.port}?timeout=0.6", timeout=0.2))
            assert ax.bus.timeout == 0.6
            await ax.bus.connect()
            t = time.monotonic()
            with pytest.raises(AxisUnreachable):
                await ax.position()
            assert 1.2 <= time.monotonic() - t < 2.5  # two attempts of 0.6 s, not of 0.2 s
            ax.bus.close()
            srv.check()

    run(body())
    assert BusURL.parse("serial:///dev/ttyUSB0?baud=9600&timeout=0.5").timeout == 0.5
    assert BusURL.parse("tcp://10.0.0.5:502").timeout is None
    with pytest.raises(ValueError, match="unknown option timout"):
        BusURL.parse("tcp://10.0.0.5:502?timout=1")
    with pytest.raises(ValueError, match="timeout in Modbus URL .*got 'soon'"):
        BusURL.parse("tcp://10.0.0.5:502?timeout=soon")
    with pytest.raises(ValueError, match="baud in Modbus URL .*got '9600x'"):
        BusURL.parse("serial:///dev/ttyUSB0?baud=9600x")
    with pytest.raises(ValueError, match="parity in Modbus URL .*expected N, E or O"):
        BusURL.parse("serial:///dev/ttyUSB0?parity=X")


def test_low_word_first_position() -> None:
    script = [("0001 0000 0006 01 03 0012 0002", "0001 0000 0007 01 03 04 5F90 0001")]

    async def body() -> None:
        async with ScriptServer(script) as srv:
            ax = srv.axis(low_word_first=True)
            await ax.bus.connect()
            assert await ax.position() == 90.0
            ax.bus.close()
            srv.check()

    run(body())


# ==================================================================================================
# (b) integration against TableSim
# ==================================================================================================


@contextlib.asynccontextmanager
async def station(scale: float = 20.0, framer: str = "tcp", **sim_kw):
    """A TableSim on an ephemeral port and a connected Turntable."""
    sim = TableSim(SimClock(scale), **sim_kw)
    await sim.start(0, framer=framer)
    table = Turntable(sim.url())
    try:
        await table.connect()
        yield sim, table
    finally:
        await table.close()
        await sim.stop()


async def ready(table: Turntable) -> None:
    await table.enable_all()
    await table.home_all(vel_dps=30, acc_dps2=60)


@pytest.mark.parametrize("framer", ["tcp", "rtu"])
def test_refusals_then_enable_home_move(framer: str) -> None:
    async def body() -> None:
        async with station(framer=framer, angles=(12.0, -3.0, 4.0)) as (sim, table):
            z = table.axes["z"]
            assert z.identity is not None and z.identity.protocol_version == 1
            st = await z.status()
            assert not st.enabled and not st.homed
            with pytest.raises(CommandRefused, match="not enabled"):
                await z.move_abs(10)
            await table.enable_all()
            with pytest.raises(CommandRefused, match="not homed") as err:
                await z.move_abs(10)
            assert err.value.reason == "not homed"
            assert (await z.status()).fault_code == 0x4A  # MOVE_ABS while not homed also faults
            await table.reset_faults()
            await table.home_all(vel_dps=30, acc_dps2=60)
            assert all(s.homed for s in (await table.status_all()).values())
            await table.move_to(120.0, 35.0, -60.0)
            pos = await table.positions()
            for p, want in zip(pos, (120.0, 35.0, -60.0)):
                assert abs(p - want) <= 0.005
            for p, want in zip(sim.true_angles(), (120.0, 35.0, -60.0)):
                assert abs(p - want) <= 0.005

    run(body())


def test_relative_move_retarget_and_stop() -> None:
    async def body() -> None:
        async with station() as (sim, table):
            await ready(table)
            y = table.axes["y"]
            st = await y.move_rel(10.0)
            assert abs(st.position_deg - 10.0) <= 0.005
            await y.move_rel(-2.5)
            assert abs(await y.position() - 7.5) <= 0.005
            # re-target: start to +80, change to -20 while moving
            await y.start_move_abs(80.0)
            await asyncio.sleep(0.05)
            assert (await y.status()).moving
            await y.start_move_abs(-20.0)
            st = await y.wait_in_position(5.0)
            assert abs(st.position_deg + 20.0) <= 0.005
            # stop mid-move: ends at rest, somewhere between, in position at the stop point
            await y.start_move_abs(60.0)
            await asyncio.sleep(0.05)
            await y.stop()
            st = await y.wait_in_position(5.0)
            assert -20.0 < st.position_deg < 60.0 and not st.moving

    run(body())


def test_soft_limit_refusal() -> None:
    async def body() -> None:
        async with station() as (sim, table):
            await ready(table)
            x = table.axes["x"]
            await x.set_soft_limits(-90.0, 90.0)
            with pytest.raises(CommandRefused, match="beyond soft limit"):
                await x.move_abs(100.0)
            st = await x.status()
            assert not st.fault and not st.moving
            await x.move_abs(89.0)  # inside is fine

    run(body())


def test_protocol_errors_from_the_simulator() -> None:
    async def body() -> None:
        async with station() as (sim, table):
            z = table.axes["z"]
            with pytest.raises(AxisProtocolError) as err:  # half of the ACTUAL_POS pair
                await z._read(Reg.ACTUAL_POS + 1, 1)
            assert err.value.code == 2
            with pytest.raises(AxisProtocolError) as err:  # unmapped
                await z._read(0x0030, 1)
            assert err.value.code == 2
            with pytest.raises(AxisProtocolError) as err:  # read-only
                await z._write(Reg.STATUS, [0])
            assert err.value.code == 2
            with pytest.raises(AxisProtocolError) as err:  # PROFILE_VEL 0
                await z._write(Reg.PROFILE_VEL, [0, 0])
            assert err.value.code == 3
            with pytest.raises(AxisProtocolError) as err:  # unknown command
                await z._write(Reg.COMMAND, [99])
            assert err.value.code == 3
            await ready(table)
            with pytest.raises(AxisProtocolError) as err:  # faster than MAX_VEL (60 deg/s)
                await z.move_abs(10, vel_dps=100)
            assert err.value.code == 3

    run(body())


def test_time_scale_20_runs_a_90_degree_move_20_times_faster() -> None:
    async def body() -> None:
        async with station(scale=20.0, homed=True, enabled=True) as (sim, table):
            t_sim, t_wall = sim.clock.now(), time.monotonic()
            await table.move_to(90.0, 0.0, 0.0, speed_dps=30, accel_dps2=60)
            wall = time.monotonic() - t_wall
            sim_elapsed = sim.clock.now() - t_sim
            profile = trapezoid_time(90, 30, 60)  # 3.5 s
            assert profile <= sim_elapsed <= profile + 1.0  # plus servo settling and polling
            # at least 1/20 of the profile; the upper bound leaves a busy host a second and still
            # fails a table that ran in real time (3.5 s)
            assert profile / 20 <= wall <= (profile + 1.0) / 20 + 1.0

    run(body())


# ==================================================================================================
# (c) faults
# ==================================================================================================


def test_alarm_mid_move_raises_axis_fault_and_stops_the_others() -> None:
    async def body() -> None:
        async with station(scale=5.0) as (sim, table):
            await ready(table)
            sim.alarm("y", 0x30, at_angle=20.0)
            t = time.monotonic()
            with pytest.raises(AxisFault, match="axis y: fault 0x30 overload") as err:
                await table.move_to(40.0, 40.0, 40.0)
            assert err.value.code == 0x30 and err.value.name == "overload"
            # y passes 20 deg after ~0.9 s simulated = 0.18 s wall; reported well within a second
            assert time.monotonic() - t < 1.0
            await asyncio.sleep(0.3)
            sts = await table.status_all()
            assert not any(s.moving for s in sts.values())
            # braked from 30 deg/s at 300 deg/s^2: 1.5 deg past the alarm angle
            assert sts["y"].fault_code == 0x30 and 20.0 <= sts["y"].position_deg < 22.0

    run(body())


@pytest.mark.parametrize("framer", ["tcp", "rtu"])
def test_silent_axis_is_unreachable_within_a_second(framer: str) -> None:
    async def body() -> None:
        async with station(scale=1.0, framer=framer, homed=True, enabled=True) as (sim, table):
            move = asyncio.ensure_future(table.move_to(60.0, 60.0, 60.0))
            await asyncio.sleep(0.3)
            sim.silence("x")
            t = time.monotonic()
            with pytest.raises(AxisUnreachable, match="axis x"):
                await move
            assert time.monotonic() - t < 1.0
            # z and y were told to STOP: they come to rest well short of 60 deg
            for name in ("z", "y"):
                st = await table.axes[name].wait_in_position(2.0)
                assert 1.0 < st.position_deg < 50.0
            sim.silence("x", False)
            assert (await table.axes["x"].status()).moving  # x never heard the STOP

    run(body())


def test_stuck_encoder_ends_in_following_error() -> None:
    async def body() -> None:
        async with station(scale=5.0) as (sim, table):
            await ready(table)
            z = table.axes["z"]
            await z.start_move_abs(90.0)
            await asyncio.sleep(0.2)  # 1 s simulated: well under way
            sim.stick_encoder("z")
            with pytest.raises(AxisFault, match="following error") as err:
                await z.wait_in_position(3.0)
            assert err.value.code == 0x10
            await asyncio.sleep(0.1)
            enc = await z.position()
            assert abs(sim.true_angles()[0] - enc) > 0.5  # the true angle ran away from the encoder

    run(body())


def test_estop_faults_refuses_and_recovers() -> None:
    async def body() -> None:
        async with station() as (sim, table):
            await ready(table)
            move = asyncio.ensure_future(table.move_to(90.0, 0.0, 0.0))
            await asyncio.sleep(0.05)
            sim.estop(True)
            with pytest.raises(AxisFault, match=r"0x68 E-stop \(release the E-stop, then reset\)"):  # what to do
                await move
            st = await table.axes["z"].status()
            assert st.estop and not st.enabled
            with pytest.raises(CommandRefused, match="E-stop"):
                await table.axes["z"].enable()
            sim.estop(False)
            await table.reset_faults()
            await table.enable_all()
            await table.move_to(10.0, 0.0, 0.0)
            assert abs((await table.positions())[0] - 10.0) <= 0.005

    run(body())


def test_hard_limit_fault() -> None:
    async def body() -> None:
        async with station(hard_limits={"y": (-50.0, 50.0)}) as (sim, table):
            await ready(table)
            with pytest.raises(AxisFault, match="0x66 hardware limit"):
                await table.axes["y"].move_abs(60.0)
            st = await table.axes["y"].status()
            assert st.has(Status.LIMIT_POS)

    run(body())


def test_a_move_refused_for_a_fault_names_the_fault() -> None:
    """An alarm raised while an axis held was reported at the next move as "MOVE_ABS refused: fault
    active", without saying which fault."""
    async def body() -> None:
        async with station() as (sim, table):
            await ready(table)
            sim.alarm("z", 0x30)
            with pytest.raises(CommandRefused, match=r"MOVE_ABS refused: fault active \(fault 0x30 overload\)"):
                await table.axes["z"].move_abs(10.0)

    run(body())


def test_watchdog_quick_stops_an_unpolled_axis() -> None:
    async def body() -> None:
        async with station(scale=5.0) as (sim, table):
            await ready(table)
            z = table.axes["z"]
            await z.write_value(Reg.WATCHDOG_MS, 300, signed=False, wide=False)
            await z.start_move_abs(90.0)
            await asyncio.sleep(0.2)  # 1 s simulated without a request to z
            st = await z.status()
            assert st.fault_code == 0x85 and st.position_deg < 30.0

    run(body())


def test_model_jog_into_soft_limit_and_non_resettable_fault() -> None:
    """Pure model (no I/O): jogging into a soft limit faults 0x67; overcurrent is not resettable."""
    a = AxisSim("x", 3, homed=True, enabled=True)
    a.regs[Reg.SOFT_LIMIT_MIN], a.regs[Reg.SOFT_LIMIT_MAX], a.regs[Reg.SOFT_LIMIT_ENABLE] = -5000, 5000, 1
    a.regs[Reg.JOG_VEL] = 10_000
    assert a.execute(Command.JOG_POS) == 0
    a.advance(2.0)
    assert a.fault == 0x67 and a.status_word() & Status.SOFT_LIMIT_POS
    assert a.execute(Command.RESET_FAULT) == 0 and a.fault == 0
    a.alarm(0x20)
    assert a.execute(Command.RESET_FAULT) == 3 and a.fault == 0x20
    before = a.cmd_count
    assert a.execute(Command.STOP) == 0 and a.cmd_count == before + 1  # STOP is always accepted


def test_model_timed_alarm_and_true_angle_history() -> None:
    a = AxisSim("z", 1, homed=True, enabled=True)
    a.regs[Reg.TARGET_POS], a.regs[Reg.PROFILE_VEL] = 10_000, 10_000
    a.execute(Command.MOVE_ABS)
    a.alarm(0x21, at_time=0.5)
    a.advance(0.4)
    assert a.fault == 0
    a.advance(3.0)
    assert a.fault == 0x21 and a.mode == "idle"
    stopped = a.true_angle(3.0)
    assert 0.0 < a.true_angle(0.3) < a.true_angle(0.45) < stopped < 10.0  # past times interpolate


def test_one_url_per_axis() -> None:
    async def body() -> None:
        sim = TableSim(SimClock(20.0), homed=True, enabled=True)
        port = await sim.start()
        table = Turntable({"z": f"tcp://127.0.0.1:{port}", "y": f"tcp://localhost:{port}",
                           "x": f"tcp://localhost:{port}"})
        try:
            assert len(table.buses) == 2 and table.axes["y"].bus is table.axes["x"].bus
            await table.connect()
            await table.move_to(5.0, -5.0, 15.0)
            assert [round(p, 2) for p in await table.positions()] == [5.0, -5.0, 15.0]
        finally:
            await table.close()
            await sim.stop()

    run(body())


def test_bus_reconnects_after_the_server_restarts() -> None:
    async def body() -> None:
        sim = TableSim(SimClock(20.0))
        port = await sim.start()
        table = Turntable(sim.url())
        await table.connect()
        await sim.stop()
        with pytest.raises(AxisUnreachable):
            await table.positions()
        sim2 = TableSim(SimClock(20.0), angles=(1.0, 2.0, 3.0))
        await sim2.start(port)
        try:
            assert await table.positions() == (1.0, 2.0, 3.0)
        finally:
            await table.close()
            await sim2.stop()

    run(body())
