"""The simulated station's configuration (TOML): the world, the table, the mounted units, the faults.

Anything the file does not set is ideal (zero imperfection, zero noise), so a config says exactly what
is simulated. Unknown keys are refused, so a typo cannot silently simulate an ideal world.
"""

from __future__ import annotations

import inspect
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AllowInfNan, BaseModel, ConfigDict, Field, Strict, ValidationError, model_validator

from physics.effects import CATALOGUE, CONCEAL, Effect, make_effect
from physics.sensor import ACC_LSB_PER_G, LinearSensor, Unit, angles_to_Mo, random_unit, reference_unit
from physics.simulate import World
from physics.table import TableGeometry

#: A number as TOML writes one (an integer is taken, a string such as "55" refused rather than read), finite.
Num = Annotated[float, Strict(), AllowInfNan(False)]
#: An integer (not a float, a bool or a string).
Int = Annotated[int, Strict()]
#: A count of the compass's wire (a signed 16-bit integer): a larger sensitivity, bias or noise saturates
#: every reading, so no lab could calibrate such a unit (drivers/compass.py refuses counts beyond it).
FULL_SCALE_LSB = 32767.0
#: Fastest simulated station: motion, sample rates and settle times this many times faster than real
#: time; the service takes no more for a station's time_scale (service/schemas.py uses this).
MAX_TIME_SCALE = 1000.0
#: Smallest |det| of a sensor's direction cosines: below it two axes are (nearly) parallel or all three
#: (nearly) in one plane, and the unit could not measure a field along every direction.
MIN_ORIENTATION_DET = 0.1

Vec2 = Annotated[list[Num], Field(min_length=2, max_length=2)]
Vec3 = Annotated[list[Num], Field(min_length=3, max_length=3)]
Mat3 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]
#: Three sensitivities, LSB per lab field (or per g): > 0 and within the wire's full scale.
Sens3 = Annotated[list[Annotated[Num, Field(gt=0, le=FULL_SCALE_LSB)]], Field(min_length=3, max_length=3)]
#: Three biases in LSB, within the wire's full scale.
Bias3 = Annotated[list[Annotated[Num, Field(ge=-FULL_SCALE_LSB, le=FULL_SCALE_LSB)]], Field(min_length=3, max_length=3)]

#: Expected form of each key, quoted in error messages.
FORMS: dict[str, str] = {
    "inclination_deg": "a number of degrees, e.g. 55.0",
    "declination_deg": "a number of degrees, e.g. 23.0",
    "base_tilt_deg": "[about x, about y] in degrees, e.g. [0.05, -0.03]",
    "nonperp_deg": "[z-y pair, y-x pair] departures from 90 deg, degrees",
    "encoder_zero_deg": "[z, y, x] true angle when the encoder reads 0, degrees",
    "time_scale": f"a number > 0 and <= {MAX_TIME_SCALE:g} (20 runs 20 times faster than real time)",
    "temperature_c": "the lab's temperature, deg C, e.g. 23.0",
    "seed": "an integer >= 0, e.g. 1",
    "homed": "true or false",
    "enabled": "true or false",
    "start_deg": "[z, y, x] angles the table starts at, degrees",
    "serial": 'a string, e.g. "SN-0001"',
    "mag_M_o": "a 3x3 direction-cosine matrix, rows = sensor axes, e.g. [[1,0,0],[0,1,0],[0,0,1]]",
    "mag_angles_deg": "a 3x3 matrix of angles between sensor and body axes (the paper's Table 1)",
    "mag_k": f"3 sensitivities > 0 and <= {FULL_SCALE_LSB:g}, LSB per lab field, e.g. [3268.0, 3163.4, 3201.5]",
    "mag_bias": f"3 biases in LSB, -{FULL_SCALE_LSB:g} to {FULL_SCALE_LSB:g}, e.g. [423.2, -480.5, 301.2]",
    "mag_noise_lsb": f"the magnetometer's noise, LSB, 0 to {FULL_SCALE_LSB:g}, e.g. 3.0",
    "acc_M_o": "a 3x3 direction-cosine matrix",
    "acc_angles_deg": "a 3x3 matrix of angles, degrees",
    "acc_k": f"3 sensitivities > 0 and <= {FULL_SCALE_LSB:g}, LSB per g, e.g. [16384.0, 16384.0, 16384.0]",
    "acc_bias": f"3 biases in LSB, -{FULL_SCALE_LSB:g} to {FULL_SCALE_LSB:g}",
    "acc_noise_lsb": f"the accelerometer's noise, LSB, 0 to {FULL_SCALE_LSB:g}, e.g. 4.0",
    "warmup_c": "degrees C the unit warms up by after power-on, e.g. 4.0",
    "warmup_tau_s": "the warm-up's time constant in seconds, > 0, e.g. 300",
    "id": "one of " + ", ".join(CONCEAL),
    "slot": "a slot number of the fixture (0 for the first [[unit]])",
    "kind": "one of " + ", ".join(
        ["axis_alarm", "axis_silent", "stuck_encoder", "estop", "compass_silent", "garbage",
         "fused_line", "truncated_line", "compass_reset", "port_vanish", "bad_readings"]),
    "axis": '"z", "y" or "x"',
    "at_s": "simulated seconds after the start, >= 0, e.g. 30.0",
    "at_angle_deg": "axis_alarm: the axis's angle in degrees at which it alarms, e.g. 100.0",
    "code": "the alarm code, 1 to 0xFFFF, e.g. 0x30",
    "count": "bad_readings: how many consecutive readings are wrong, >= 1",
    "pattern": "bad_readings: \"zeros\" (a brown-out), \"random\" (corrupted values) or \"bitflip\" (one bit of one axis)",
}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class WorldConfig(_Strict):
    """The lab and the table's geometry."""

    inclination_deg: Num = Field(55.0, ge=-90, le=90)
    declination_deg: Num = 23.0
    base_tilt_deg: Vec2 = [0.0, 0.0]
    nonperp_deg: Vec2 = [0.0, 0.0]
    encoder_zero_deg: Vec3 = [0.0, 0.0, 0.0]
    temperature_c: Num = 23.0
    warmup_c: Num = 0.0
    warmup_tau_s: Num = Field(300.0, gt=0)
    time_scale: Num = Field(1.0, gt=0, le=MAX_TIME_SCALE)
    seed: Int | None = Field(None, ge=0)  # numpy's generators take no negative seed

    def world(self) -> World:
        """The physics world this describes."""
        geometry = TableGeometry(tuple(self.base_tilt_deg), tuple(self.nonperp_deg), tuple(self.encoder_zero_deg))  # type: ignore[arg-type]
        return World(self.inclination_deg, self.declination_deg, geometry, self.temperature_c,
                     warmup_c=self.warmup_c, warmup_tau_s=self.warmup_tau_s)


class TableConfig(_Strict):
    """The turntable's controllers."""

    units: dict[Literal["z", "y", "x"], Int] = {"z": 1, "y": 2, "x": 3}
    framer: Literal["tcp", "rtu"] = "tcp"
    homed: Annotated[bool, Strict()] = False  # (lax, 1 and "yes" were taken for true)
    enabled: Annotated[bool, Strict()] = False
    start_deg: Vec3 = [0.0, 0.0, 0.0]
    hard_limits_deg: dict[Literal["z", "y", "x"], Vec2] = {}


def orientation_problem(cosines: np.ndarray) -> str | None:
    """What makes a sensor's 3x3 direction cosines (rows: sensor axes) unusable, or None: a row of zeros
    (an axis at 90 deg to every body axis) or axes that do not span space (|det| of the normalised rows
    below :data:`MIN_ORIENTATION_DET`)."""
    norms = np.linalg.norm(cosines, axis=1)
    if not np.all(norms > 1e-6):
        return f"sensor axis {int(np.argmin(norms))} is at 90 deg to every body axis"
    det = abs(float(np.linalg.det(cosines / norms[:, None])))
    if det < MIN_ORIENTATION_DET:
        return (f"the three sensor axes do not span space (|det| {det:.3g} < {MIN_ORIENTATION_DET:g}: two axes "
                "parallel or all three in one plane)")
    return None


class UnitConfig(_Strict):
    """One compass in the fixture, with its true parameters."""

    serial: str = Field(min_length=1)
    model: str = "XDC-3"
    firmware: str = "1.2.0"
    transport: Literal["pty", "tcp"] = "pty"
    mag_M_o: Mat3 | None = None
    mag_angles_deg: Mat3 | None = None
    mag_k: Sens3  # required: a unit's scale has no ideal value
    mag_bias: Bias3 = [0.0, 0.0, 0.0]
    mag_noise_lsb: Num = Field(0.0, ge=0, le=FULL_SCALE_LSB)
    acc_M_o: Mat3 | None = None
    acc_angles_deg: Mat3 | None = None
    acc_k: Sens3 = [ACC_LSB_PER_G] * 3
    acc_bias: Bias3 = [0.0, 0.0, 0.0]
    acc_noise_lsb: Num = Field(0.0, ge=0, le=FULL_SCALE_LSB)

    @model_validator(mode="after")
    def _one_orientation(self) -> "UnitConfig":
        for s in ("mag", "acc"):
            M_o, angles = getattr(self, f"{s}_M_o"), getattr(self, f"{s}_angles_deg")
            if M_o is not None and angles is not None:
                raise ValueError(f"give {s}_M_o or {s}_angles_deg, not both")
            if M_o is not None and not np.allclose(np.linalg.norm(np.array(M_o), axis=1), 1.0, atol=1e-3):
                raise ValueError(f"{s}_M_o: each row must be a unit vector (direction cosines); "
                                 f"put the scale in {s}_k")
            if angles is not None:
                problem = orientation_problem(np.cos(np.radians(np.array(angles))))
                if problem:
                    raise ValueError(f"{s}_angles_deg: {problem} (expected {FORMS[f'{s}_angles_deg']}, "
                                     "each sensor axis near one body axis, e.g. [[0,90,90],[90,0,90],[90,90,0]])")
            elif M_o is not None:
                problem = orientation_problem(np.array(M_o))
                if problem:
                    raise ValueError(f"{s}_M_o: {problem} (expected {FORMS[f'{s}_M_o']})")
        return self

    def unit(self) -> Unit:
        """The physics unit this describes (raw outputs quantised to 1 LSB, as on the wire)."""
        def orientation(M_o: list[list[float]] | None, angles: list[list[float]] | None) -> np.ndarray:
            if angles is not None:
                return angles_to_Mo(np.array(angles))
            return np.eye(3) if M_o is None else np.array(M_o, dtype=float)
        mag = LinearSensor(orientation(self.mag_M_o, self.mag_angles_deg), np.array(self.mag_k), np.array(self.mag_bias),
                           noise_lsb=self.mag_noise_lsb, quantized=True)
        acc = LinearSensor(orientation(self.acc_M_o, self.acc_angles_deg), np.array(self.acc_k), np.array(self.acc_bias),
                           noise_lsb=self.acc_noise_lsb, quantized=True)
        return Unit(self.serial, mag, acc, model=self.model, firmware=self.firmware)


FaultKind = Literal["axis_alarm", "axis_silent", "stuck_encoder", "estop", "compass_silent", "garbage",
                    "fused_line", "truncated_line", "compass_reset", "port_vanish", "bad_readings"]
AXIS_FAULTS = {"axis_alarm", "axis_silent", "stuck_encoder"}


class FaultConfig(_Strict):
    """A fault to inject through the side channel: now, at a simulated time, or (axis faults) at an angle."""

    kind: FaultKind
    axis: Literal["z", "y", "x"] | None = None
    slot: Int | None = Field(None, ge=0)
    at_s: Num | None = Field(None, ge=0)
    at_angle_deg: Num | None = None
    code: Int = Field(0x20, ge=1, le=0xFFFF)
    nbytes: Int = Field(40, ge=1)
    count: Int = Field(1, ge=1)
    pattern: Literal["zeros", "random", "bitflip"] = "zeros"

    @model_validator(mode="after")
    def _target(self) -> "FaultConfig":
        if self.kind in AXIS_FAULTS and self.axis is None:
            raise ValueError(f"fault {self.kind} needs axis = \"z\", \"y\" or \"x\"")
        if self.kind not in AXIS_FAULTS and self.kind != "estop" and self.slot is None:
            raise ValueError(f"fault {self.kind} needs slot = <the compass's slot number>")
        if self.at_angle_deg is not None and self.kind != "axis_alarm":
            raise ValueError("at_angle_deg applies to axis_alarm only; use at_s")
        if self.at_angle_deg is not None and self.at_s is not None:  # (at_s was silently ignored)
            raise ValueError("give at_angle_deg or at_s, not both (one fault fires once)")
        return self


#: Parameters an effect takes from its unit rather than from the config.
FROM_UNIT: dict[str, tuple[str, ...]] = {"nonlinearity": ("k", "bias")}
#: Effects of the table itself (shared by every slot), which a ``slot`` cannot select.
TABLE_EFFECTS = ("table_axis_error",)


def _effect_keys(effect_id: str) -> tuple[list[str], list[str]]:
    """(required, optional) config keys of a catalogue effect: its constructor's parameters."""
    params = inspect.signature(CONCEAL[effect_id].__init__).parameters
    names = [(n, p) for n, p in params.items() if n != "self" and n not in FROM_UNIT.get(effect_id, ())]
    return ([n for n, p in names if p.default is inspect.Parameter.empty],
            [n for n, p in names if p.default is not inspect.Parameter.empty])


def _effect_form(effect_id: str, key: str) -> str:
    form = CATALOGUE[effect_id].params.get(key) if effect_id in CATALOGUE else None
    return form or {"t_ref_c": "deg C at which the bias is nominal, e.g. 23.0",
                    "t0": "simulated seconds at which the drift starts, e.g. 0",
                    "freq_hz": "the mains frequency in Hz, e.g. 50.0",
                    "sample_rate_hz": "the compass's sample rate in Hz, e.g. 20"}.get(key, "see physics/effects.py")


class EffectConfig(BaseModel):
    """Extra physics concealed in the station (``[[effect]]``): ``id`` from the catalogue of
    physics/effects.py, ``slot`` (default: every unit) and the effect's parameters as keys, e.g.
    ``id = "stage_hard_iron"``, ``stage = "outer"``, ``m = [0.01, 0, 0]``. ``nonlinearity`` takes its
    unit's k and bias from the ``[[unit]]`` itself."""

    model_config = ConfigDict(extra="allow")

    id: str
    slot: int | None = Field(None, ge=0)

    @property
    def params(self) -> dict[str, Any]:
        """The effect's parameters (every key but id and slot)."""
        return dict(self.model_extra or {})

    @model_validator(mode="after")
    def _buildable(self) -> "EffectConfig":
        if self.id not in CONCEAL:
            raise ValueError(f"id: unknown effect {self.id!r} (expected {FORMS['id']})")
        if self.slot is not None and self.id in TABLE_EFFECTS:
            raise ValueError(f"{self.id} is the table's own and acts on every slot: remove slot")
        required, optional = _effect_keys(self.id)
        unknown = [k for k in self.params if k not in required + optional]
        missing = [k for k in required if k not in self.params]
        problems = [f"{k}: taken from the [[unit]] (its mag_{k}), not given here" if k in FROM_UNIT.get(self.id, ())
                    else f"{k}: unknown key for {self.id} (its keys: {', '.join(required + optional)})" for k in unknown]
        problems += [f"{k}: missing (expected {_effect_form(self.id, k)})" for k in missing]
        if not problems:
            try:
                self.build(np.ones(3), np.zeros(3))
            except (ValueError, TypeError) as e:
                text = str(e).removeprefix(f"effect {self.id}: ")
                key = text.split(":", 1)[0].strip()
                if key in required + optional:
                    problems.append(f"{text} (expected {_effect_form(self.id, key)})")
                else:  # the message does not say which key: give every key's form
                    problems.append(f"{text} (expected " + "; ".join(
                        f"{k}: {_effect_form(self.id, k)}" for k in required + optional) + ")")
        if problems:
            raise ValueError(f"{self.id}: " + "; ".join(problems))
        return self

    def build(self, k: np.ndarray, bias: np.ndarray) -> Effect:
        """The effect, for a unit of sensitivities ``k`` and biases ``bias`` (LSB)."""
        extra = {"k": list(k), "bias": list(bias)} if self.id in FROM_UNIT else {}
        return make_effect(self.id, {**self.params, **extra})


class StationConfig(_Strict):
    """A whole simulated station."""

    world: WorldConfig = WorldConfig()
    table: TableConfig = TableConfig()
    unit: list[UnitConfig] = Field(default_factory=list)
    fault: list[FaultConfig] = Field(default_factory=list)
    effect: list[EffectConfig] = Field(default_factory=list)

    @model_validator(mode="after")
    def _slots(self) -> "StationConfig":
        serials = [u.serial for u in self.unit]
        dup = {s for s in serials if serials.count(s) > 1}
        if dup:
            raise ValueError(f"duplicate unit serial(s): {', '.join(sorted(dup))}")
        for f in self.fault:
            if f.slot is not None and f.slot >= max(1, len(self.unit)):
                raise ValueError(f"fault {f.kind}: slot {f.slot} does not exist (the fixture has {len(self.unit)} unit(s))")
        for i, e in enumerate(self.effect):
            if e.slot is not None and e.slot >= max(1, len(self.unit)):
                raise ValueError(f"effect[{i}].slot: {e.id}: slot {e.slot} does not exist "
                                 f"(the fixture has {len(self.unit)} unit(s))")
        return self

    def effects(self) -> list[tuple[int | None, Effect]]:
        """The concealed effects as (slot or None for every slot, Effect), built fresh (some keep state).
        An effect that needs its unit's parameters is built once per slot it acts on."""
        out: list[tuple[int | None, Effect]] = []
        for e in self.effect:
            if e.id in FROM_UNIT:
                slots = [e.slot] if e.slot is not None else list(range(len(self.unit)))
                for slot in slots:
                    u = self.unit[slot]
                    out.append((slot, e.build(np.array(u.mag_k), np.array(u.mag_bias))))
            else:
                out.append((e.slot, e.build(np.ones(3), np.zeros(3))))
        return out


class ConfigError(ValueError):
    """A station config that cannot be simulated; the message names the key and the expected form."""


def default_config(seed: int | None = None, time_scale: float = 1.0) -> StationConfig:
    """No config file: one random production unit (its own noise) on an ideal table and base."""
    rng = np.random.default_rng(seed)
    u = random_unit(rng)
    unit = UnitConfig(serial=u.serial, mag_M_o=u.mag.M_o.tolist(), mag_k=u.mag.k.tolist(), mag_bias=u.mag.bias.tolist(),
                      mag_noise_lsb=u.mag.noise_lsb, acc_M_o=u.acc.M_o.tolist() if u.acc else None,
                      acc_k=u.acc.k.tolist() if u.acc else [ACC_LSB_PER_G] * 3,
                      acc_bias=u.acc.bias.tolist() if u.acc else [0.0] * 3,
                      acc_noise_lsb=u.acc.noise_lsb if u.acc else 0.0)
    return StationConfig(world=WorldConfig(time_scale=time_scale, seed=seed), unit=[unit])


def reference_config(seed: int | None = 1, time_scale: float = 1.0) -> StationConfig:
    """The paper's reference unit (3 LSB magnetometer noise, 4 LSB accelerometer noise) on a table whose
    base is tilted by 0.05 and -0.03 deg: the demonstration station."""
    u = reference_unit(3.0, 4.0)
    unit = UnitConfig(serial=u.serial, mag_M_o=u.mag.M_o.tolist(), mag_k=u.mag.k.tolist(), mag_bias=u.mag.bias.tolist(),
                      mag_noise_lsb=3.0, acc_noise_lsb=4.0)
    return StationConfig(world=WorldConfig(base_tilt_deg=[0.05, -0.03], time_scale=time_scale, seed=seed), unit=[unit])


def parse_config(data: dict[str, object], source: str = "config") -> StationConfig:
    """Validate a config mapping; errors name every bad key and its expected form."""
    try:
        cfg = StationConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(f"{source}: " + "; ".join(_describe(err) for err in e.errors())) from None
    if not cfg.unit:
        raise ConfigError(f"{source}: no [[unit]] table: a station needs at least one unit "
                          "([[unit]] with serial and mag_k at least)")
    return cfg


def parse_fault(data: object) -> FaultConfig:
    """Validate one fault (the keys of a ``[[fault]]`` table), e.g. from the control port."""
    try:
        return FaultConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError("fault: " + "; ".join(_describe(err) for err in e.errors())) from None


def load_config(path: Path) -> StationConfig:
    """Read and validate a station TOML file."""
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    return parse_config(data, str(path))


def _describe(err: dict[str, object]) -> str:
    """One pydantic error as `unit[0].mag_k: <problem> (expected <form>)`."""
    loc = err.get("loc", ())
    parts: list[str] = []
    for p in loc:  # type: ignore[union-attr]
        if isinstance(p, int):
            parts[-1:] = [f"{parts[-1]}[{p}]"] if parts else [f"[{p}]"]
        elif p in ("list[float]", "none", "function-after[_one_orientation(), UnitConfig]"):
            continue
        else:
            parts.append(str(p))
    key = next((p for p in reversed(parts) if p.split("[")[0] in FORMS), None)
    name = ".".join(parts) or "(top level)"
    msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
    if err.get("type") == "extra_forbidden":
        msg = "unknown key (check its spelling)"
    elif err.get("type") == "missing":
        msg = "missing"
    elif str(err.get("type", "")).endswith("_type"):  # the wrong kind of value: say what was given
        given = err.get("input")
        msg = f"{msg}, got {type(given).__name__} {given!r}"
    form = f" (expected {FORMS[key.split('[')[0]]})" if key else ""
    return f"{name}: {msg}{form}"
