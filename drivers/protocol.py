"""The wire protocols of PROTOCOLS.md as constants, imported by the drivers and the simulators alike.

Nothing here does I/O. Change a number here and both sides follow.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag

# --------------------------------------------------------------------------------------------------
# Turntable: one Modbus unit per axis, all holding registers, 0-based protocol addresses.
# --------------------------------------------------------------------------------------------------

#: Default Modbus unit ids: outer z (azimuth), middle y, inner x.
AXIS_UNITS: dict[str, int] = {"z": 1, "y": 2, "x": 3}
COUNTS_PER_DEG = 1000
PROTOCOL_VERSION = 1
PRODUCT_ID = 0x5443  # "TC"


class Reg(IntEnum):
    """Holding-register addresses. 32-bit values occupy (addr, addr+1), high word first."""

    PRODUCT_ID = 0x0000
    FW_VERSION = 0x0001
    SERIAL_NO = 0x0002  # u32
    AXIS_INDEX = 0x0004
    COUNTS_PER_DEG = 0x0005
    PROTOCOL_VERSION = 0x0006

    STATUS = 0x0010
    FAULT_CODE = 0x0011
    ACTUAL_POS = 0x0012  # i32 mdeg, multi-turn
    ACTUAL_VEL = 0x0014  # i32 mdeg/s
    DEMAND_POS = 0x0016  # i32
    FOLLOWING_ERR = 0x0018  # i32
    CMD_COUNT = 0x001A
    LAST_CMD_RESULT = 0x001B
    WARNING_CODE = 0x001C
    TEMPERATURE = 0x001D  # i16, 0.1 degC
    ACTUAL_POS_MOD = 0x001E  # u32, 0..359999

    TARGET_POS = 0x0020  # i32
    PROFILE_VEL = 0x0022  # u32
    PROFILE_ACC = 0x0024  # u32
    PROFILE_DEC = 0x0026  # u32
    COMMAND = 0x0028
    JOG_VEL = 0x002A  # u32

    SOFT_LIMIT_MIN = 0x0040  # i32
    SOFT_LIMIT_MAX = 0x0042  # i32
    SOFT_LIMIT_ENABLE = 0x0044
    IN_POS_WINDOW = 0x0045
    MAX_VEL = 0x0046  # u32
    HOME_OFFSET = 0x0048  # i32
    HOME_METHOD = 0x004A
    WATCHDOG_MS = 0x004B
    FOLLOWING_ERR_LIMIT = 0x004C  # u32


#: The register blocks a controller maps: (first address, count). Anything else is exception 0x02.
IDENTITY_BLOCK = (0x0000, 0x10)
STATUS_BLOCK = (0x0010, 0x10)
MOTION_BLOCK = (0x0020, 0x0C)
CONFIG_BLOCK = (0x0040, 0x0E)

#: 32-bit registers (the first address of each pair) and whether each is signed.
WIDE_REGS: dict[int, bool] = {
    Reg.SERIAL_NO: False,
    Reg.ACTUAL_POS: True,
    Reg.ACTUAL_VEL: True,
    Reg.DEMAND_POS: True,
    Reg.FOLLOWING_ERR: True,
    Reg.ACTUAL_POS_MOD: False,
    Reg.TARGET_POS: True,
    Reg.PROFILE_VEL: False,
    Reg.PROFILE_ACC: False,
    Reg.PROFILE_DEC: False,
    Reg.JOG_VEL: False,
    Reg.SOFT_LIMIT_MIN: True,
    Reg.SOFT_LIMIT_MAX: True,
    Reg.MAX_VEL: False,
    Reg.HOME_OFFSET: True,
    Reg.FOLLOWING_ERR_LIMIT: False,
}
#: Signed 16-bit registers.
SIGNED_REGS = {Reg.TEMPERATURE}
#: Registers a host may write (the motion/command and configuration blocks).
WRITABLE = set(range(0x0020, 0x002C)) | set(range(0x0040, 0x004E))

# Defaults of the configuration block.
DEFAULT_IN_POS_WINDOW = 5  # mdeg
DEFAULT_MAX_VEL = 60_000  # mdeg/s
DEFAULT_FOLLOWING_ERR_LIMIT = 1000  # mdeg


class Status(IntFlag):
    """STATUS register bits."""

    READY = 1 << 0
    ENABLED = 1 << 1
    MOVING = 1 << 2
    IN_POSITION = 1 << 3
    HOMED = 1 << 4
    HOMING = 1 << 5
    FAULT = 1 << 6
    WARNING = 1 << 7
    LIMIT_POS = 1 << 8
    LIMIT_NEG = 1 << 9
    SOFT_LIMIT_POS = 1 << 10
    SOFT_LIMIT_NEG = 1 << 11
    ESTOP = 1 << 12
    JOGGING = 1 << 13
    STOPPING = 1 << 14


class Command(IntEnum):
    """COMMAND register codes; a write executes the command."""

    NOP = 0
    MOVE_ABS = 1
    MOVE_REL = 2
    JOG_POS = 3
    JOG_NEG = 4
    HOME = 5
    STOP = 6
    QUICK_STOP = 7
    ENABLE = 8
    DISABLE = 9
    RESET_FAULT = 10
    SET_POSITION = 11


class CmdResult(IntEnum):
    """LAST_CMD_RESULT: why a command was refused (a refusal is not a Modbus exception)."""

    OK = 0
    NOT_ENABLED = 1
    NOT_HOMED = 2
    FAULT_ACTIVE = 3
    BEYOND_SOFT_LIMIT = 4
    BUSY_HOMING = 5
    ESTOP = 6


CMD_RESULT_TEXT: dict[int, str] = {
    CmdResult.OK: "ok",
    CmdResult.NOT_ENABLED: "not enabled",
    CmdResult.NOT_HOMED: "not homed",
    CmdResult.FAULT_ACTIVE: "fault active",
    CmdResult.BEYOND_SOFT_LIMIT: "beyond soft limit",
    CmdResult.BUSY_HOMING: "busy homing",
    CmdResult.ESTOP: "E-stop",
}

#: FAULT_CODE values (numbered as Oriental Motor's AZ alarms) and their names.
FAULTS: dict[int, str] = {
    0x10: "following error",
    0x20: "overcurrent",
    0x21: "drive overheat",
    0x25: "undervoltage",
    0x28: "encoder error",
    0x30: "overload",
    0x31: "overspeed",
    0x4A: "homing required",
    0x62: "homing failed",
    0x63: "home sensor not found",
    0x66: "hardware limit",
    0x67: "soft limit",
    0x68: "E-stop",
    0x70: "invalid motion data",
    0x85: "communication watchdog",
}
#: Faults that RESET_FAULT clears. The others need a power cycle or service (E-stop: release it first).
RESETTABLE_FAULTS = {0x10, 0x21, 0x30, 0x31, 0x4A, 0x62, 0x63, 0x66, 0x67, 0x70, 0x85}


#: What the technician does about a fault a reset alone does not clear.
FAULT_ADVICE: dict[int, str] = {
    0x68: "release the E-stop, then reset",
    0x20: "a reset does not clear it: check the motor and its cable, then power-cycle the axis controller",
    0x25: "a reset does not clear it: check the axis controller's supply",
    0x28: "a reset does not clear it: check the encoder cable, then power-cycle the axis controller",
}


def with_advice(text: str, code: int) -> str:
    """``text`` about fault ``code`` and, for one a reset alone does not clear, what to do (:data:`FAULT_ADVICE`)."""
    return text + (f" ({FAULT_ADVICE[code]})" if code in FAULT_ADVICE else "")


def fault_name(code: int) -> str:
    """Human name of a FAULT_CODE value, e.g. ``0x10 following error``."""
    return f"0x{code:02X} {FAULTS.get(code, 'unknown fault')}"


def status_names(status: int) -> list[str]:
    """Names of the STATUS bits that are set, lowest bit first."""
    return [bit.name for bit in Status if status & bit and bit.name]


class ModbusExc(IntEnum):
    """Modbus exception codes this map uses (protocol errors only)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_ADDRESS = 0x02
    ILLEGAL_VALUE = 0x03
    DEVICE_FAILURE = 0x04
    GATEWAY_NO_RESPONSE = 0x0B


def to_words(value: int, signed: bool, low_word_first: bool = False) -> list[int]:
    """A 32-bit value as two 16-bit registers (high word first unless ``low_word_first``)."""
    lo_bound, hi_bound = (-(1 << 31), (1 << 31) - 1) if signed else (0, (1 << 32) - 1)
    if not lo_bound <= value <= hi_bound:
        raise ValueError(f"{value} does not fit a {'signed' if signed else 'unsigned'} 32-bit register")
    u = value & 0xFFFFFFFF
    words = [(u >> 16) & 0xFFFF, u & 0xFFFF]
    return words[::-1] if low_word_first else words


def from_words(words: list[int] | tuple[int, int], signed: bool, low_word_first: bool = False) -> int:
    """The 32-bit value held in two registers."""
    hi, lo = (words[1], words[0]) if low_word_first else (words[0], words[1])
    u = ((hi & 0xFFFF) << 16) | (lo & 0xFFFF)
    return u - (1 << 32) if signed and u & 0x80000000 else u


def to_i16(word: int) -> int:
    """A register read as a signed 16-bit value."""
    return word - 0x10000 if word & 0x8000 else word


# --------------------------------------------------------------------------------------------------
# Compass: NMEA-0183-framed ASCII sentences, talker $PXDC.
# --------------------------------------------------------------------------------------------------

TALKER = "PXDC"
MAX_LINE = 128  # bytes, including $ and *HH; longer lines are dropped
DEFAULT_BAUD = 115200
BAUDS = (9600, 19200, 38400, 57600, 115200)
RATES_HZ = (0, 1, 2, 5, 10, 20, 50, 100)
AVG_RANGE = (1, 64)
RAW_FIELDS = 10  # RAW,seq,mx,my,mz,ax,ay,az,temp,st
SEQ_MODULO = 1 << 16


class Nak(IntEnum):
    """NAK reason codes."""

    BAD_CHECKSUM = 1
    UNKNOWN_COMMAND = 2
    BAD_ARGUMENT = 3
    BUSY = 4


class CompassStatus(IntFlag):
    """The hex status field of a RAW sentence."""

    MAG_SATURATED = 1 << 0
    ACC_SATURATED = 1 << 1
    SELF_TEST_FAILED = 1 << 2


def checksum(body: bytes) -> int:
    """XOR of every byte between ``$`` and ``*``."""
    c = 0
    for b in body:
        c ^= b
    return c


def sentence(*fields: object) -> bytes:
    """A complete line ``$PXDC,<fields>*HH\\r\\n`` (fields joined with commas, checksum upper case)."""
    body = ",".join([TALKER, *(str(f) for f in fields)]).encode("ascii")
    return b"$" + body + b"*%02X\r\n" % checksum(body)


def banner(model: str, firmware: str, serial: str) -> bytes:
    """The boot banner: plain text, not a sentence, e.g. ``XDC-3 compass fw 1.2.0 SN 10234 ready``."""
    return f"{model} compass fw {firmware} SN {serial} ready\r\n".encode("ascii")
