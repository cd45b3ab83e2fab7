"""The catalogue of physical effects the nominal model leaves out (issue 6).

Each entry has an id, a plain-language description, the signature it leaves in a recording, what the
nominal model absorbs of it, the parameters of its forward model with plausibility limits, and how to
separate it from the effects it can be confused with. Two forward implementations use the same
parameters and meaning:

- :class:`Effect` subclasses here *conceal* an effect in a simulation, sample by sample in time
  (stages ``geometry``, ``sample_time``, ``body_field``, ``mag_raw``); the simulated station
  (drivers/sim/world.py) and the offline timeline simulator (physics/simulate.py) apply them.
- physics/discrepancy/ *fits* each effect as a parametric term of the twin, vectorised: its entry in
  physics/discrepancy/registry.py (keyed by the same id) builds its regressors and reads the rest
  (frame, plausible ranges, needs) from :data:`CATALOGUE`. A new effect is an :class:`Entry` here, its
  concealment class here, and one registry entry.

They are written separately on purpose: the blind proof (``compasscal prove``) would not catch a
mistake that both sides shared.

Conventions (PHYSICS.md): ``h_b`` is the field in body axes in lab-field units; ``C_LP`` the platform
attitude; gimbal angles (psi, theta, phi) about z (outer), y (middle), x (inner). A vector fixed in the
*outer* stage is seen in the body frame through ``(Ry(theta) Rx(phi))^T``, one fixed in the *middle*
stage through ``Rx(phi)^T``. Anything fixed in the platform (inner stage) is the unit's own bias or
matrix: the nominal model absorbs it completely.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from physics.frames import rot_x, rot_y
from physics.table import TableGeometry

#: Stages of the table an effect can ride on (the platform itself is absorbed by the nominal model).
STAGES = ("outer", "middle")

#: A hysteresis reversal: the field along a body axis must move this far (lab-field units) for its
#: direction of approach to count as changed (shared definition of "direction of approach").
HYSTERESIS_STEP = 0.002


@dataclass(frozen=True)
class Entry:
    """One catalogue entry (see module docstring)."""

    id: str
    title: str
    description: str
    signature: str
    absorbed: str
    params: dict[str, str]  # name -> unit and shape
    plausible: dict[str, float]  # name -> largest plausible |value| (anything bigger is suspect)
    needs: str  # what a recording must contain for the effect to be identifiable
    separate: dict[str, str] = field(default_factory=dict)  # other id -> experiment that separates them
    #: where it lives in the analyser's one finding schema: (frame, form, against); frame "stage" is the
    #: fitted stage's (outer or middle)
    model: tuple[str, str, str | None] = ("sensor", "offset", None)


CATALOGUE: dict[str, Entry] = {e.id: e for e in [
    Entry(
        "stage_hard_iron", "Permanent magnet on a table stage",
        "A magnetised part (a motor, a steel screw) fixed to the outer or middle gimbal adds a constant "
        "field in that stage's frame, which the unit sees turning as the inner axes turn.",
        "first harmonics of the residual against theta_t and phi_t, with no dependence on psi_t; "
        "stationary in the stage's frame",
        "a magnet on the platform itself is indistinguishable from the unit's bias; one on the base "
        "(lab-fixed) only changes the apparent field I, D",
        {"stage": "outer | middle", "m": "lab-field units, 3 (in the stage frame)"},
        {"m": 0.05},
        "poses tilted about both inner axes (theta_t and phi_t)",
        {"stage_soft_iron": "repeat the tilted poses at two azimuths 90 deg apart: induced iron follows "
                            "the field, a magnet does not",
         "table_axis_error": "repeat with the unit rotated by 90 deg on the platform: a magnet moves with "
                             "the stage, an axis error with the geometry",
         "field_gradient": "sweep the inner axes at several azimuths (the characterize plan): a gradient's "
                           "signature turns with the azimuth, a stage magnet's does not"},
        model=('stage', 'offset', None),
    ),
    Entry(
        "stage_soft_iron", "Magnetisable material on a table stage",
        "Soft steel on the outer or middle gimbal is magnetised by the Earth field; the induced field "
        "follows the field's direction in that stage's frame.",
        "residual linear in the field expressed in the stage frame: depends on psi_t through the stage's "
        "view of the field, and on theta_t, phi_t through the turn back into the body",
        "soft iron on the platform is indistinguishable from the unit's matrix M",
        {"stage": "outer | middle", "A": "symmetric 3x3, dimensionless (induced / inducing field)"},
        {"A": 0.05},
        "tilted poses at several azimuths",
        {"stage_hard_iron": "repeat the tilted poses at two azimuths 90 deg apart"},
        model=('stage', 'linear', None),
    ),
    Entry(
        "nonlinearity", "Output not linear in the field",
        "Each sensor axis responds with a small cubic term (the onset of saturation, or an odd "
        "non-linearity of the sensing element).",
        "third harmonics against every rotation angle, largest on the axis that sees the largest field",
        "the linear part of the response (k) absorbs the cubic term's first-harmonic share",
        {"c3": "LSB at full field, 3 (raw += c3 * u^3, u = linear output / k)"},
        {"c3": 0.02 * 5000},
        "any full turns (third harmonics need at least 8 poses per turn)",
        {"field_gradient": "shift the unit on the platform: a gradient changes, a non-linearity does not"},
        model=('sensor', 'cubic', None),
    ),
    Entry(
        "temperature_drift", "Bias drifting with temperature",
        "The sensor's offset follows its temperature (warm-up after power-on, the room).",
        "residual following temp_c, fixed in the sensor frame whatever the attitude",
        "a constant temperature is absorbed by the bias",
        {"bias_per_c": "LSB per deg C, 3"},
        {"bias_per_c": 20.0},
        "a temperature that changes during the run (temp_c logged)",
        {"field_drift": "hold one pose for the warm-up, then repeat the run warm: a field drift does not "
                        "follow the unit's temperature and turns with the table",
         "mains_interference": "log temperature at a constant attitude for several minutes"},
        model=('sensor', 'offset', 'temp_c'),
    ),
    Entry(
        "field_drift", "Lab field changing during the run",
        "The ambient field changes slowly (a vehicle, a lift, diurnal variation, a nearby instrument).",
        "residual trend in time that is fixed in the lab frame: it turns with the table, unlike a sensor drift",
        "a constant field offset is absorbed into the fitted field direction",
        {"rate_per_s": "lab-field units per second, 3 (lab frame)"},
        {"rate_per_s": 1e-4},
        "a run long enough for the drift to show, with a repeated closing pose",
        {"temperature_drift": "repeat the run at a constant temperature, or log a reference magnetometer "
                              "fixed in the lab"},
        model=('lab', 'offset', 'time'),
    ),
    Entry(
        "time_lag", "Sample lags the encoder angle",
        "The compass's output filter or a time-stamp skew makes each sample see the table where it was a "
        "moment before.",
        "only while moving: residual proportional to the rate of turn, changing sign with the direction",
        "nothing on static holds (invisible without motion)",
        {"lag_s": "seconds"},
        {"lag_s": 0.5},
        "samples taken while the table turns, both ways",
        {"hysteresis": "hold still after each approach: a lag vanishes at rest, hysteresis stays"},
        model=('sensor', 'lag', 'rate'),
    ),
    Entry(
        "hysteresis", "Output depends on the direction of approach",
        "The sensing element remembers the last direction its field changed (magnetic hysteresis of "
        "the core or flux concentrator).",
        "static holds at the same pose differ by approach direction; the offset follows the sign of the "
        "last field change on each axis",
        "an average over both approaches is absorbed by the bias",
        {"offset": "lab-field units, 3 (body axes)"},
        {"offset": 0.01},
        "holds approached from both sides",
        {"time_lag": "hold still longer after each approach: a lag vanishes at rest, hysteresis stays"},
        model=('platform', 'hysteresis', None),
    ),
    Entry(
        "table_axis_error", "Table axes not ideal",
        "Axes not perpendicular and encoder zeros offset, so the platform's true attitude differs from "
        "the encoder angles; the accelerometer sees it too.",
        "residual in the direction of the derivative of the field with respect to each error angle, "
        "visible only in tilted poses",
        "the azimuth zero is absorbed into D and the base tilt into the field direction",
        {"nonperp_deg": "degrees, 2 (y about outer x, x about middle z)",
         "encoder_zero_deg": "degrees, 2 (y, x)"},
        {"nonperp_deg": 0.2, "encoder_zero_deg": 0.5},
        "poses tilted about both inner axes at several azimuths",
        {"stage_hard_iron": "repeat with the unit rotated by 90 deg on the platform"},
        model=('table', 'rotation', None),
    ),
    Entry(
        "field_gradient", "Sensor off the rotation centre in a non-uniform field",
        "The sensing element sits away from the intersection of the axes, so it moves through a field "
        "gradient as the table turns.",
        "second harmonics of the residual against psi_t and the other axes",
        "nothing at the rotation centre",
        {"gradient": "lab-field units per metre, 5 (Gxx, Gyy, Gxy, Gxz, Gyz; traceless symmetric)",
         "offset_m": "metres, 3 (sensor position in body axes)"},
        {"gradient_times_offset": 0.01},
        "full turns about at least two axes",
        {"nonlinearity": "shift the unit on the platform: a gradient changes, a non-linearity does not"},
        model=('lab', 'gradient', None),
    ),
    Entry(
        "mains_interference", "50/60 Hz pickup aliased into the samples",
        "Mains-frequency field or supply ripple is sampled below its Nyquist rate and folds to a slow "
        "beat or a near-Nyquist alternation.",
        "a narrow line in the spectrum of the static holds, coherent across holds, fixed in the sensor frame",
        "its average over a hold is nearly zero: pose means hide it",
        {"amplitude_lsb": "LSB, 3", "alias_hz": "Hz (the frequency seen after sampling)", "phase_rad": "rad"},
        {"amplitude_lsb": 50.0},
        "static holds of several seconds",
        {"temperature_drift": "hold one pose for several minutes and look at the spectrum"},
        model=('sensor', 'line', 'time'),
    ),
]}

#: Pseudo-findings that are not physical effects of the catalogue.
UNEXPLAINED = "unexplained"
PARAMETER_SHIFT = "parameter_shift"


def separating_experiment(a: str, b: str) -> str:
    """The experiment that would tell effect ``a`` from ``b`` (either order; a generic one if none is listed)."""
    for x, y in ((a, b), (b, a)):
        if x in CATALOGUE and y in CATALOGUE[x].separate:
            return CATALOGUE[x].separate[y]
    return (f"a characterize run (both directions at two speeds, holds approached from both sides, tilted "
            f"poses at several azimuths, temperature logged) makes {a} and {b} separable")


# --------------------------------------------------------------------------------------------------
# Concealment: effects applied sample by sample in a simulation
# --------------------------------------------------------------------------------------------------

class Effect:
    """Extra physics concealed in a simulation. Each stage defaults to "no effect"; an effect
    overrides the stage(s) it acts on.

    Stages, in the order a simulated world applies them: ``geometry`` once, when the world is built
    (table axis errors: the accelerometer sees them too); then for each sample of one unit at
    simulated time ``t``: ``sample_time`` (which instant's table angles the sample sees, e.g. a filter
    lag), ``body_field`` (the field in body axes, in lab-field units, before the sensor: stage iron,
    gradients, field drift, hysteresis), ``mag_raw`` (the magnetometer output in counts after the
    linear sensor: nonlinearity, temperature drift, mains pickup). Return new arrays; never modify
    the inputs in place (the world reuses them while the table holds still). ``body_field`` is called
    for every sample the unit produces, in time order, moving or not.
    """

    id: str = ""

    def geometry(self, g: TableGeometry) -> TableGeometry:
        """The table's true geometry with this effect."""
        return g

    def sample_time(self, t: float, slot: int) -> float:
        """The instant whose table angles this sample sees."""
        return t

    def body_field(self, t: float, slot: int, angles_deg: np.ndarray, C_LP: np.ndarray, h_b: np.ndarray) -> np.ndarray:
        """The field in the body frame (3,) at true gimbal angles ``angles_deg`` (psi, theta, phi)."""
        return h_b

    def mag_raw(self, t: float, slot: int, raw: np.ndarray, temp_c: float) -> np.ndarray:
        """The magnetometer output (3,) in counts, before quantisation."""
        return raw

    def params(self) -> dict[str, Any]:
        """The true parameters, JSON-safe, named as in :data:`CATALOGUE`."""
        return {}


def stage_to_body(stage: str, theta_deg: float, phi_deg: float) -> np.ndarray:
    """Rotation Q (3x3) taking a vector in ``stage``'s frame to body axes: ``v_b = Q v_stage``."""
    if stage == "outer":
        return (rot_y(theta_deg) @ rot_x(phi_deg)).T
    if stage == "middle":
        return rot_x(phi_deg).T
    raise ValueError(f"stage: expected one of {STAGES}, got {stage!r}")


def _vec(v: Sequence[float], n: int, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected {n} finite numbers, got {v!r}")
    return a


class StageHardIron(Effect):
    """A magnet fixed in ``stage``'s frame: ``h_b += Q m``."""

    id = "stage_hard_iron"

    def __init__(self, stage: str, m: Sequence[float]) -> None:
        stage_to_body(stage, 0.0, 0.0)  # validates the stage
        self.stage, self.m = stage, _vec(m, 3, "m")

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        return h_b + stage_to_body(self.stage, angles_deg[1], angles_deg[2]) @ self.m

    def params(self) -> dict[str, Any]:
        return {"stage": self.stage, "m": self.m.tolist()}


def symmetric(a6: Sequence[float]) -> np.ndarray:
    """3x3 symmetric matrix from (xx, yy, zz, xy, xz, yz)."""
    xx, yy, zz, xy, xz, yz = _vec(a6, 6, "A")
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


class StageSoftIron(Effect):
    """Soft iron fixed in ``stage``'s frame: the induced field ``A h_stage``, i.e. ``h_b += Q A Q^T h_b``."""

    id = "stage_soft_iron"

    def __init__(self, stage: str, A: Sequence[Sequence[float]]) -> None:
        stage_to_body(stage, 0.0, 0.0)
        A = np.asarray(A, dtype=float)
        if A.shape != (3, 3) or not np.allclose(A, A.T):
            raise ValueError("A: expected a symmetric 3x3 matrix")
        self.stage, self.A = stage, A

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        Q = stage_to_body(self.stage, angles_deg[1], angles_deg[2])
        return h_b + Q @ self.A @ Q.T @ h_b

    def params(self) -> dict[str, Any]:
        return {"stage": self.stage, "A": self.A.tolist()}


class Nonlinearity(Effect):
    """A cubic term per sensor axis: ``raw += c3 * u^3`` with ``u = (raw - bias) / k`` (the linear output
    in lab-field units), so ``c3`` is the LSB added at full field along that axis."""

    id = "nonlinearity"

    def __init__(self, c3: Sequence[float], k: Sequence[float], bias: Sequence[float]) -> None:
        self.c3, self.k, self.bias = _vec(c3, 3, "c3"), _vec(k, 3, "k"), _vec(bias, 3, "bias")

    def mag_raw(self, t, slot, raw, temp_c):  # type: ignore[no-untyped-def]
        u = (raw - self.bias) / self.k
        return raw + self.c3 * u ** 3

    def params(self) -> dict[str, Any]:
        return {"c3": self.c3.tolist()}


class TemperatureDrift(Effect):
    """The bias follows the temperature: ``raw += bias_per_c * (temp_c - t_ref_c)``."""

    id = "temperature_drift"

    def __init__(self, bias_per_c: Sequence[float], t_ref_c: float = 23.0) -> None:
        self.bias_per_c, self.t_ref_c = _vec(bias_per_c, 3, "bias_per_c"), float(t_ref_c)

    def mag_raw(self, t, slot, raw, temp_c):  # type: ignore[no-untyped-def]
        return raw + self.bias_per_c * (temp_c - self.t_ref_c)

    def params(self) -> dict[str, Any]:
        return {"bias_per_c": self.bias_per_c.tolist()}


class FieldDrift(Effect):
    """The lab field drifts linearly: ``H_L(t) = H_L + rate (t - t0)``, seen in body axes through C_LP."""

    id = "field_drift"

    def __init__(self, rate_per_s: Sequence[float], t0: float = 0.0) -> None:
        self.rate, self.t0 = _vec(rate_per_s, 3, "rate_per_s"), float(t0)

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        return h_b + C_LP.T @ (self.rate * (t - self.t0))

    def params(self) -> dict[str, Any]:
        return {"rate_per_s": self.rate.tolist()}


class TimeLag(Effect):
    """Each sample sees the table as it was ``lag_s`` earlier."""

    id = "time_lag"

    def __init__(self, lag_s: float) -> None:
        self.lag_s = float(lag_s)

    def sample_time(self, t: float, slot: int) -> float:
        return t - self.lag_s

    def params(self) -> dict[str, Any]:
        return {"lag_s": self.lag_s}


class Hysteresis(Effect):
    """``h_b += offset * s`` where ``s_j`` is the sign of the last change of the true ``h_b[j]`` larger than
    :data:`HYSTERESIS_STEP` (0 until the first such change). Stateful, per slot; needs every sample in
    time order."""

    id = "hysteresis"

    def __init__(self, offset: Sequence[float]) -> None:
        self.offset = _vec(offset, 3, "offset")
        self._state: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        anchor, sign = self._state.get(slot, (np.asarray(h_b, float).copy(), np.zeros(3)))
        d = h_b - anchor
        moved = np.abs(d) > HYSTERESIS_STEP
        sign = np.where(moved, np.sign(d), sign)
        anchor = np.where(moved, h_b, anchor)
        self._state[slot] = (anchor, sign)
        return h_b + self.offset * sign

    def params(self) -> dict[str, Any]:
        return {"offset": self.offset.tolist()}


class TableAxisError(Effect):
    """Non-perpendicular axes and encoder zero offsets of the middle and inner axes (a geometry change,
    so the accelerometer sees it too)."""

    id = "table_axis_error"

    def __init__(self, nonperp_deg: Sequence[float], encoder_zero_deg: Sequence[float]) -> None:
        self.nonperp = _vec(nonperp_deg, 2, "nonperp_deg")
        self.zero = _vec(encoder_zero_deg, 2, "encoder_zero_deg")

    def geometry(self, g: TableGeometry) -> TableGeometry:
        z = g.encoder_zero_deg
        return TableGeometry(base_tilt_deg=g.base_tilt_deg,
                             nonperp_deg=(g.nonperp_deg[0] + self.nonperp[0], g.nonperp_deg[1] + self.nonperp[1]),
                             encoder_zero_deg=(z[0], z[1] + self.zero[0], z[2] + self.zero[1]))

    def params(self) -> dict[str, Any]:
        return {"nonperp_deg": self.nonperp.tolist(), "encoder_zero_deg": self.zero.tolist()}


def gradient_matrix(g5: Sequence[float]) -> np.ndarray:
    """Traceless symmetric gradient (3x3) from (Gxx, Gyy, Gxy, Gxz, Gyz)."""
    gxx, gyy, gxy, gxz, gyz = _vec(g5, 5, "gradient")
    return np.array([[gxx, gxy, gxz], [gxy, gyy, gyz], [gxz, gyz, -gxx - gyy]])


class FieldGradient(Effect):
    """The sensor sits at ``offset_m`` (body axes) from the axes' intersection in a field with a uniform
    gradient G (lab frame): ``H_L(p) = H_L + G p`` with ``p = C_LP offset``, so ``h_b += C^T G C offset``."""

    id = "field_gradient"

    def __init__(self, gradient: Sequence[float], offset_m: Sequence[float]) -> None:
        self.G = gradient_matrix(gradient)
        self.g5 = _vec(gradient, 5, "gradient")
        self.offset = _vec(offset_m, 3, "offset_m")

    def body_field(self, t, slot, angles_deg, C_LP, h_b):  # type: ignore[no-untyped-def]
        return h_b + C_LP.T @ self.G @ C_LP @ self.offset

    def params(self) -> dict[str, Any]:
        return {"gradient": self.g5.tolist(), "offset_m": self.offset.tolist()}


class MainsInterference(Effect):
    """Pickup at the mains frequency along a fixed direction of the sensor output:
    ``raw += amplitude * cos(2 pi f t + phase)``; sampling folds it to ``alias_hz``."""

    id = "mains_interference"

    def __init__(self, amplitude_lsb: Sequence[float], freq_hz: float, phase_rad: float = 0.0,
                 sample_rate_hz: float = 20.0) -> None:
        self.amplitude = _vec(amplitude_lsb, 3, "amplitude_lsb")
        self.freq, self.phase, self.rate = float(freq_hz), float(phase_rad), float(sample_rate_hz)

    def mag_raw(self, t, slot, raw, temp_c):  # type: ignore[no-untyped-def]
        return raw + self.amplitude * np.cos(2 * np.pi * self.freq * t + self.phase)

    @property
    def alias_hz(self) -> float:
        """The frequency the samples show (folded into 0 .. rate/2)."""
        f = self.freq % self.rate
        return float(min(f, self.rate - f))

    def params(self) -> dict[str, Any]:
        return {"amplitude_lsb": self.amplitude.tolist(), "alias_hz": self.alias_hz, "freq_hz": self.freq,
                "phase_rad": self.phase}


CONCEAL: dict[str, type[Effect]] = {c.id: c for c in (
    StageHardIron, StageSoftIron, Nonlinearity, TemperatureDrift, FieldDrift, TimeLag, Hysteresis,
    TableAxisError, FieldGradient, MainsInterference)}


def make_effect(effect_id: str, params: dict[str, Any]) -> Effect:
    """Build the concealed form of catalogue effect ``effect_id`` from its keyword parameters."""
    if effect_id not in CONCEAL:
        raise ValueError(f"effect: expected one of {', '.join(CONCEAL)}, got {effect_id!r}")
    try:
        return CONCEAL[effect_id](**params)
    except TypeError as e:
        raise ValueError(f"effect {effect_id}: {e}") from None
