"""The nominal sensor model (PHYSICS.md, "Sensor model") and simulated units.

Magnetometer and accelerometer share one structure: raw counts ``m = M_k M_o v_b + b + n`` where
``v_b`` is the field (lab-field units) or the specific force (g) in body coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike


def split_matrix(M: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Split any 3x3 ``M = diag(k) M_o`` into (M_o with unit rows, k = row norms).

    The split is unique; the sign is fixed elsewhere (a fit chooses the solution whose M_o has a
    positive diagonal, PHYSICS.md).
    """
    M = np.asarray(M, dtype=float)
    k = np.linalg.norm(M, axis=1)
    return M / k[:, None], k


def angles_to_Mo(angles_deg: ArrayLike) -> np.ndarray:
    """M_o from the 3x3 angles between sensor axes (rows) and body axes (columns): cosines, rows normalised."""
    Mo = np.cos(np.radians(np.asarray(angles_deg, dtype=float)))
    return Mo / np.linalg.norm(Mo, axis=1)[:, None]


def Mo_to_angles(M_o: ArrayLike) -> np.ndarray:
    """Angles (deg) between sensor axes (rows) and body axes (columns), the paper's Table 1."""
    return np.degrees(np.arccos(np.clip(np.asarray(M_o, dtype=float), -1.0, 1.0)))


@dataclass(frozen=True)
class LinearSensor:
    """One three-axis sensor: ``raw = diag(k) M_o v + bias + noise`` (optionally quantised to 1 LSB)."""

    M_o: np.ndarray
    k: np.ndarray
    bias: np.ndarray
    noise_lsb: float = 0.0
    quantized: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "M_o", np.asarray(self.M_o, dtype=float).reshape(3, 3))
        object.__setattr__(self, "k", np.asarray(self.k, dtype=float).reshape(3))
        object.__setattr__(self, "bias", np.asarray(self.bias, dtype=float).reshape(3))

    @classmethod
    def from_matrix(cls, M: ArrayLike, bias: ArrayLike, **kw: float | bool) -> "LinearSensor":
        """Build from the combined matrix ``M = diag(k) M_o``."""
        M_o, k = split_matrix(M)
        return cls(M_o=M_o, k=k, bias=np.asarray(bias, dtype=float), **kw)  # type: ignore[arg-type]

    @classmethod
    def ideal(cls, k: float) -> "LinearSensor":
        """A perfect sensor: axes along the body axes, equal sensitivity, no bias, no noise."""
        return cls(M_o=np.eye(3), k=np.full(3, k), bias=np.zeros(3))

    @property
    def M(self) -> np.ndarray:
        """Combined matrix ``diag(k) M_o``."""
        return self.k[:, None] * self.M_o

    @property
    def angles_deg(self) -> np.ndarray:
        """Angles between sensor and body axes, degrees."""
        return Mo_to_angles(self.M_o)

    def expected(self, v_b: ArrayLike) -> np.ndarray:
        """Noise-free, unquantised output (N, 3) for body vectors (N, 3): ``M_k M_o h_b + b``, the sensor model without ``n``."""
        v = np.atleast_2d(np.asarray(v_b, dtype=float))
        return v @ self.M.T + self.bias

    def measure(self, v_b: ArrayLike, rng: np.random.Generator | None = None) -> np.ndarray:
        """Raw output (N, 3) for body vectors (N, 3); noise needs an rng, else the output is noise-free."""
        raw = self.expected(v_b)
        if rng is not None and self.noise_lsb > 0:
            raw = raw + rng.normal(0.0, self.noise_lsb, raw.shape)
        if self.quantized:
            raw = np.round(raw)
        return raw

    def correct(self, raw: ArrayLike) -> np.ndarray:
        """Body vectors from raw output (eq. 11): ``M_o^-1 M_k^-1 (raw - bias)``."""
        r = np.atleast_2d(np.asarray(raw, dtype=float)) - self.bias
        return np.linalg.solve(self.M, r.T).T


@dataclass(frozen=True)
class Unit:
    """A compass unit: its true (or fitted) magnetometer and accelerometer."""

    serial: str
    mag: LinearSensor
    acc: LinearSensor | None
    model: str = "simulated"
    firmware: str = "sim-1.0"
    extra: dict[str, object] = field(default_factory=dict)

    def with_noise(self, mag_noise_lsb: float | None = None, acc_noise_lsb: float | None = None) -> "Unit":
        """A copy with other noise levels (None keeps the current one)."""
        mag = self.mag if mag_noise_lsb is None else replace(self.mag, noise_lsb=mag_noise_lsb)
        acc = self.acc
        if acc is not None and acc_noise_lsb is not None:
            acc = replace(acc, noise_lsb=acc_noise_lsb)
        return replace(self, mag=mag, acc=acc)


#: The paper's Tables 1 and 2 (Gao et al. 2017), as PHYSICS.md gives them.
REFERENCE_ANGLES_DEG = np.array(
    [[1.3020, 88.7122, 90.1977], [92.2085, 2.2337, 89.6656], [89.3381, 92.3069, 2.4001]]
)
REFERENCE_K = np.array([3268.0250, 3163.3724, 3201.5393])
REFERENCE_BIAS = np.array([423.2436, -480.5164, 301.2213])

#: Nominal accelerometer scale (a 16-bit +-2 g part).
ACC_LSB_PER_G = 16384.0


def reference_unit(mag_noise_lsb: float = 0.0, acc_noise_lsb: float = 0.0, serial: str = "GAO2017-REF") -> Unit:
    """The paper's reference unit; its accelerometer is ideal (the paper calibrated it separately)."""
    mag = LinearSensor(angles_to_Mo(REFERENCE_ANGLES_DEG), REFERENCE_K, REFERENCE_BIAS, noise_lsb=mag_noise_lsb)
    acc = replace(LinearSensor.ideal(ACC_LSB_PER_G), noise_lsb=acc_noise_lsb)
    return Unit(serial=serial, mag=mag, acc=acc, model="GAO2017 MI compass")


def _misaligned_axes(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """Rows e_i each tilted by an angle up to ``max_deg`` in a random direction (not orthogonal)."""
    rows = []
    for i in range(3):
        tilt = np.radians(rng.uniform(0.0, max_deg))
        # a random direction perpendicular to e_i
        perp = np.delete(np.arange(3), i)
        az = rng.uniform(0.0, 2 * np.pi)
        u = np.zeros(3)
        u[i] = np.cos(tilt)
        u[perp[0]] = np.sin(tilt) * np.cos(az)
        u[perp[1]] = np.sin(tilt) * np.sin(az)
        rows.append(u)
    return np.array(rows)


def random_unit(
    rng: np.random.Generator,
    serial: str | None = None,
    mag_noise_lsb: float | None = None,
    acc_noise_lsb: float | None = None,
) -> Unit:
    """A production unit with realistic spreads.

    Magnetometer: sensitivity log-uniform 1000-5000 LSB per lab field, axis mismatch up to 5 %,
    each axis misaligned by up to 3 deg, bias up to 1000 LSB per axis, noise 1-5 LSB.
    Accelerometer: 16384 LSB/g within 2 %, misalignment up to 1 deg, bias up to 300 LSB, noise 2-6 LSB.
    """
    k0 = float(np.exp(rng.uniform(np.log(1000.0), np.log(5000.0))))
    mag = LinearSensor(
        M_o=_misaligned_axes(rng, 3.0),
        k=k0 * (1.0 + rng.uniform(-0.05, 0.05, 3)),
        bias=rng.uniform(-1000.0, 1000.0, 3),
        noise_lsb=float(rng.uniform(1.0, 5.0)) if mag_noise_lsb is None else mag_noise_lsb,
        quantized=True,
    )
    acc = LinearSensor(
        M_o=_misaligned_axes(rng, 1.0),
        k=ACC_LSB_PER_G * (1.0 + rng.uniform(-0.02, 0.02, 3)),
        bias=rng.uniform(-300.0, 300.0, 3),
        noise_lsb=float(rng.uniform(2.0, 6.0)) if acc_noise_lsb is None else acc_noise_lsb,
        quantized=True,
    )
    if serial is None:
        serial = f"SIM-{rng.integers(0, 10**6):06d}"
    return Unit(serial=serial, mag=mag, acc=acc)
