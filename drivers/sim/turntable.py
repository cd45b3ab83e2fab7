"""A simulated three-axis turntable: one Modbus axis controller per axis, as in PROTOCOLS.md.

``AxisSim`` is a pure model (no I/O): trapezoidal profiles on the demand position, a servo loop whose
actual position trails the demand, every command and status bit of the register map, and the
faults. It is advanced lazily to the simulated time of each access (``SimClock``), in fixed 1 ms
simulated steps, so timing is exact however rarely it is polled and scales with the time scale.

``TableSim`` puts three of them (units 1, 2, 3 = z, y, x) behind a Modbus server (through
``drivers/modbus.py``, the only module that knows pymodbus), answers the simulated world's
``true_angles``, and offers fault injection as a side channel that never goes through the protocol.

Internal positions are in millidegrees in the *mechanical* frame (the true angle); the encoder reads
``mechanical + enc_offset`` (the offset is fixed by homing or SET_POSITION), and every register in the
protocol is in the encoder frame.
"""

from __future__ import annotations

import math
from bisect import bisect_left

from drivers.modbus import ExceptionReply, NoReply, ServerHandle, sim_device, start_server, stop_server
from drivers.protocol import (
    CONFIG_BLOCK,
    COUNTS_PER_DEG,
    DEFAULT_FOLLOWING_ERR_LIMIT,
    DEFAULT_IN_POS_WINDOW,
    DEFAULT_MAX_VEL,
    IDENTITY_BLOCK,
    MOTION_BLOCK,
    PRODUCT_ID,
    PROTOCOL_VERSION,
    RESETTABLE_FAULTS,
    STATUS_BLOCK,
    WIDE_REGS,
    AXIS_UNITS,
    CmdResult,
    Command,
    ModbusExc,
    Reg,
    Status,
    from_words,
    to_words,
)
from drivers.sim.clock import SimClock

DT = 0.002  # s of simulated time per integration step (servo wn*DT = 0.05: stable and accurate)
FW_VERSION = 0x0102
QUICK_STOP_DEC = 300_000.0  # mdeg/s^2: fast, yet the servo still follows (error ~ a / wn^2 ~ 0.5 deg)
BRAKE_DEC = 300_000.0  # mdeg/s^2: a faulted or disabled axis brakes to rest
SERVO_WN = 2 * math.pi * 4.0  # rad/s: 95 mdeg of lag at 60 deg/s^2, settles into 5 mdeg in ~0.2 s
SERVO_ZETA = 1.0
_KP, _KD = SERVO_WN ** 2, 2 * SERVO_ZETA * SERVO_WN
HARDWARE_MAX_VEL = 360_000  # mdeg/s: the largest MAX_VEL the controller accepts
MAX_ACCEL = 10_000_000  # mdeg/s^2: the largest PROFILE_ACC / PROFILE_DEC accepted
IN_POS_DWELL = 0.1  # s: IN_POSITION only after the encoder stayed in the window this long (settling)
HISTORY_S = 5.0  # s of simulated time kept for true_angles() at past times

_MOVING_MODES = ("move", "home", "jog", "stop")


def _sign(x: float) -> float:
    return (x > 0) - (x < 0)


class AxisSim:
    """One axis controller and its mechanics; advanced with ``advance(t)`` in simulated seconds.

    ``angle_deg`` is the initial true mechanical angle. The encoder starts reading the same value
    (offset 0) but HOMED is clear until HOME or SET_POSITION. ``hard_limits`` are mechanical angles
    (deg) at which the limit switches trip (fault 0x66); ``home_angle`` is where the home sensor is.
    """

    def __init__(self, name: str, unit: int, *, t0: float = 0.0, angle_deg: float = 0.0,
                 homed: bool = False, enabled: bool = False,
                 hard_limits: tuple[float, float] | None = None, home_angle: float = 0.0,
                 serial_no: int = 0) -> None:
        self.name = name
        self.unit = unit
        self.serial_no = serial_no or (20240000 + unit)
        self.hard_limits = (
            (hard_limits[0] * COUNTS_PER_DEG, hard_limits[1] * COUNTS_PER_DEG) if hard_limits else None
        )
        self.home_mech = home_angle * COUNTS_PER_DEG
        self.t = t0
        # mechanics (mechanical frame, mdeg)
        self.mech = angle_deg * COUNTS_PER_DEG
        self.mvel = 0.0
        # controller
        self.enc_offset = 0.0
        self.dem = self.mech
        self.dvel = 0.0
        self.target = self.mech  # mechanical frame (unused while jogging)
        self.mode = "idle"  # idle | move | home | jog | stop
        self.stop_dec = 0.0
        self.jog_dir = 0
        self.enabled = enabled
        self.homed = homed
        self.fault = 0
        self.estop_on = False
        self.limit_bits = 0
        self.cmd_count = 0
        self.last_result = 0
        self.last_command = 0
        self.stuck_enc: float | None = None
        self.in_window_since: float | None = None  # start of the current stay in the window
        self.silent = False
        self.last_request_t = t0
        self.pending: list[tuple[int, float | None, float | None]] = []  # (code, at_time, at_angle)
        self.history: list[tuple[float, float]] = [(t0, self.mech)]
        # registers of the motion and configuration blocks (encoder frame, raw ints)
        self.regs: dict[int, int] = {
            Reg.TARGET_POS: round(self.mech), Reg.PROFILE_VEL: 10_000, Reg.PROFILE_ACC: 20_000,
            Reg.PROFILE_DEC: 20_000, Reg.JOG_VEL: 5_000,
            Reg.SOFT_LIMIT_MIN: -180_000, Reg.SOFT_LIMIT_MAX: 180_000, Reg.SOFT_LIMIT_ENABLE: 0,
            Reg.IN_POS_WINDOW: DEFAULT_IN_POS_WINDOW, Reg.MAX_VEL: DEFAULT_MAX_VEL,
            Reg.HOME_OFFSET: 0, Reg.HOME_METHOD: 0, Reg.WATCHDOG_MS: 0,
            Reg.FOLLOWING_ERR_LIMIT: DEFAULT_FOLLOWING_ERR_LIMIT,
        }
        self.spare_regs: dict[int, int] = {}  # writable but unused addresses (0x0029, ...)

    # ---------------------------------------------------------------------------------------------
    # derived quantities
    # ---------------------------------------------------------------------------------------------

    @property
    def servo_on(self) -> bool:
        """The position loop runs (enabled, no fault, no E-stop)."""
        return self.enabled and not self.fault and not self.estop_on

    @property
    def fb(self) -> float:
        """The position the controller believes (mechanical frame): the encoder, stuck or not."""
        return self.stuck_enc - self.enc_offset if self.stuck_enc is not None else self.mech

    def encoder(self) -> int:
        """ACTUAL_POS in counts."""
        return round(self.fb + self.enc_offset)

    def position_deg(self) -> float:
        """The axis position in the controller frame as a healthy encoder would read it."""
        return (self.mech + self.enc_offset) / COUNTS_PER_DEG

    def _in_window(self) -> bool:
        return (self.servo_on and self.mode == "idle"
                and abs(self.fb - self.target) <= self.regs[Reg.IN_POS_WINDOW])

    def _update_window(self) -> None:
        if not self._in_window():
            self.in_window_since = None
        elif self.in_window_since is None:
            self.in_window_since = self.t

    def in_position(self) -> bool:
        """IN_POSITION: profile finished and the encoder within IN_POS_WINDOW of the target for
        IN_POS_DWELL (as a drive's in-position settling time), so a servo still swinging through
        the window is not reported in position."""
        return (self._in_window() and self.in_window_since is not None
                and self.t - self.in_window_since >= IN_POS_DWELL - 1e-9)

    def status_word(self) -> int:
        """The STATUS register."""
        s = Status(0)
        if not self.fault and not self.estop_on:
            s |= Status.READY
        if self.enabled:
            s |= Status.ENABLED
        if self.mode in _MOVING_MODES:
            s |= Status.MOVING
        if self.in_position():
            s |= Status.IN_POSITION
        if self.homed:
            s |= Status.HOMED
        if self.mode == "home":
            s |= Status.HOMING
        if self.fault:
            s |= Status.FAULT
        s |= Status(self.limit_bits)
        if self.regs[Reg.SOFT_LIMIT_ENABLE] and self.homed:
            enc = self.encoder()
            if enc >= self.regs[Reg.SOFT_LIMIT_MAX]:
                s |= Status.SOFT_LIMIT_POS
            if enc <= self.regs[Reg.SOFT_LIMIT_MIN]:
                s |= Status.SOFT_LIMIT_NEG
        if self.estop_on:
            s |= Status.ESTOP
        if self.mode == "jog":
            s |= Status.JOGGING
        if self.mode == "stop":
            s |= Status.STOPPING
        return int(s)

    # ---------------------------------------------------------------------------------------------
    # time stepping
    # ---------------------------------------------------------------------------------------------

    def _quiet(self) -> bool:
        """Nothing changes until an outside event: skip ahead instead of stepping."""
        if self.mode != "idle" or self.mvel != 0.0:
            return False
        return not self.servo_on or self.dem == self.fb

    def advance(self, t: float) -> None:
        """Integrate the model up to simulated time ``t`` (no-op for a time in the past)."""
        while self.t < t - 1e-12:
            if self._quiet():
                self._update_window()
                t_next = t
                timed = [at for _, at, _ in self.pending if at is not None]
                if timed:
                    t_next = min(t, max(self.t, min(timed)))
                self.t = t_next
                self._check_timed_alarms()
                self._record()
                if t_next >= t:
                    break
                continue
            self._step(min(DT, t - self.t))
        self._trim_history()

    def _step(self, dt: float) -> None:
        prev = self.mech + self.enc_offset
        self.t += dt
        if self.servo_on:
            self._profile_step(dt)
            # Servo: P on the position encoder, D on the motor's own velocity feedback with the
            # demand velocity fed forward; no acceleration feed-forward, so the actual position
            # lags by about a / wn^2 while accelerating (and overshoots a little when stopping).
            acc = _KP * (self.dem - self.fb) + _KD * (self.dvel - self.mvel)
            self.mvel += acc * dt
            self.mech += self.mvel * dt
            if self.mode == "idle" and abs(self.dem - self.fb) < 1e-3 and abs(self.mvel) < 1e-3:
                if self.stuck_enc is None:
                    self.mech = self.dem
                else:
                    self.dem = self.fb
                self.mvel = 0.0  # settled: let advance() skip ahead
            if abs(self.dem - self.fb) > self.regs[Reg.FOLLOWING_ERR_LIMIT]:
                self._raise_fault(0x10)
        else:
            # Servo off (disabled, fault, E-stop): the brake stops the axis; demand tracks feedback.
            dv = min(abs(self.mvel), BRAKE_DEC * dt)
            v_new = self.mvel - _sign(self.mvel) * dv
            self.mech += 0.5 * (self.mvel + v_new) * dt
            self.mvel = v_new
            self.dem, self.dvel, self.target, self.mode = self.fb, 0.0, self.fb, "idle"
        if self.hard_limits or self.mode == "jog":
            self._check_limits(prev)
        if self.pending:
            self._check_timed_alarms()
            self._check_angle_alarms(prev, self.mech + self.enc_offset)
        wd = self.regs[Reg.WATCHDOG_MS]
        if wd and self.mode in ("move", "home", "jog") and self.t - self.last_request_t > wd / 1000.0:
            self._begin_stop(QUICK_STOP_DEC)
            self._raise_fault(0x85)
        self._update_window()
        self._record()

    def _profile_step(self, dt: float) -> None:
        """Advance the demand position by one step of the trapezoidal profile."""
        if self.mode == "idle":
            self.dvel = 0.0
            return
        vmax = float(min(self.regs[Reg.PROFILE_VEL], self.regs[Reg.MAX_VEL]))
        acc = float(self.regs[Reg.PROFILE_ACC])
        dec = float(self.regs[Reg.PROFILE_DEC])
        v = self.dvel
        if self.mode == "stop":
            v_des, dec = 0.0, self.stop_dec
        elif self.mode == "jog":
            v_des = self.jog_dir * min(float(self.regs[Reg.JOG_VEL]), float(self.regs[Reg.MAX_VEL]))
        else:
            d = self.target - self.dem
            v_des = _sign(d) * min(vmax, math.sqrt(2.0 * dec * abs(d)))
        rate = acc if (v * v_des >= 0 and abs(v_des) > abs(v)) else dec
        v_new = v + max(-rate * dt, min(rate * dt, v_des - v))
        step = 0.5 * (v + v_new) * dt
        if self.mode in ("move", "home"):
            d = self.target - self.dem
            # Arrive when this step reaches the target at a speed the sqrt law brings there
            # (<= ~2 dec dt); a re-target just ahead of a fast axis overshoots and comes back.
            if (d == 0 or (_sign(step) == _sign(d) and abs(d) <= abs(step))) \
                    and abs(v_new) <= 3.0 * dec * dt + 1e-9:
                self.dem, self.dvel = self.target, 0.0
                self._finish()
                return
        self.dem += step
        self.dvel = v_new
        if self.mode == "stop" and v_new == 0.0:
            self.target = self.dem
            self._finish()

    def _finish(self) -> None:
        """The profile is done (MOVING clears; IN_POSITION follows when the servo settles)."""
        if self.mode == "home":
            # The home sensor is at home_mech modulo a turn: make that turn the mechanical zero turn
            # (the true angle is physically periodic) and let the encoder read HOME_OFFSET there.
            turns = round((self.dem - self.home_mech) / 360_000.0) * 360_000.0
            self.mech -= turns
            self.dem -= turns
            self.target = self.dem
            self.history = [(t, a - turns) for t, a in self.history]
            self.enc_offset = self.regs[Reg.HOME_OFFSET] - self.home_mech
            if self.stuck_enc is not None:
                self.stuck_enc = self.mech + self.enc_offset
            self.homed = True
        self.mode = "idle"

    def _begin_stop(self, dec: float) -> None:
        if self.mode in _MOVING_MODES:
            self.mode = "stop"
            self.stop_dec = dec

    def _raise_fault(self, code: int) -> None:
        """Latch a fault: the servo stops (brake) and FAULT is set."""
        if not self.fault or code == 0x68:
            self.fault = code
        self.mode = "idle"
        self.dem, self.dvel, self.target = self.fb, 0.0, self.fb

    def _check_limits(self, prev_enc: float) -> None:
        pos = self.mech
        bits = 0
        if self.hard_limits:
            lo, hi = self.hard_limits
            moving_out = False
            if pos >= hi:
                bits |= Status.LIMIT_POS
                moving_out = self.mvel > 0
            if pos <= lo:
                bits |= Status.LIMIT_NEG
                moving_out = self.mvel < 0
            if moving_out and not self.fault:
                self._raise_fault(0x66)
        self.limit_bits = int(bits)
        if self.mode == "jog" and self.regs[Reg.SOFT_LIMIT_ENABLE] and self.homed and not self.fault:
            enc = self.fb + self.enc_offset
            if (self.jog_dir > 0 and enc >= self.regs[Reg.SOFT_LIMIT_MAX]) or (
                    self.jog_dir < 0 and enc <= self.regs[Reg.SOFT_LIMIT_MIN]):
                self._raise_fault(0x67)

    def _check_timed_alarms(self) -> None:
        for item in list(self.pending):
            code, at_time, _ = item
            if at_time is not None and self.t >= at_time:
                self.pending.remove(item)
                self._raise_fault(code)

    def _check_angle_alarms(self, a0: float, a1: float) -> None:
        lo, hi = min(a0, a1), max(a0, a1)
        for item in list(self.pending):
            code, _, at_angle = item
            if at_angle is not None and a0 != a1 and lo <= at_angle * COUNTS_PER_DEG <= hi:
                self.pending.remove(item)
                self._raise_fault(code)

    def _record(self) -> None:
        self.history.append((self.t, self.mech))

    def _trim_history(self) -> None:
        if len(self.history) > 2 * int(HISTORY_S / DT) + 10:
            cut = bisect_left(self.history, (self.t - HISTORY_S, -math.inf))
            del self.history[:cut]

    def true_angle(self, t: float) -> float:
        """The true mechanical angle (deg) at simulated time ``t`` (interpolated if in the past)."""
        self.advance(t)
        h = self.history
        if t >= h[-1][0] or len(h) == 1:
            return h[-1][1] / COUNTS_PER_DEG
        i = bisect_left(h, (t, -math.inf))
        if i == 0:
            return h[0][1] / COUNTS_PER_DEG
        (t0, a0), (t1, a1) = h[i - 1], h[i]
        f = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        return (a0 + f * (a1 - a0)) / COUNTS_PER_DEG

    # ---------------------------------------------------------------------------------------------
    # side channel (fault injection)
    # ---------------------------------------------------------------------------------------------

    def alarm(self, code: int, at_time: float | None = None, at_angle: float | None = None) -> None:
        """Raise fault ``code`` now, at simulated ``at_time``, or when the axis passes ``at_angle``."""
        if at_time is None and at_angle is None:
            self._raise_fault(code)
        else:
            self.pending.append((code, at_time, at_angle))

    def set_estop(self, on: bool) -> None:
        """Press (fault 0x68, servo off, ENABLED cleared) or release the E-stop."""
        self.estop_on = on
        if on:
            self.enabled = False
            self._raise_fault(0x68)

    def stick_encoder(self, on: bool) -> None:
        """Freeze the encoder reading (the motor keeps being driven: following-error fault)."""
        self.stuck_enc = float(self.encoder()) if on else None
        if self.mode == "idle":
            # At rest the controller now believes it is exactly where the encoder says (a
            # sub-window re-target), so a stuck encoder at rest does not make the axis creep.
            self.dem = self.target = self.fb

    # ---------------------------------------------------------------------------------------------
    # registers
    # ---------------------------------------------------------------------------------------------

    def touch(self, t: float) -> None:
        """A request arrived at simulated time ``t``: advance, then feed the watchdog."""
        self.advance(t)
        self.last_request_t = t

    def _value(self, addr: int) -> int:
        """The (signed or unsigned, possibly 32-bit) value whose first address is ``addr``."""
        if addr in self.regs:
            return self.regs[addr]
        fe = self.dem - self.fb if self.servo_on else 0.0
        enc = self.encoder()
        return {
            Reg.PRODUCT_ID: PRODUCT_ID,
            Reg.FW_VERSION: FW_VERSION,
            Reg.SERIAL_NO: self.serial_no,
            Reg.AXIS_INDEX: self.unit,
            Reg.COUNTS_PER_DEG: COUNTS_PER_DEG,
            Reg.PROTOCOL_VERSION: PROTOCOL_VERSION,
            Reg.STATUS: self.status_word(),
            Reg.FAULT_CODE: self.fault,
            Reg.ACTUAL_POS: enc,
            Reg.ACTUAL_VEL: 0 if self.stuck_enc is not None else round(self.mvel),
            Reg.DEMAND_POS: round(self.dem + self.enc_offset),
            Reg.FOLLOWING_ERR: round(fe),
            Reg.CMD_COUNT: self.cmd_count,
            Reg.LAST_CMD_RESULT: self.last_result,
            Reg.WARNING_CODE: 0,
            Reg.TEMPERATURE: 285 + 5 * self.unit,
            Reg.ACTUAL_POS_MOD: enc % 360_000,
            Reg.COMMAND: self.last_command,
        }.get(addr, self.spare_regs.get(addr, 0))

    def read_registers(self, addr: int, count: int) -> list[int]:
        """Registers ``addr .. addr+count-1`` (the caller has checked they are mapped)."""
        _check_pairs(addr, count)
        out: list[int] = []
        a = addr
        while a < addr + count:
            if a in WIDE_REGS:
                out.extend(to_words(self._value(a), WIDE_REGS[a]))
                a += 2
            else:
                out.append(self._value(a) & 0xFFFF)
                a += 1
        return out[:count]

    def write_registers(self, addr: int, values: list[int]) -> None:
        """Store parameters, then run COMMAND if it was written. ExceptionReply on a bad value."""
        count = len(values)
        _check_pairs(addr, count)
        new: dict[int, int] = {}
        a = addr
        while a < addr + count:
            i = a - addr
            if a in WIDE_REGS:
                new[a] = from_words(values[i:i + 2], WIDE_REGS[a])
                a += 2
            else:
                new[a] = values[i]
                a += 1
        for reg, v in new.items():
            _validate(reg, v, new.get(Reg.MAX_VEL, self.regs[Reg.MAX_VEL]))
        command = new.pop(Reg.COMMAND, None)
        for reg, v in new.items():
            if reg in self.regs:
                self.regs[reg] = v
            else:
                self.spare_regs[reg] = v
        if command is not None:
            self.last_command = command
            self.execute(Command(command))

    # ---------------------------------------------------------------------------------------------
    # commands
    # ---------------------------------------------------------------------------------------------

    def execute(self, cmd: Command) -> int:
        """Run a command synchronously: CMD_COUNT +1 and LAST_CMD_RESULT set before the reply."""
        result = self._run(cmd)
        self._update_window()  # a new target clears IN_POSITION at once
        self.cmd_count = (self.cmd_count + 1) & 0xFFFF
        self.last_result = int(result)
        return int(result)

    def _run(self, cmd: Command) -> CmdResult:
        R = CmdResult
        if cmd == Command.NOP:
            return R.OK
        if cmd in (Command.STOP, Command.QUICK_STOP):  # always accepted
            self._begin_stop(float(self.regs[Reg.PROFILE_DEC]) if cmd == Command.STOP else QUICK_STOP_DEC)
            return R.OK
        if cmd == Command.DISABLE:
            self.enabled = False
            return R.OK
        if self.estop_on:
            return R.ESTOP
        if cmd == Command.RESET_FAULT:
            if self.fault and self.fault not in RESETTABLE_FAULTS and self.fault != 0x68:
                return R.FAULT_ACTIVE  # needs a power cycle or service
            self.fault = 0
            self.dem, self.dvel, self.target = self.fb, 0.0, self.fb
            return R.OK
        if self.fault:
            return R.FAULT_ACTIVE
        if cmd == Command.ENABLE:
            if not self.enabled:
                self.enabled = True
                self.dem, self.dvel, self.target, self.mode = self.fb, 0.0, self.fb, "idle"
            return R.OK
        if cmd == Command.SET_POSITION:
            if self.mode == "home":
                return R.BUSY_HOMING
            # Preset: the encoder reads TARGET_POS here. Mechanical-frame targets are unaffected.
            shift = self.regs[Reg.TARGET_POS] - (self.fb + self.enc_offset)
            self.enc_offset += shift
            if self.stuck_enc is not None:
                self.stuck_enc += shift
            self.homed = True
            return R.OK
        if not self.enabled:
            return R.NOT_ENABLED
        if self.mode == "home":
            return R.BUSY_HOMING
        if cmd == Command.HOME:
            turns = round((self.dem - self.home_mech) / 360_000.0)
            self.target = self.home_mech + 360_000.0 * turns
            self.mode = "home"
            return R.OK
        if cmd in (Command.JOG_POS, Command.JOG_NEG):
            self.mode = "jog"
            self.jog_dir = 1 if cmd == Command.JOG_POS else -1
            return R.OK
        # MOVE_ABS / MOVE_REL
        if cmd == Command.MOVE_ABS and not self.homed:
            self.fault = 0x4A
            return R.NOT_HOMED
        if cmd == Command.MOVE_ABS:
            target_enc = float(self.regs[Reg.TARGET_POS])
        else:  # relative to the running target, or to where the profile stands
            base = self.target if self.mode == "move" else self.dem
            target_enc = base + self.enc_offset + self.regs[Reg.TARGET_POS]
        if self.regs[Reg.SOFT_LIMIT_ENABLE] and self.homed and not (
                self.regs[Reg.SOFT_LIMIT_MIN] <= target_enc <= self.regs[Reg.SOFT_LIMIT_MAX]):
            return R.BEYOND_SOFT_LIMIT
        self.target = target_enc - self.enc_offset
        if self.mode not in ("move",):
            self.mode = "move"  # from idle, stop or jog: the profile continues from (dem, dvel)
        return R.OK


def _check_pairs(addr: int, count: int) -> None:
    """Exception 0x02 when a request covers only half of a 32-bit pair."""
    end = addr + count
    for a in WIDE_REGS:
        if (addr <= a < end) != (addr <= a + 1 < end):
            raise ExceptionReply(ModbusExc.ILLEGAL_ADDRESS)


def _validate(reg: int, v: int, max_vel: int) -> None:
    """Exception 0x03 for a value out of range."""
    ok = True
    if reg == Reg.COMMAND:
        ok = v in Command._value2member_map_
    elif reg in (Reg.PROFILE_VEL, Reg.JOG_VEL):
        ok = 0 < v <= max_vel
    elif reg in (Reg.PROFILE_ACC, Reg.PROFILE_DEC):
        ok = 0 < v <= MAX_ACCEL
    elif reg == Reg.MAX_VEL:
        ok = 0 < v <= HARDWARE_MAX_VEL
    elif reg == Reg.SOFT_LIMIT_ENABLE:
        ok = v in (0, 1)
    elif reg in (Reg.IN_POS_WINDOW, Reg.FOLLOWING_ERR_LIMIT):
        ok = v > 0
    if not ok:
        raise ExceptionReply(ModbusExc.ILLEGAL_VALUE)


_BLOCKS = [
    (IDENTITY_BLOCK[0], IDENTITY_BLOCK[1], True),
    (STATUS_BLOCK[0], STATUS_BLOCK[1], True),
    (MOTION_BLOCK[0], MOTION_BLOCK[1], False),
    (CONFIG_BLOCK[0], CONFIG_BLOCK[1], False),
]


class TableSim:
    """Three simulated axis controllers (z outer, y middle, x inner) behind one Modbus server.

    ``angles``: initial true angles (psi, theta, phi) in degrees for (z, y, x).
    ``hard_limits``: per axis name, (min, max) mechanical degrees; none by default.
    Real tables power up un-homed and disabled, and so does this one unless told otherwise.
    """

    def __init__(self, clock: SimClock | None = None, angles: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 *, homed: bool = False, enabled: bool = False,
                 hard_limits: dict[str, tuple[float, float]] | None = None,
                 units: dict[str, int] | None = None,
                 home_angles: dict[str, float] | None = None) -> None:
        self.clock = clock or SimClock()
        self.units = dict(units or AXIS_UNITS)
        hard_limits = hard_limits or {}
        home_angles = home_angles or {}
        t0 = self.clock.now()
        self.axes: dict[str, AxisSim] = {}
        for name, angle in zip(("z", "y", "x"), angles):
            self.axes[name] = AxisSim(
                name, self.units[name], t0=t0, angle_deg=angle, homed=homed, enabled=enabled,
                hard_limits=hard_limits.get(name), home_angle=home_angles.get(name, 0.0),
            )
        self.framer = "tcp"
        self._handle: ServerHandle | None = None

    # --- the world's view ---------------------------------------------------------------------

    def true_angles(self, t_sim: float | None = None) -> tuple[float, float, float]:
        """TRUE mechanical angles (psi, theta, phi) in degrees at simulated time ``t_sim`` (default now).

        These differ from the encoders when an encoder is stuck (and by the servo lag in motion).
        """
        t = self.clock.now() if t_sim is None else t_sim
        return (self.axes["z"].true_angle(t), self.axes["y"].true_angle(t), self.axes["x"].true_angle(t))

    def axis(self, axis: str | int) -> AxisSim:
        """An axis by name ("z", "y", "x") or unit id."""
        if isinstance(axis, str):
            return self.axes[axis]
        for a in self.axes.values():
            if a.unit == axis:
                return a
        raise KeyError(f"no axis with unit {axis}")

    # --- fault injection (side channel, never through the protocol) --------------------------------

    def alarm(self, axis: str | int, code: int, at_time: float | None = None,
              at_angle: float | None = None) -> None:
        """Raise fault ``code`` on ``axis`` now, at simulated time ``at_time``, or when it passes
        ``at_angle`` (degrees, the controller's frame: what ACTUAL_POS reads)."""
        a = self.axis(axis)
        a.advance(self.clock.now())
        a.alarm(code, at_time, at_angle)

    def silence(self, axis: str | int, on: bool = True) -> None:
        """The axis stops answering. Over Modbus TCP the gateway answers exception 0x0B (gateway
        target failed to respond), as real gateways do; with RTU framing there is no reply at all."""
        self.axis(axis).silent = on

    def stick_encoder(self, axis: str | int, on: bool = True) -> None:
        """Freeze the axis's encoder while the motor keeps moving (ends in a following-error fault)."""
        a = self.axis(axis)
        a.advance(self.clock.now())
        a.stick_encoder(on)

    def estop(self, on: bool = True) -> None:
        """Press or release the E-stop (all axes: fault 0x68, servo off)."""
        t = self.clock.now()
        for a in self.axes.values():
            a.advance(t)
            a.set_estop(on)

    # --- Modbus --------------------------------------------------------------------------------

    def _handler(self, a: AxisSim):
        def handle(address: int, count: int, values: list[int] | None) -> list[int] | None:
            if a.silent:
                if self.framer == "tcp":
                    raise ExceptionReply(ModbusExc.GATEWAY_NO_RESPONSE)
                raise NoReply()
            a.touch(self.clock.now())
            if values is None:
                return a.read_registers(address, count)
            a.write_registers(address, values)
            return None
        return handle

    def devices(self) -> list:
        """The pymodbus device objects (opaque here) for the three units."""
        return [sim_device(a.unit, _BLOCKS, self._handler(a)) for a in self.axes.values()]

    async def start(self, port: int = 0, framer: str = "tcp", host: str = "127.0.0.1") -> int:
        """Serve the three units on (host, port), port 0 = ephemeral; returns the bound port.

        ``framer="rtu"`` serves RTU frames over the TCP socket (URL ``rtu+tcp://host:port``).
        """
        if self._handle is not None:
            raise RuntimeError("TableSim already started")
        self.framer = framer
        self._handle = await start_server(self.devices(), port=port, framer=framer, host=host)
        return self._handle.port

    @property
    def port(self) -> int | None:
        """The bound port while serving."""
        return self._handle.port if self._handle else None

    def url(self) -> str:
        """The URL a Turntable connects to."""
        if self._handle is None:
            raise RuntimeError("TableSim not started")
        scheme = "rtu+tcp" if self.framer == "rtu" else "tcp"
        return f"{scheme}://127.0.0.1:{self._handle.port}"

    async def stop(self) -> None:
        """Stop serving."""
        if self._handle is not None:
            await stop_server(self._handle)
            self._handle = None
