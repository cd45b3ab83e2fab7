"""A unit's calibration, whatever method produced it, and how it is applied and scored.

Every method returns a :class:`Calibration`: a linear magnetometer model (M_o, k, bias), optionally
an accelerometer model, the field it found, and, for the two methods that are not purely linear, a
``heading_model`` (the five-coefficient deviation curve, or the two-axis compass's dip). The same
heading computation and the same evaluations then score every method alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from physics.frames import SPECIFIC_FORCE_L, to_body
from physics.heading import error_summary, heading_error, magnetic_heading, pitch_roll, reference_heading, wrap180
from physics.sensor import LinearSensor, Unit
from physics.simulate import World
from physics.table import platform_attitude

FORMAT = "compasscal-calibration/1"

#: Stages of the paper's Fig. 5, in order: what is corrected at each stage.
STAGES = ("raw", "bias", "sensitivity", "full")


@dataclass
class Calibration:
    """The result of any calibration method (see module docstring)."""

    method: str
    mag: LinearSensor
    acc: LinearSensor | None = None
    inclination_deg: float = float("nan")
    declination_deg: float = float("nan")
    base_tilt_deg: tuple[float, float] = (0.0, 0.0)
    serial: str | None = None
    sigma: dict[str, Any] = field(default_factory=dict)
    quality: dict[str, Any] = field(default_factory=dict)
    heading_model: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)

    # --- applying it -------------------------------------------------------------------------
    def specific_force(self, acc_raw: np.ndarray) -> np.ndarray:
        """Calibrated specific force f_b (g) from raw accelerometer counts."""
        if self.acc is None:
            raise ValueError("this calibration has no accelerometer model")
        return self.acc.correct(acc_raw)

    def body_field(self, mag_raw: np.ndarray, f_b: np.ndarray, stage: str = "full") -> np.ndarray:
        """Field in body axes from raw magnetometer counts, corrected up to ``stage`` (Fig. 5)."""
        raw = np.atleast_2d(np.asarray(mag_raw, dtype=float))
        if stage == "raw":
            return raw
        h = raw - self.mag.bias
        if stage == "bias":
            return h
        h = h / self.mag.k
        if stage == "sensitivity":
            return h
        if stage != "full":
            raise ValueError(f"stage: expected one of {STAGES}, got {stage!r}")
        h = np.linalg.solve(self.mag.M_o, h.T).T
        if self.heading_model and self.heading_model["kind"] == "two_axis":
            h = _two_axis_vertical(h, f_b, self.heading_model["extended_dip_deg"])
        return h

    def heading(self, mag_raw: np.ndarray, f_b: np.ndarray, stage: str = "full") -> np.ndarray:
        """Magnetic heading (deg) the calibrated compass reports; f_b is the specific force it uses."""
        psi = magnetic_heading(self.body_field(mag_raw, f_b, stage), f_b)
        if stage == "full" and self.heading_model and self.heading_model["kind"] == "deviation5":
            psi = (psi - deviation5_curve(psi, self.heading_model["coefficients_deg"])) % 360.0
        return psi

    # --- JSON --------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The calibration JSON of the physics issue (required keys first; extra keys allowed)."""
        def sensor(s: LinearSensor | None) -> dict[str, Any] | None:
            if s is None:
                return None
            return {"M_o": s.M_o.tolist(), "k": s.k.tolist(), "bias": s.bias.tolist(), "angles_deg": s.angles_deg.tolist()}

        mag = sensor(self.mag)
        assert mag is not None
        mag["sigma"] = {key: _tolist(self.sigma.get(key)) for key in ("angles_deg", "k", "bias")}
        acc = sensor(self.acc)
        if acc is not None and "acc" in self.sigma:
            acc["sigma"] = {key: _tolist(v) for key, v in self.sigma["acc"].items()}
        return {
            "format": FORMAT,
            "serial": self.serial,
            "method": self.method,
            "magnetometer": mag,
            "accelerometer": acc,
            "field": {
                "inclination_deg": _num(self.inclination_deg),
                "declination_deg": _num(self.declination_deg),
                "sigma": {k: _num(self.sigma.get(k)) for k in ("inclination_deg", "declination_deg")},
            },
            "base_tilt_deg": [float(x) for x in self.base_tilt_deg],
            "base_tilt_sigma_deg": _tolist(self.sigma.get("base_tilt_deg")),
            "quality": self.quality,
            "heading_model": self.heading_model,
            "notes": self.notes,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Calibration":
        """Read the calibration JSON back; errors name the missing or malformed key."""
        if d.get("format") != FORMAT:
            raise ValueError(f"format: expected {FORMAT!r}, got {d.get('format')!r}")

        def sensor(key: str, s: dict[str, Any] | None) -> LinearSensor | None:
            if s is None:
                return None
            try:
                return LinearSensor(*(_numbers(f"{key}.{name}", s[name], shape)
                                      for name, shape in (("M_o", (3, 3)), ("k", (3,)), ("bias", (3,)))))
            except (KeyError, TypeError, ValueError) as e:
                raise ValueError(f"{key}: needs M_o (3x3), k (3) and bias (3): {e}") from None

        mag = sensor("magnetometer", d.get("magnetometer"))
        if mag is None:
            raise ValueError("magnetometer: missing")
        sig = dict(d["magnetometer"].get("sigma") or {})
        fld = d.get("field") or {}
        sig.update({k: v for k, v in (fld.get("sigma") or {}).items() if v is not None})
        return cls(
            method=d.get("method", "unknown"),
            serial=d.get("serial"),
            mag=mag,
            acc=sensor("accelerometer", d.get("accelerometer")),
            inclination_deg=_float_or_nan(fld.get("inclination_deg")),
            declination_deg=_float_or_nan(fld.get("declination_deg")),
            base_tilt_deg=tuple(d.get("base_tilt_deg") or (0.0, 0.0)),  # type: ignore[arg-type]
            sigma=sig,
            quality=d.get("quality") or {},
            heading_model=d.get("heading_model"),
            notes=list(d.get("notes") or []),
        )


def _numbers(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite float array of ``shape``; true/false, text and null are refused by their place
    (numpy read ``true`` as a sensitivity of 1 and ``"1108"`` as 1108)."""
    def walk(x: Any, at: str) -> None:
        if isinstance(x, (list, tuple)):
            for i, e in enumerate(x):
                walk(e, f"{at}[{i}]")
        elif isinstance(x, (bool, str)) or x is None:
            raise ValueError(f"{at}: a number is required, got {x!r}")

    walk(value, name)
    a = np.array(value, dtype=float)
    if a.shape != shape:
        raise ValueError(f"{name}: expected {'x'.join(map(str, shape))} numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite numbers, got {value!r}")
    return a


def deviation5_curve(psi_deg: np.ndarray, coef_deg: list[float]) -> np.ndarray:
    """Deviation ``A + B sin psi + C cos psi + D sin 2psi + E cos 2psi`` (deg), seed 004's eq. 4."""
    p = np.radians(np.asarray(psi_deg, dtype=float))
    A, B, C, D, E = coef_deg
    return A + B * np.sin(p) + C * np.cos(p) + D * np.sin(2 * p) + E * np.cos(2 * p)


def _two_axis_vertical(h: np.ndarray, f_b: np.ndarray, dip_deg: float) -> np.ndarray:
    """Seed 003's Theorem 1: replace h_z by the value that puts the levelled field at the dip angle."""
    pitch, roll = (np.radians(a) for a in pitch_roll(f_b))
    st, ct, sp, cp = np.sin(pitch), np.cos(pitch), np.sin(roll), np.cos(roll)
    out = np.array(h, dtype=float)
    # levelled z = -sin(theta) h_x + cos(theta) sin(phi) h_y + cos(theta) cos(phi) h_z = sin(dip)
    out[:, 2] = (np.sin(np.radians(dip_deg)) + st * out[:, 0] - ct * sp * out[:, 1]) / (ct * cp)
    return out


# --- scoring against the truth of a simulated world -----------------------------------------------

def attitude_grid(max_tilt_deg: float = 60.0, tilt_step_deg: float = 30.0, heading_step_deg: float = 15.0) -> np.ndarray:
    """Encoder angles (N, 3) of the paper's Fig. 6 check: every heading at pitch and roll up to the limit."""
    tilts = np.arange(-max_tilt_deg, max_tilt_deg + 1e-9, tilt_step_deg)
    psi = np.arange(0.0, 360.0, heading_step_deg)
    P, T, R = np.meshgrid(psi, tilts, tilts, indexing="ij")
    return np.column_stack([P.ravel(), T.ravel(), R.ravel()])


def level_turn(step_deg: float = 1.0) -> np.ndarray:
    """Encoder angles (N, 3) of a level full turn about z."""
    psi = np.arange(0.0, 360.0, step_deg)
    return np.column_stack([psi, np.zeros_like(psi), np.zeros_like(psi)])


def truth_errors(cal: Calibration, unit: Unit, world: World, angles: np.ndarray, stage: str = "full",
                 true_tilt: bool = False) -> np.ndarray:
    """Heading errors (deg) of ``cal`` applied to noise-free readings of the true ``unit``.

    The reference is the body's true magnetic heading in ``world``. The compass levels itself with
    its own calibrated accelerometer when the calibration has one (as it would in use), else with
    the true specific force; ``true_tilt`` forces the latter, to isolate the magnetometer.
    """
    C = platform_attitude(angles[:, 0], angles[:, 1], angles[:, 2], world.geometry)
    h_b, f_true = to_body(C, world.field_L), to_body(C, SPECIFIC_FORCE_L)
    # the expected readings, not rounded: rounding one noise-free reading is an error of up to half a
    # count per axis (0.08 deg on a weak unit's horizontal field) that no calibration can remove, while
    # in noise (several counts) the rounding averages out like the rest of the noise
    mag = replace(unit.mag, quantized=False).measure(h_b)
    if cal.acc is not None and unit.acc is not None and not true_tilt:
        f_b = cal.specific_force(replace(unit.acc, quantized=False).measure(f_true))
    else:
        f_b = f_true
    return heading_error(cal.heading(mag, f_b, stage), reference_heading(C, world.declination_deg))


def truth_summary(cal: Calibration, unit: Unit, world: World) -> dict[str, float]:
    """Max and RMS heading error level (1 deg steps) and over the +-60 deg attitude grid."""
    level = error_summary(truth_errors(cal, unit, world, level_turn()))
    tilted = error_summary(truth_errors(cal, unit, world, attitude_grid()))
    return {"level_max": level["max"], "level_rms": level["rms"], "tilted_max": tilted["max"], "tilted_rms": tilted["rms"]}


def staged_truth_errors(cal: Calibration, unit: Unit, world: World) -> dict[str, float]:
    """Max heading error over a level turn at each stage of Fig. 5, with the true tilt."""
    turn = level_turn(0.25)
    return {s: float(np.max(np.abs(truth_errors(cal, unit, world, turn, stage=s, true_tilt=True)))) for s in STAGES}


def json_safe(x: Any) -> Any:
    """A JSON-safe copy: numpy scalars and arrays to Python, NaN and infinities to None (PostgreSQL's
    json refuses NaN), anything else that JSON cannot hold to its text; recursively."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if x is None or isinstance(x, str):
        return x
    return str(x)


def _tolist(v: Any) -> Any:
    if v is None:
        return None
    return np.asarray(v, dtype=float).tolist()


def _num(v: Any) -> float | None:
    if v is None:
        return None
    v = float(v)
    return None if not np.isfinite(v) else v


def _float_or_nan(v: Any) -> float:
    return float("nan") if v is None else float(v)


__all__ = [
    "Calibration", "FORMAT", "STAGES", "attitude_grid", "deviation5_curve", "json_safe", "level_turn",
    "staged_truth_errors", "truth_errors", "truth_summary", "wrap180",
]
