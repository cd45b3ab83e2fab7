"""The composition root of a station: the concrete drivers built from URLs.

The engine only knows the :class:`~drivers.Table` and :class:`~drivers.Fixture` roles; this is the one
place that picks the Modbus :class:`~drivers.turntable.Turntable` and the serial
:class:`~drivers.compass.SerialFixture` for them (the service's worker, the CLI, the benchmarks and
the tests all open their stations here).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from drivers import Station
from drivers.compass import SerialFixture
from drivers.turntable import POLL_INTERVAL, Turntable


@asynccontextmanager
async def open_station(modbus: str, compasses: list[str], *, time_scale: float = 1.0,
                       sample_rate_hz: int = 20, name: str = "station") -> AsyncIterator[Station]:
    """Connect a station's table (Modbus URL) and fixture (one serial URL per slot); close both after."""
    # status polls at the same table-time interval whatever the time scale (not more often than every 0.5 ms)
    table = Turntable(modbus, poll_interval=max(POLL_INTERVAL / time_scale, 0.0005))
    fixture = SerialFixture({slot: url for slot, url in enumerate(compasses)})
    await table.connect()
    try:
        await fixture.open()
        try:
            yield Station(table, fixture, time_scale=time_scale, sample_rate_hz=sample_rate_hz, name=name)
        finally:
            await fixture.close()
    finally:
        await table.close()
