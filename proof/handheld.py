"""Hand-held recordings for the blind proof without table angles (issue 12): a random unit carried along
a smooth random path over the sphere, effects concealed through their forward implementations
(physics.effects, proof.concealments), then noise and quantisation; the out-of-catalogue cases drawn
on them (:func:`make_handheld_case`) and the proof's list of cases (:func:`handheld_jobs`).

Written independently of the analyser: it never imports physics.discrepancy. A case's size is the
magnitude's non-centrality before any nominal fit, ``lambda = sum over the window's samples of
(kbar * (field-magnitude change, in field units))^2 / sigma^2`` with kbar the unit's mean sensitivity
(LSB per field): the part of the departure the field's magnitude can show at all, an upper bound of what
a test that also fits the nominal ellipsoid can see. For the axes turning (misalignment_drift), which
hardly change the magnitude, the dip's change (rad, the angle between the field and the vertical) adds
its square to the magnitude's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physics import effects
from physics.frames import field_direction, rot_x, rot_y, rot_z
from physics.recording import Recording
from physics.sensor import random_unit
from proof.concealments import (GainVsTemp, IntermittentInterference, LabSegmentOffset, MisalignmentDrift,
                                SensorSegmentOffset)

RATE_HZ = 22.0  # 50 Hz mains folds to 6 Hz
#: Out-of-catalogue kinds a recording without angles can show (a stage's frame needs the table's angles; the
#: sensor's axes turning slowly show on the dip against the accelerometer, hardly on the field's magnitude).
HANDHELD_KINDS = ("segment_offset_sensor", "segment_offset_lab", "intermittent_interference", "gain_vs_temp",
                  "misalignment_drift")


def _attitude(t: np.ndarray, par: np.ndarray) -> np.ndarray:
    """A smooth hand-held path: yaw turning on, pitch within +-80 deg, roll over the full circle."""
    yaw = par[0] * t + 60 * np.sin(2 * np.pi * t / par[1] + par[2])
    pitch = 80 * np.sin(2 * np.pi * t / par[3] + par[4])
    roll = 180 * np.sin(2 * np.pi * t / par[5] + par[6]) + 40 * np.sin(2 * np.pi * t / 7.3)
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def _draw(seed: int) -> tuple[np.random.Generator, Any, np.ndarray, np.ndarray]:
    """The seed's draws: its generator (for the noise that follows), the unit, the path's parameters, the field."""
    rng = np.random.default_rng(seed)
    unit = random_unit(rng)
    par = np.array([rng.uniform(8, 15) * rng.choice([-1, 1]), rng.uniform(20, 40), rng.uniform(0, 6.3),
                    rng.uniform(25, 45), rng.uniform(0, 6.3), rng.uniform(30, 60), rng.uniform(0, 6.3)])
    return rng, unit, par, field_direction(rng.uniform(40, 70), rng.uniform(0, 360))


def simulate_handheld(seed: int, n: int = 2400, conceal: list[effects.Effect] | None = None,
                      temp_c: np.ndarray | None = None, with_gyro: bool = True,
                      field: np.ndarray | None = None) -> tuple[Recording, object]:
    """A hand-held recording of a random unit (angles empty), effects concealed sample by sample.

    ``field``: the lab field direction (default: dip 40-70 deg, any azimuth, from the seed).
    """
    rng, unit, par, H = _draw(seed)
    t = np.arange(n) / RATE_HZ
    H = H if field is None else np.asarray(field, float)
    conceal = conceal or []
    temps = np.full(n, 23.0) if temp_c is None else temp_c
    mag = np.empty((n, 3))
    for i in range(n):
        ts = t[i]
        for e in conceal:
            ts = e.sample_time(ts, 0)
        C = _attitude(np.array([ts]), par)[0]
        h = C.T @ H
        for e in conceal:
            h = e.body_field(t[i], 0, np.zeros(3), C, h)
        raw = unit.mag.M @ h + unit.mag.bias
        for e in conceal:
            raw = e.mag_raw(t[i], 0, raw, temps[i])
        mag[i] = raw
    mag = np.round(mag + rng.normal(0, unit.mag.noise_lsb, mag.shape))
    C = _attitude(t, par)
    f_b = np.einsum("nji,j->ni", C, [0.0, 0.0, -1.0])
    acc = unit.acc.measure(f_b, rng)
    extra = None
    if with_gyro:  # body rates from C^T dC/dt
        eps = 1e-4
        dC = (_attitude(t + eps, par) - _attitude(t - eps, par)) / (2 * eps)
        W = np.einsum("nji,njk->nik", C, dC)
        w = np.degrees(np.column_stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]]))
        w = w + rng.normal(0, 0.05, w.shape)
        extra = {k: [f"{x:.4f}" for x in w[:, j]] for j, k in enumerate(("gx", "gy", "gz"))}
    nan = np.full(n, np.nan)
    rec = Recording.from_arrays(t=t, step=["handheld"] * n, psi_t=nan, theta_t=nan, phi_t=nan, mag=mag, acc=acc,
                                temp_c=temp_c, meta={"gyro_unit": "deg/s"}, extra=extra)
    return rec, unit


def _windows(rng: np.random.Generator, span: float, k: int) -> list[list[float]]:
    """``k`` disjoint windows inside (5 %, 95 %) of the run, each at least 15 % of it, gaps of 10 % at least."""
    while True:
        lengths = rng.uniform(0.15, 0.35, k) * span
        gaps = rng.uniform(0.1, 0.3, k + 1) * span
        total = lengths.sum() + gaps[1:k].sum()
        if total < 0.9 * span:
            break
    start = rng.uniform(0.05 * span, 0.95 * span - total)
    out = []
    for i in range(k):
        out.append([float(start), float(start + lengths[i])])
        start += lengths[i] + gaps[i + 1]
    return out


def make_handheld_case(seed: int, kind: str | None, lam: float, n: int = 2400) -> tuple[Recording, dict[str, Any]]:
    """One hand-held recording with an out-of-catalogue ``kind`` concealed at non-centrality ``lam`` (module
    docstring), or none (``kind`` None: a null); and its truth (frame, form, input or windows, lambda). Every
    recording logs a warm-up (``temp_c``) of 0-4 deg C, 2-5 for a gain following it, as the table proof's do."""
    rng = np.random.default_rng([seed, 77])
    t = np.arange(n) / RATE_HZ
    warm = rng.uniform(2.0, 5.0) if kind == "gain_vs_temp" else rng.uniform(0.0, 4.0)  # as the table proof's
    temp = 23.0 + warm * (1.0 - np.exp(-t / rng.uniform(20.0, 60.0)))
    H = field_direction(rng.uniform(40, 70), rng.uniform(0, 360))
    if kind is None:
        rec, _ = simulate_handheld(seed, n=n, temp_c=temp, field=H)
        return rec, {"kind": None, "lambda": 0.0}
    unit = random_unit(np.random.default_rng(seed))  # simulate_handheld draws the same unit from the seed
    segs = _windows(rng, n / RATE_HZ, 2 if kind == "intermittent_interference" else 1)
    inside = np.zeros(n, bool)
    for a, b in segs:
        inside |= (t >= a) & (t < b)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    kbar = float(np.mean(np.linalg.norm(unit.mag.M, axis=1)))
    # the field-magnitude change (field units) per unit of size, on the same path as the recording
    if kind == "segment_offset_lab":  # along the lab field, whatever the attitude
        change = np.full(int(inside.sum()), float(H @ u))
    elif kind == "misalignment_drift":  # the axes turning by u rad per s about mid-run: field and dip change
        _, _, par, _ = _draw(seed)
        C = _attitude(t, par)
        h = np.einsum("nji,j->ni", C, H)  # the field in body axes (unit length)
        g = np.einsum("nji,j->ni", C, [0.0, 0.0, 1.0])  # the vertical in body axes
        ref = float(t.mean())
        lin = h @ unit.mag.M.T
        dh = np.linalg.solve(unit.mag.M, np.cross(u[None, :] * (t - ref)[:, None], lin).T).T
        cos_i = np.einsum("nj,nj->n", h, g)
        along = np.einsum("nj,nj->n", h, dh)
        turn = -np.einsum("nj,nj->n", dh, g - cos_i[:, None] * h) / np.sqrt(np.maximum(1.0 - cos_i ** 2, 1e-12))
        change = np.sqrt(along ** 2 + turn ** 2)  # the magnitude's change and the dip's (field units, rad)
    else:  # counts in the sensor frame, seen along the calibrated field's direction
        rec0, _ = simulate_handheld(seed, n=n, temp_c=temp, field=H)
        lin = rec0.mag - unit.mag.bias
        h = np.linalg.solve(unit.mag.M, lin.T).T
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        if kind == "gain_vs_temp":  # a gain of u per deg C about the run's mean temperature
            ref = float(np.mean(temp))
            change = np.einsum("nj,nj->n", h, np.linalg.solve(unit.mag.M, (u * lin * (temp - ref)[:, None]).T).T)
        else:
            change = h[inside] @ np.linalg.solve(unit.mag.M, u)
    size = float(np.sqrt(lam / max(np.sum((kbar * change) ** 2) / unit.mag.noise_lsb ** 2, 1e-300)))
    if kind == "gain_vs_temp":
        eff = GainVsTemp(gain_per_c=size * u, bias=unit.mag.bias, t_ref_c=ref)
        truth = {"gain_per_c": (size * u).tolist()}
    elif kind == "misalignment_drift":
        eff = MisalignmentDrift(rate_rad_per_s=size * u, bias=unit.mag.bias, t_mid=ref)
        truth = {"rate_rad_per_s": (size * u).tolist()}
    else:
        cls = {"segment_offset_sensor": SensorSegmentOffset, "segment_offset_lab": LabSegmentOffset,
               "intermittent_interference": IntermittentInterference}[kind]
        eff = cls(size * u, segs)
        truth = {"offset": (size * u).tolist()}
    rec, _ = simulate_handheld(seed, n=n, conceal=[eff], temp_c=temp, field=H)
    return rec, {"kind": kind, "lambda": lam, **eff.model(), **truth}


def handheld_jobs(n: int, nulls: int, seed: int) -> list[tuple[int, str | None, float]]:
    """The hand-held proof's cases as (case seed, kind, lambda): ``n`` per kind of :data:`HANDHELD_KINDS` at
    non-centralities log-uniform over 3-300, then ``nulls`` without a departure (kind None, lambda 0)."""
    rng = np.random.default_rng(seed)
    jobs: list[tuple[int, str | None, float]] = [
        (int(rng.integers(1 << 30)), kind, float(np.exp(rng.uniform(np.log(3), np.log(300)))))
        for kind in HANDHELD_KINDS for _ in range(n)]
    jobs += [(int(rng.integers(1 << 30)), None, 0.0) for _ in range(nulls)]
    return jobs
