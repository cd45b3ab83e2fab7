"""The composition root of a station: the concrete drivers built from URLs.

The engine only knows the :class:`~drivers.Table` and :class:`~drivers.Fixture` roles; this is the one
place that picks the Modbus :class:`~drivers.turntable.Turntable` and the serial
:class:`~drivers.compass.SerialFixture` for them (the service's worker, the CLI, the benchmarks and
the tests all open their stations here).
"""

from __future__ import annotations

import ipaddress
import os
import socket
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import lru_cache
from urllib.parse import urlsplit

from drivers import Station
from drivers.compass import SerialFixture
from drivers.modbus import BusURL
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


@lru_cache(maxsize=256)  # (a station check resolves every station's hosts: a slow resolver once, not each time)
def _host(name: str) -> str:
    """A host as one address: an IP as written, a name resolved (``localhost`` is 127.0.0.1); a name that
    does not resolve here stays itself, lower-cased."""
    name = name.lower()
    try:
        return str(ipaddress.ip_address(name))
    except ValueError:
        pass
    try:
        return sorted(info[4][0] for info in socket.getaddrinfo(name, None, socket.AF_INET))[0]
    except (OSError, IndexError):
        return name


def hardware_key(url: str, modbus: bool = False) -> str:
    """The piece of hardware a table's (``modbus``) or a compass's URL reaches, whatever its spelling: a
    network endpoint as ``host:port`` (the framing, ``?timeout=`` and the host's name aside), a device
    as its real path (``/dev/serial/by-id/...`` is the ``/dev/ttyUSB0`` it links to). Two URLs with one
    key drive one device."""
    if modbus:
        try:
            bus = BusURL.parse(url)
        except ValueError:  # a station stored before its form was refused ("tcp://HOST", no port): as written
            return url
        return f"{_host(bus.host)}:{bus.port}" if bus.kind != "serial" else os.path.realpath(bus.device)
    if "://" not in url:
        return os.path.realpath(url)
    parts = urlsplit(url)
    if parts.hostname and parts.port:  # socket://, rfc2217://
        return f"{_host(parts.hostname)}:{parts.port}"
    return url
