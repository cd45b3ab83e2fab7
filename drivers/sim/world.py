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

from physics.frames import SPECIFIC_FORCE_L
from physics.sensor import Unit
from physics.simulate import World
from physics.table import platform_attitude

#: Raw counts are signed 16-bit on the wire; beyond this the device clips and flags saturation.
RAW_LIMIT = 32767


class Effect:
    """Extra physics the nominal model leaves out, concealed in the simulation (the hook for the
    discrepancy engine's catalogue). Each method defaults to "no effect"; an effect overrides the
    stage(s) it acts on.

    Stages, in the order the world applies them for one sample of one unit at simulated time ``t``:
    ``sample_time`` (which instant's table angles the sample sees, e.g. a filter lag),
    ``body_field`` (the field in the body frame, in units of the lab field, before the sensor: stage
    hard or soft iron, gradients, field drift), ``mag_raw`` (the magnetometer output in counts, after
    the linear sensor: nonlinearity, temperature drift, hysteresis, mains pickup). Return new arrays;
    never modify the inputs in place (the world reuses them while the table holds still).
    """

    def sample_time(self, t: float, slot: int) -> float:
        """The instant whose table angles this sample sees."""
        return t

    def body_field(self, t: float, slot: int, angles_deg: np.ndarray, C_LP: np.ndarray, h_b: np.ndarray) -> np.ndarray:
        """The field in the body frame (3,) at encoder angles ``angles_deg`` (psi, theta, phi)."""
        return h_b

    def mag_raw(self, t: float, slot: int, raw: np.ndarray, temp_c: float) -> np.ndarray:
        """The magnetometer output (3,) in counts, before quantisation."""
        return raw


@dataclass
class SimWorld:
    """One station's truth: ``units[slot]`` mounted on the platform, the table's true angles from
    ``angles(t)`` (encoder degrees of the mechanism, i.e. what a perfect encoder would read)."""

    world: World
    units: list[Unit]
    angles: Callable[[float], tuple[float, float, float]]
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    effects: Sequence[Effect] = ()
    _last: tuple = field(default=(None, None, None, None), init=False, repr=False)

    def temperature_c(self, t: float, slot: int) -> float:
        """Temperature inside the unit (constant lab temperature; effects may model warm-up)."""
        return self.world.temperature_c

    def read(self, slot: int, t: float) -> tuple[list[int], list[int], float]:
        """One raw sample of the unit in ``slot`` at simulated time ``t``: (mag counts, acc counts,
        temperature degC). Counts are clipped to +-32767, which the device reports as saturated."""
        unit = self.units[slot]
        ts = t
        for e in self.effects:
            ts = e.sample_time(ts, slot)
        ang = np.asarray(self.angles(ts), dtype=float)
        key = tuple(ang)
        if key != self._last[0]:  # the table holds still while a pose is sampled: reuse its attitude
            C = platform_attitude(ang[0], ang[1], ang[2], self.world.geometry)[0]
            self._last = (key, C, C.T @ self.world.field_L, C.T @ SPECIFIC_FORCE_L)
        _, C, h_b, f_b = self._last
        for e in self.effects:
            h_b = e.body_field(t, slot, ang, C, h_b)
        temp = self.temperature_c(t, slot)
        mag = unit.mag.measure(h_b, self.rng)[0]
        for e in self.effects:
            mag = e.mag_raw(t, slot, mag, temp)
        acc = unit.acc.measure(f_b, self.rng)[0] if unit.acc is not None else np.zeros(3)
        return _counts(mag), _counts(acc), temp

    def reader(self, slot: int) -> Callable[[float], tuple[list[int], list[int], float]]:
        """``read`` bound to one slot, for that slot's simulated compass."""
        return lambda t: self.read(slot, t)


def _counts(v: np.ndarray) -> list[int]:
    """Round to integer counts, clipped to the 16-bit range."""
    return [int(x) for x in np.clip(np.round(v), -RAW_LIMIT, RAW_LIMIT)]
