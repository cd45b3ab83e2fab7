"""The simulated world behind a simulated station: lab field, table geometry, the mounted units with
their true parameters, and any extra physics concealed in it.

The forward model is physics/ (``platform_attitude`` for the body's field and gravity,
``LinearSensor.expected`` for the sensor's output, plus its white noise); this module only adds what a
live device needs on top: time, the table's current true angles, integer raw counts with saturation,
temperature, and the hook for concealed effects.
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
    _z: list[float] = field(default_factory=list, init=False, repr=False)
    _z_next: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        pairs = [e if isinstance(e, tuple) else (None, e) for e in self.effects]
        # the table's geometry is shared by every slot, so a geometry effect applies to all
        geometry = self.world.geometry
        for _, e in pairs:
            geometry = e.geometry(geometry)
        self.geometry = geometry  # the table's true geometry, with any concealed axis errors
        self._by_slot = [[e for s, e in pairs if s is None or s == slot] for slot in range(len(self.units))]
        #: per slot: (true angles, noise-free mag output, noise-free acc output) at the last sample
        self._expected: list[tuple] = [(None, [], [])] * len(self.units)

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
        ang = tuple(float(a) for a in self.angles(ts))
        expected = self._expected[slot]
        # a held pose reads the same noise-free output sample after sample: computed once per attitude
        # (a simulated station streams 20 lines a second per unit, times the time scale)
        if effects or expected[0] != ang:
            C, h_b, f_b = self._attitude(ang)
            for e in effects:
                h_b = e.body_field(t, slot, np.asarray(ang), C, h_b)
            acc = unit.acc.expected(f_b)[0].tolist() if unit.acc is not None else [0.0, 0.0, 0.0]
            expected = self._expected[slot] = (ang, unit.mag.expected(h_b)[0].tolist(), acc)
        temp = self.temperature_c(t, slot)
        mag = self._noisy(expected[1], unit.mag.noise_lsb)
        if effects:
            raw = np.asarray(mag)
            for e in effects:
                raw = e.mag_raw(t, slot, raw, temp)
            mag = raw.tolist()
        acc = self._noisy(expected[2], unit.acc.noise_lsb) if unit.acc is not None else expected[2]
        return _counts(mag), _counts(acc), temp

    def _attitude(self, ang: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(C_LP, h_b, f_b) at true angles ``ang``; the last one is kept, as every slot asks for it."""
        if ang != self._last[0]:
            C = platform_attitude(ang[0], ang[1], ang[2], self.geometry)[0]
            self._last = (ang, C, C.T @ self.world.field_L, C.T @ SPECIFIC_FORCE_L)
        return self._last[1], self._last[2], self._last[3]

    def _noisy(self, v: list[float], sigma: float) -> list[float]:
        """``v`` plus white noise of ``sigma`` (LSB) per axis, from ``rng`` in blocks (one draw per
        sample costs more than the rest of the sample)."""
        if sigma <= 0:
            return v
        if self._z_next + 3 > len(self._z):
            self._z, self._z_next = self.rng.standard_normal(3 * 1024).tolist(), 0
        z, i = self._z, self._z_next
        self._z_next = i + 3
        return [v[0] + sigma * z[i], v[1] + sigma * z[i + 1], v[2] + sigma * z[i + 2]]

    def reader(self, slot: int) -> Callable[[float], tuple[list[int], list[int], float]]:
        """``read`` bound to one slot, for that slot's simulated compass."""
        return lambda t: self.read(slot, t)


def _counts(v: Sequence[float]) -> list[int]:
    """Round to integer counts (half to even, as numpy), clipped to the 16-bit range."""
    return [max(-RAW_LIMIT, min(RAW_LIMIT, round(x))) for x in v]
