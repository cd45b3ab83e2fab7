"""Device drivers (Modbus turntable, serial compass) and their simulators.

This module is what the rest of the code may depend on without knowing the hardware: the drivers'
base error, the two roles a station's hardware plays for a procedure (:class:`Table` and
:class:`Fixture`: exactly what the engine asks of them, and what their answers must carry) and the
:class:`Station` that pairs them. The concrete drivers (``turntable.Turntable``,
``compass.SerialFixture``) fit these roles; ``station.open_station`` builds them from URLs (the
composition root). The roles are described structurally, without importing the drivers' own data
types, so this module stays the package's ground floor (the drivers import :class:`DriverError` from here).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from physics.table import DRIVE_SETTLE_S


class DriverError(Exception):
    """Base of every driver error."""


#: What the operator does about a station fault, by the driver error (its class name) or the word that
#: names it in the fault's text, before a reset can clear it (the faults said what went wrong only).
_COMPASS_REMEDY = "check the compass's cable and power, and that no other program holds its port"
FAULT_REMEDIES: dict[str, str] = {
    "E-stop": "release the E-stop",
    "BusUnreachable": "check the table's power and its network or serial line to the Modbus URL",
    "AxisUnreachable": "check that axis controller's power and its bus cable",
    "MoveTimeout": "check that nothing blocks the table",
    **dict.fromkeys(("CompassTimeout", "CompassDisconnected", "FixtureError"), _COMPASS_REMEDY),
}


def advised(fault: str) -> str:
    """A station fault's text with what to do about it (:data:`FAULT_REMEDIES`, each remedy once, in the
    order the text names them), then reset the station; the text alone when none applies or it says so."""
    found = sorted((fault.find(key), remedy) for key, remedy in FAULT_REMEDIES.items() if key in fault)
    remedies = list(dict.fromkeys(r for _, r in found if r not in fault))
    return fault + (f" (to clear it: {'; '.join(remedies)}; then reset the station)" if remedies else "")


#: The interpreter's thread switch interval for a process that drives hardware (s; Python's default
#: is 5 ms). The drivers answer on sub-second timeouts (a Modbus request 0.4 s) from threads and event
#: loops that share the interpreter with fits and analyses: each hand-over of the GIL from a
#: CPU-bound thread costs up to one interval, and a Modbus round trip takes a few dozen of them.
#: Measured with two CPU-bound threads beside a simulated table (benchmarks/drivers.py): status
#: reads of three axes took about 200 ms median and 420-650 ms at worst at 5 ms; 27 ms and 71-75 ms
#: at 1 ms.
SWITCH_INTERVAL_S = 0.001


def keep_drivers_responsive() -> None:
    """Shorten the interpreter's thread switch interval (:data:`SWITCH_INTERVAL_S`) so the drivers'
    threads and loops (and simulated devices hosted in the same process) answer within their timeouts
    while other threads compute; and freeze the objects made so far (the command line's imports,
    ~84 000) out of the garbage collector's full collections, which stop every thread while they walk
    them (~40 ms idle for the service's ~220 000 import-time objects, several times that on a loaded
    machine). Called once by every command-line entry point."""
    import gc
    import sys

    sys.setswitchinterval(SWITCH_INTERVAL_S)
    gc.collect()
    gc.freeze()


# ------------------------------------------------------------------------------------ the table

class AxisState(Protocol):
    """One axis's status poll, as far as a run reads it (``turntable.AxisStatus`` is one)."""

    @property
    def enabled(self) -> bool:
        """The drive is enabled."""
        ...

    @property
    def homed(self) -> bool:
        """The axis has been homed since power-up."""
        ...

    @property
    def fault(self) -> bool:
        """The axis is in fault (it needs a reset before it moves again)."""
        ...

    @property
    def fault_code(self) -> int:
        """The controller's fault code (0: none)."""
        ...

    @property
    def fault_name(self) -> str:
        """What the fault code means ("" when no fault)."""
        ...


class Table(Protocol):
    """A three-axis turntable (z outer = psi, y middle = theta, x inner = phi; degrees), as a
    procedure's engine drives it. Every call has a deadline and raises a :class:`DriverError`
    (``MoveTimeout`` for a move that did not finish in time) rather than hang."""

    async def status_all(self) -> Mapping[str, AxisState]:
        """One status poll per axis, by axis name."""
        ...

    async def enable_all(self) -> None:
        """Enable every axis."""
        ...

    async def home_all(self, *, vel_dps: float, acc_dps2: float) -> None:
        """Home every axis at this speed and acceleration, and wait until they are homed."""
        ...

    async def move_to(self, psi: float, theta: float, phi: float, *, speed_dps: float,
                      accel_dps2: float) -> tuple[float, float, float]:
        """Move all three axes to these angles together and wait until each is in position; return
        the encoder positions. On an error every axis is stopped first."""
        ...

    async def scan(self, axis: str, deg: float, speed_dps: float, accel_dps2: float, *,
                   trace: list[tuple[float, float, float]]) -> float:
        """Turn one axis (``"z"``, ``"y"`` or ``"x"``) to ``deg`` while the others hold, appending each
        encoder poll to ``trace`` as it comes (monotonic time before the request, after the reply,
        degrees), so the polls up to an error are kept. Returns the final encoder position. On an
        error every axis is stopped first."""
        ...

    async def positions(self) -> tuple[float, float, float]:
        """The encoder positions (psi, theta, phi)."""
        ...

    async def stop_all(self) -> object:
        """Stop every axis (what it returns is not used)."""
        ...


# ---------------------------------------------------------------------------------- the fixture

class Sample(Protocol):
    """One compass sample, as far as a run records it (``compass.CompassSample`` is one)."""

    @property
    def seq(self) -> int:
        """The device's sample counter (mod 65536): its own sample clock."""
        ...

    @property
    def t_host(self) -> float:
        """When it arrived (``time.monotonic()``)."""
        ...

    @property
    def mag(self) -> tuple[int, int, int]:
        """Magnetometer, raw counts."""
        ...

    @property
    def acc(self) -> tuple[int, int, int]:
        """Accelerometer, raw counts."""
        ...

    @property
    def temp_c(self) -> float:
        """Sensor temperature (deg C)."""
        ...


class SampleStream(Protocol):
    """One compass of a fixture, as a stream of samples."""

    def samples(self, *, timeout: float) -> AsyncIterator[Sample]:
        """Every sample as it arrives from the call on; raises once ``timeout`` seconds pass without one
        (after yielding every sample received)."""
        ...

    def recent(self, n: int) -> list[Sample]:
        """The last ``n`` samples received, oldest first (lines delivered on time before a late burst
        place the burst's lines on the sample clock)."""
        ...


class Fixture(Protocol):
    """The slots of a station's fixture, one compass each, driven together. A call that fails on some
    slots raises ``compass.FixtureError`` carrying the other slots' results and each failed slot's
    error (a failed read's error carries the samples it did receive)."""

    @property
    def compasses(self) -> Mapping[Hashable, SampleStream]:
        """Each slot's compass, by slot."""
        ...

    async def identify_all(self) -> Mapping[Hashable, tuple[str, str, str]]:
        """``{slot: (model, serial, firmware)}``."""
        ...

    async def set_rate_all(self, hz: int) -> None:
        """Set every compass streaming at ``hz`` samples a second."""
        ...

    async def read_all(self, n: int, *, timeout: float | None) -> Mapping[Hashable, Sequence[Sample]]:
        """The next ``n`` samples of every slot, read concurrently within ``timeout`` seconds."""
        ...


# ---------------------------------------------------------------------------------- the station

@dataclass
class Station:
    """The hardware one run drives. ``time_scale`` > 1 for a simulator running faster than real time:
    the engine then reports table time (simulated seconds) in the recording and its events."""

    table: Table
    fixture: Fixture
    time_scale: float = 1.0
    speed_dps: float = 30.0
    accel_dps2: float = 60.0
    sample_rate_hz: int = 20
    name: str = "station"
    #: the drives' settling into position after a move (for the plan's nominal seconds, progress and
    #: time left, not for control: the engine waits for IN_POSITION)
    settle_s: float = DRIVE_SETTLE_S
