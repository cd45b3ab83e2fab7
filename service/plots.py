"""Figures people would rather look at than read (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display on a station PC or in CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from physics import errorsep as es  # noqa: E402
from physics.calibration import STAGES, Calibration  # noqa: E402
from physics.frames import field_direction  # noqa: E402
from physics.heading import heading_error  # noqa: E402
from physics.recording import Recording  # noqa: E402
from physics.table import base_rotation  # noqa: E402

STAGE_LABELS = {"raw": "raw", "bias": "bias removed", "sensitivity": "+ sensitivity", "full": "+ non-orthogonality"}


def calibration_figure(rec: Recording, cal: Calibration, path: Path) -> None:
    """Staged heading error against heading on the level turn (Fig. 5) and residuals per sample by step."""
    f_b = es.specific_force(rec, cal.acc)
    level = (np.abs(rec.theta_t) < 0.01) & (np.abs(rec.phi_t) < 0.01)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    ref = rec.psi_t - cal.declination_deg
    order = np.argsort(rec.psi_t[level])
    for stage in STAGES:
        e = heading_error(cal.heading(rec.mag[level], f_b[level], stage), ref[level])
        axes[0].plot(rec.psi_t[level][order], e[order], ".-", label=STAGE_LABELS[stage], ms=3)
    axes[0].set(title="Heading error by stage (level turn)", xlabel="table azimuth psi_t (deg)", ylabel="error (deg)")
    axes[0].legend()
    e_full = heading_error(cal.heading(rec.mag[level], f_b[level]), ref[level])
    axes[1].plot(rec.psi_t[level][order], e_full[order], ".", ms=3)
    axes[1].set(title=f"Calibrated heading error ({cal.method})", xlabel="psi_t (deg)", ylabel="error (deg)")
    v = base_rotation(cal.base_tilt_deg).T @ field_direction(cal.inclination_deg, cal.declination_deg)
    resid = rec.mag - cal.mag.measure(np.einsum("nji,j->ni", es.rotations(rec), v))
    for i, name in enumerate(("m_x", "m_y", "m_z")):
        axes[2].plot(resid[:, i], ".", ms=2, label=name)
    steps = rec.step
    edges = np.flatnonzero(steps[1:] != steps[:-1]) + 1
    for e in edges:
        axes[2].axvline(e, color="0.8", lw=0.8)
    for s, start in zip(steps[np.r_[0, edges]], np.r_[0, edges]):
        axes[2].text(start, 1.0, str(s), transform=axes[2].get_xaxis_transform(), fontsize=7, va="bottom")
    axes[2].set(title="Model residuals by sample", xlabel="sample", ylabel="raw - model (LSB)")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
