"""Simulated time: one clock per simulated station, so motion, sample rates and settle times scale together."""

from __future__ import annotations

import asyncio
import time


class SimClock:
    """Simulated seconds since the station started, running ``time_scale`` times faster than the wall.

    Every simulator reads time from here (never from ``time`` directly), so a time scale of 20 makes a
    2-minute calibration take 6 wall seconds with identical physics.
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        self.time_scale = float(time_scale)
        self._t0 = time.monotonic()

    def now(self) -> float:
        """Simulated seconds since start."""
        return (time.monotonic() - self._t0) * self.time_scale

    def wall(self, sim_seconds: float) -> float:
        """Wall seconds that ``sim_seconds`` of simulated time take."""
        return sim_seconds / self.time_scale

    async def sleep(self, sim_seconds: float) -> None:
        """Sleep for ``sim_seconds`` of simulated time."""
        await asyncio.sleep(max(0.0, sim_seconds) / self.time_scale)

    async def sleep_until(self, sim_t: float) -> None:
        """Sleep until the simulated clock reads ``sim_t``."""
        await self.sleep(sim_t - self.now())
