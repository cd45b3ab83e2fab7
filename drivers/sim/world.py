"""The simulated world behind a simulated station: lab field, table geometry, the mounted units with
their true parameters, and any extra physics concealed in it.

The forward model is physics/ (``World.body_vectors`` and ``LinearSensor.measure``); this module only
adds what a live device needs on top: time, the table's current true angles, integer raw counts with
saturation, temperature, and the hook for concealed effects.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from physics.effects import Effect  # re-exported: the stage interface lives with the catalogue
from physics.frames import SPECIFIC_FORCE_L
from physics.sensor import Unit
from physics.simulate import World
from physics.table import platform_attitude

#: Raw counts are signed 16-bit on the wire; beyond this the device clips and flags saturation.
RAW_LIMIT = 32767


@dataclass
class SimWorld:
    """One station's truth: ``units[slot]`` mounted on the platform, the table's true angles from
    ``angles(t)`` (encoder degrees of the mechanism, i.e. what a perfect encoder would read)."""

    world: World
    units: list[Unit]
    angles: Callable[[float], tuple[float, float, float]]
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    #: concealed effects: an Effect acts on every slot; (slot, Effect) on that slot only (None: all)
    effects: Sequence[Effect | tuple[int | None, Effect]] = ()
    _last: tuple = field(default=(None, None, None, None), init=False, repr=False)

    def __post_init__(self) -> None:
        pairs = [e if isinstance(e, tuple) else (None, e) for e in self.effects]
        # the table's geometry is shared by every slot, so a geometry effect applies to all
        geometry = self.world.geometry
        for _, e in pairs:
            geometry = e.geometry(geometry)
        self.geometry = geometry  # the table's true geometry, with any concealed axis errors
        self._by_slot = [[e for s, e in pairs if s is None or s == slot] for slot in range(len(self.units))]

    def effects_of(self, slot: int) -> list[Effect]:
        """The effects concealed in the unit of ``slot``, in the order they apply."""
        return list(self._by_slot[slot])

    def temperature_c(self, t: float, slot: int) -> float:
        """Temperature inside the unit at simulated time ``t`` (the lab's, plus the warm-up when the
        world models one)."""
        at = getattr(self.world, "temperature_at", None)
        return float(at(t)) if at is not None else self.world.temperature_c

    def read(self, slot: int, t: float) -> tuple[list[int], list[int], float]:
        """One raw sample of the unit in ``slot`` at simulated time ``t``: (mag counts, acc counts,
        temperature degC). Counts are clipped to +-32767, which the device reports as saturated."""
        unit = self.units[slot]
        effects = self._by_slot[slot]
        ts = t
        for e in effects:
            ts = e.sample_time(ts, slot)
        ang = np.asarray(self.angles(ts), dtype=float)
        key = tuple(ang)
        if key != self._last[0]:  # the table holds still while a pose is sampled: reuse its attitude
            C = platform_attitude(ang[0], ang[1], ang[2], self.geometry)[0]
            self._last = (key, C, C.T @ self.world.field_L, C.T @ SPECIFIC_FORCE_L)
        _, C, h_b, f_b = self._last
        for e in effects:
            h_b = e.body_field(t, slot, ang, C, h_b)
        temp = self.temperature_c(t, slot)
        mag = unit.mag.measure(h_b, self.rng)[0]
        for e in effects:
            mag = e.mag_raw(t, slot, mag, temp)
        acc = unit.acc.measure(f_b, self.rng)[0] if unit.acc is not None else np.zeros(3)
        return _counts(mag), _counts(acc), temp

    def reader(self, slot: int) -> Callable[[float], tuple[list[int], list[int], float]]:
        """``read`` bound to one slot, for that slot's simulated compass."""
        return lambda t: self.read(slot, t)


def _counts(v: np.ndarray) -> list[int]:
    """Round to integer counts, clipped to the 16-bit range."""
    return [int(x) for x in np.clip(np.round(v), -RAW_LIMIT, RAW_LIMIT)]
