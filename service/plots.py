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
    """Staged heading error against heading on the level turn (Fig. 5) and residuals per sample by step;
    for a recording without table angles, what the magnetometer alone shows (:func:`_angle_free_figure`)."""
    if not rec.has_angles:
        _angle_free_figure(rec, cal, path)
        return
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


def _angle_free_figure(rec: Recording, cal: Calibration, path: Path) -> None:
    """A hand-held recording's calibration (no table angles, so no heading error to draw): the calibrated
    field's magnitude at each sample, which a good calibration holds at 1, and the readings' horizontal
    components raw and calibrated (an off-centre ellipse made a centred circle)."""
    h = cal.mag.correct(np.asarray(rec.mag, dtype=float))
    mag = np.linalg.norm(h, axis=1)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    axes[0].plot(mag, ".", ms=2)
    axes[0].axhline(1.0, color="0.5", lw=0.8)
    axes[0].set(title=f"Calibrated field magnitude ({cal.method}; rms spread {100 * np.std(mag) / np.mean(mag):.2f} %)",
                xlabel="sample", ylabel="|h| (field units)")
    raw = (rec.mag - cal.mag.bias) / np.mean(cal.mag.k)
    axes[1].plot(raw[:, 0], raw[:, 1], ".", ms=2, label="raw (bias off, one scale)")
    axes[1].plot(h[:, 0], h[:, 1], ".", ms=2, label="calibrated")
    axes[1].set(title="x and y components", xlabel="x", ylabel="y", aspect="equal")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- web pages and certificates
#
# The pages and the PDF certificate draw with the object-oriented API (``Figure``, no pyplot): the
# service renders pages in a thread pool, and pyplot's global figure registry is not thread-safe.

import io  # noqa: E402
import uuid  # noqa: E402
from datetime import datetime, timedelta  # noqa: E402
from typing import Any, Mapping, Sequence  # noqa: E402

from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402

from physics.fit import evaluate, pose_means  # noqa: E402
from physics.frames import SPECIFIC_FORCE_L, to_body  # noqa: E402
from physics.heading import reference_heading, wrap180  # noqa: E402
from physics.table import TableGeometry, platform_attitude  # noqa: E402
from procedures.calibrate import LOOKAHEAD_S, needed_budget_s  # noqa: E402

STAGE_COLORS = {"raw": "#d62728", "bias": "#ff7f0e", "sensitivity": "#2ca02c", "full": "#1f77b4"}
#: (marginal, fail) of an acceptance limit, by the limit's name (service.store.figures keys).
Limits = Mapping[str, tuple[float, float]]


def predicted_staged_errors(cal: Calibration, step_deg: float = 1.0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Heading error (deg) at each correction stage over a full level turn, as the calibration's own
    model predicts it: readings of a unit that is exactly this calibration's sensor, in the field
    (I, D) and on the base tilt the calibration found, corrected up to each stage.

    This is the paper's Fig. 5 for this unit, free of noise and of the recording's pose spacing; the
    full stage is zero for the linear methods by construction (the measured points show the rest).
    Returns the table azimuths and the errors by stage (empty when the field is unknown).
    """
    psi = np.arange(0.0, 360.0, step_deg)
    if not (np.isfinite(cal.inclination_deg) and np.isfinite(cal.declination_deg)):
        return psi, {}
    C = platform_attitude(psi, np.zeros_like(psi), np.zeros_like(psi),
                          TableGeometry(base_tilt_deg=tuple(float(x) for x in cal.base_tilt_deg)))  # type: ignore[arg-type]
    h_b = to_body(C, field_direction(cal.inclination_deg, cal.declination_deg))
    f_b = to_body(C, SPECIFIC_FORCE_L)  # the calibrated accelerometer's f_b is the true one, in the model
    mag = cal.mag.measure(h_b)
    ref = reference_heading(C, cal.declination_deg)
    return psi, {s: heading_error(cal.heading(mag, f_b, s), ref) for s in STAGES}


def measured_staged_errors(rec: Recording, cal: Calibration) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Heading error (deg) at each stage on the recording's level poses (readings averaged per pose,
    as physics.fit.quality scores them): table azimuth and errors by stage (empty without level poses)."""
    mean = pose_means(rec)
    lev = (np.abs(mean.theta_t) < 0.01) & (np.abs(mean.phi_t) < 0.01)
    if not lev.any():
        return np.array([]), {}
    f_b = es.specific_force(mean, cal.acc)
    ref = mean.psi_t[lev] - cal.declination_deg
    order = np.argsort(mean.psi_t[lev])
    return (mean.psi_t[lev][order],
            {s: heading_error(cal.heading(mean.mag[lev], f_b[lev], s), ref)[order] for s in STAGES})


def measured_tilted_errors(rec: Recording, cal: Calibration, max_tilt_deg: float = 60.0) -> dict[str, np.ndarray]:
    """Heading error (deg) of the calibrated compass at the recording's tilted poses within
    ``max_tilt_deg`` of pitch and roll (physics.fit.evaluate: per-pose means against the platform's
    true heading), with each pose's noise; the level poses at the tilted poses' azimuths are included
    (tilt 0). Keys: psi, theta, phi, error, sigma (arrays, maybe empty)."""
    ev = evaluate(rec, cal, max_tilt_deg)
    poses = np.asarray(ev["poses"], dtype=float).reshape(-1, 3)
    err = np.asarray(ev["error_deg"], dtype=float)
    sigma = np.asarray(ev["sigma_deg"], dtype=float)
    theta, phi = wrap180(poses[:, 1]), wrap180(poses[:, 2])
    level = (np.abs(theta) < 0.01) & (np.abs(phi) < 0.01)
    tilted = ~level & (np.abs(theta) <= max_tilt_deg) & (np.abs(phi) <= max_tilt_deg)
    # the level pose at a tilted pose's azimuth is the sweep's zero: it completes the curve
    at_tilted_psi = np.isin(np.round(poses[:, 0], 2), np.round(poses[tilted, 0], 2))
    keep = tilted | (level & at_tilted_psi)
    return {"psi": poses[keep, 0], "theta": theta[keep], "phi": phi[keep], "error": err[keep], "sigma": sigma[keep]}


def _legend_outside(ax: Axes, **kw: Any) -> None:
    """The axes' legend to the right of it, outside: never over a curve or a limit line (a legend
    inside, even at loc "best", sits on a limit line as soon as the data fill the axes)."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, **kw)


def _limit_lines(ax: Axes, limits: Limits | None, name: str) -> None:
    """The acceptance limit as +- lines, so the engineer sees the margin at a glance."""
    if not limits or name not in limits:
        return
    marginal, fail = limits[name]
    for value, color, label in ((marginal, "#e6a700", "marginal limit"), (fail, "#c00000", "fail limit")):
        ax.axhline(value, color=color, lw=0.9, ls="--", label=label)
        ax.axhline(-value, color=color, lw=0.9, ls="--")


def draw_staged(axes: Sequence[Axes], cal: Calibration, rec: Recording | None, limits: Limits | None = None) -> None:
    """Left: the staged heading error over a full level turn (model lines, measured pose means as
    markers). Right: the calibrated error alone, zoomed, with the level acceptance limits."""
    ax, zoom = axes
    psi, predicted = predicted_staged_errors(cal)
    m_psi, measured = measured_staged_errors(rec, cal) if rec is not None else (np.array([]), {})
    for stage in STAGES:
        color = STAGE_COLORS[stage]
        if stage in predicted:
            ax.plot(psi, predicted[stage], "-", color=color, lw=1.2, label=STAGE_LABELS[stage])
        if stage in measured:
            ax.plot(m_psi, measured[stage], "o", color=color, ms=3.5, mfc="none",
                    label=None if stage in predicted else STAGE_LABELS[stage])
    ax.set(title="Heading error by correction stage, level turn", xlabel="table azimuth $\\psi_t$ (deg)",
           ylabel="heading error (deg)", xlim=(0, 360), xticks=np.arange(0, 361, 60))
    ax.grid(True, lw=0.4, alpha=0.6)
    if predicted or measured:
        _legend_outside(ax, title="lines: model\no: measured" if measured and predicted else None, title_fontsize=7)
    if "full" in measured:
        zoom.plot(m_psi, measured["full"], "o-", color=STAGE_COLORS["full"], ms=3.5, lw=0.8, label="measured (pose means)")
    if "full" in predicted and np.max(np.abs(predicted["full"])) > 1e-6:  # a non-linear heading model's residual
        zoom.plot(psi, predicted["full"], "-", color="0.4", lw=1, label="model")
    _limit_lines(zoom, limits, "heading_error_level_deg")
    zoom.set(title=f"Calibrated heading error ({cal.method}), level", xlabel="table azimuth $\\psi_t$ (deg)",
             ylabel="heading error (deg)", xlim=(0, 360), xticks=np.arange(0, 361, 60))
    zoom.grid(True, lw=0.4, alpha=0.6)
    if "full" in measured:
        _legend_outside(zoom)
    else:
        zoom.text(0.5, 0.5, "no level poses recorded", transform=zoom.transAxes, ha="center", color="0.4")


def draw_tilted(ax: Axes, cal: Calibration, rec: Recording | None, limits: Limits | None = None,
                max_tilt_deg: float = 60.0) -> None:
    """Heading error of the calibrated compass at the recorded tilted poses against the tilt angle:
    pitch-only poses (a sweep about y), roll-only poses (about x), and poses with both."""
    t = measured_tilted_errors(rec, cal, max_tilt_deg) if rec is not None else None
    if t is not None and len(t["error"]):
        pitch_only = np.abs(t["phi"]) < 0.01
        roll_only = np.abs(t["theta"]) < 0.01
        both = ~pitch_only & ~roll_only
        for mask, x, label, marker, color in (
                (pitch_only, t["theta"], "pitch $\\theta_t$ (roll 0)", "o", "#1f77b4"),
                (roll_only, t["phi"], "roll $\\varphi_t$ (pitch 0)", "s", "#2ca02c"),
                (both, t["theta"], "pitch and roll (x: pitch)", "^", "#9467bd")):
            if mask.any():
                order = np.argsort(x[mask])
                ax.errorbar(x[mask][order], t["error"][mask][order], yerr=t["sigma"][mask][order], fmt=marker,
                            ls="-" if mask is not both else "none", lw=0.8, ms=4, mfc="none", color=color,
                            capsize=2, label=label)
        headings = sorted({round(float(p), 1) for p in t["psi"]})
        # said in the axis label, outside the axes: inside, a limit line ran through it
        note = "at table azimuth " + ", ".join(f"{h:g}" for h in headings[:6]) + (" ..." if len(headings) > 6 else "") + " deg"
    else:
        note = ""
        ax.text(0.5, 0.5, f"no tilted poses within +-{max_tilt_deg:g} deg recorded", transform=ax.transAxes,
                ha="center", color="0.4")
    _limit_lines(ax, limits, "heading_error_tilted_deg")
    ax.set(title=f"Calibrated heading error at pitch and roll up to +-{max_tilt_deg:g} deg",
           xlabel="tilt angle (deg)" + (f", {note}" if note else ""), ylabel="heading error (deg)",
           xlim=(-max_tilt_deg - 5, max_tilt_deg + 5), xticks=np.arange(-max_tilt_deg, max_tilt_deg + 1, 15))
    ax.grid(True, lw=0.4, alpha=0.6)
    if ax.get_legend_handles_labels()[0]:
        _legend_outside(ax)


def staged_figure(cal: Calibration, rec: Recording | None = None, limits: Limits | None = None) -> Figure:
    """The staged heading-error figure of a calibration (see :func:`draw_staged`)."""
    fig = Figure(figsize=(12, 3.8))
    draw_staged(fig.subplots(1, 2), cal, rec, limits)
    fig.tight_layout()
    return fig


def tilted_figure(cal: Calibration, rec: Recording | None = None, limits: Limits | None = None) -> Figure:
    """The tilted heading-error figure of a calibration (see :func:`draw_tilted`)."""
    fig = Figure(figsize=(9, 3.6))
    draw_tilted(fig.subplots(), cal, rec, limits)
    fig.tight_layout()
    return fig


def precision_figure(precision: Mapping[str, Any]) -> Figure | None:
    """An adaptive calibration's predicted heading error (the bounds that hold together at 95 %) after
    each round of added poses against table time, with the targets and the budget; for a unit the
    budget left short, the budget that would have reached the targets. None without rounds (a
    calibration made before they were kept)."""
    rounds = precision.get("rounds") or []
    if not rounds:
        return None
    fig = Figure(figsize=(9, 3.4))
    ax = fig.subplots()
    t = [r["table_s"] for r in rounds]
    for key, name, color in (("level", "level", "#1f77b4"), ("tilted", "pitch and roll up to +-60 deg", "#d62728")):
        ax.plot(t, [r[f"{key}_deg"] for r in rounds], "o-", color=color, ms=4, lw=1.2, label=f"predicted, {name}")
        ax.axhline(precision[f"target_{key}_deg"], color=color, ls="--", lw=0.9, label=f"target, {key}")
    budget = precision.get("budget_s")
    if budget:
        ax.axvline(budget, color="0.4", ls=":", lw=1.0, label=f"budget {budget:g} s")
    need = needed_budget_s(precision)
    if need is not None:
        ax.axvline(need, color="0.2", ls="-.", lw=1.0, label=f"would reach the targets: {need:.0f} s")
    elif not precision.get("met"):  # said in the legend: a text in the axes would cross the curves
        ax.plot([], [], " ", label=f"would reach the targets:\nnot within {LOOKAHEAD_S / 60:.0f} more min")
    ax.set(title="Predicted heading error (95 % confidence) as the adaptive plan added poses",
           xlabel="table time (s)", ylabel="heading error (deg)", yscale="log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # 0.05, not 5 x 10^-2
    # between the decades only 2, 3 and 5 are labelled (all eight overlap when the axis spans a decade or more)
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:.0e}"[0] in "235" else ""))
    ax.grid(True, which="both", lw=0.4, alpha=0.6)
    _legend_outside(ax)
    fig.tight_layout()
    return fig


#: The narrowest span a trend's time axis shows: a single calibration, or several minutes apart,
#: sit in a window this wide (matplotlib alone spans years around one date).
MIN_TREND_SPAN = timedelta(minutes=2)
#: Tick label formats by the span shown (up to, format): absolute dates and times, the date always
#: there, so that no tick needs an offset text ("30 35 40" and "+2025-06-01 10:31" elsewhere).
TREND_FORMATS = ((timedelta(hours=2), "%H:%M:%S\n%Y-%m-%d"), (timedelta(days=3), "%H:%M\n%Y-%m-%d"),
                 (timedelta(days=3 * 365), "%Y-%m-%d"))


def date_axis(ax: Axes, when: Sequence[datetime]) -> None:
    """A time x axis (UTC) that reads well at any span: the data padded to at least MIN_TREND_SPAN,
    3 to 7 ticks labelled in absolute dates or times, no offset text."""
    import matplotlib.dates as mdates

    lo, hi = min(when), max(when)
    span = max(hi - lo, MIN_TREND_SPAN)
    pad = (span - (hi - lo)) / 2 + span * 0.06  # centred in the minimum span, then a margin
    ax.set_xlim(lo - pad, hi + pad)
    shown = (hi - lo) + 2 * pad
    fmt = next((f for limit, f in TREND_FORMATS if shown <= limit), "%Y-%m")
    locator = mdates.AutoDateLocator(minticks=3, maxticks=7)
    # finer steps than matplotlib's (1, 5, 10 minutes...): 7 minutes would otherwise get one tick
    for freq, steps in ((mdates.SECONDLY, [1, 2, 3, 5, 10, 15, 20, 30]), (mdates.MINUTELY, [1, 2, 3, 5, 10, 15, 20, 30]),
                        (mdates.HOURLY, [1, 2, 3, 4, 6, 8, 12]), (mdates.MONTHLY, [1, 2, 3, 4, 6])):
        locator.intervald[freq] = steps
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.DateFormatter(fmt))
    ax.tick_params(axis="x", labelsize=7)
    ax.set_xlabel("calibrated (UTC)", fontsize=7)


def trend_figures(history: Sequence[Mapping[str, Any]]) -> dict[str, Figure]:
    """A unit's calibrations over time: sensitivities, biases, misalignment angles and heading error.

    ``history`` holds dicts with ``created_at`` (datetime), ``data`` (the calibration JSON), ``status``
    and ``figures`` (service.store.figures). Rejected calibrations are drawn with red crosses over
    their points: they are kept in the history but never used.
    """
    rows = sorted(history, key=lambda h: h["created_at"])
    when = [h["created_at"] for h in rows]
    cals = [Calibration.from_json(h["data"]) for h in rows]
    rejected = np.array([h.get("status") == "rejected" for h in rows], dtype=bool)
    axes_names = ("x_m", "y_m", "z_m")

    def sig(c: Calibration, key: str) -> np.ndarray:
        v = c.sigma.get(key)
        return np.full(3, np.nan) if v is None else np.asarray(v, dtype=float).reshape(-1)[:3]

    def diag_sigma(c: Calibration) -> np.ndarray:
        v = c.sigma.get("angles_deg")
        return np.full(3, np.nan) if v is None else np.diag(np.asarray(v, dtype=float).reshape(3, 3))

    series = {
        "sensitivity": ("Sensitivities k", "LSB per field unit",
                        np.array([c.mag.k for c in cals]), np.array([sig(c, "k") for c in cals]), axes_names),
        "bias": ("Biases b", "LSB", np.array([c.mag.bias for c in cals]), np.array([sig(c, "bias") for c in cals]),
                 axes_names),
        "misalignment": ("Misalignment: angle between sensor and body axis", "deg",
                         np.array([np.diag(c.mag.angles_deg) for c in cals]), np.array([diag_sigma(c) for c in cals]),
                         ("x_m to x_b", "y_m to y_b", "z_m to z_b")),
    }
    he = np.array([[(h.get("figures") or {}).get(k) for k in ("heading_error_level_deg", "heading_error_tilted_deg")]
                   for h in rows], dtype=float).reshape(-1, 2)
    series["heading"] = ("Heading error (max |error|, on the calibration's recording)", "deg", he,
                         np.full_like(he, np.nan), ("level", "pitch and roll up to +-60 deg"))
    out: dict[str, Figure] = {}
    for key, (title, unit, values, sigmas, labels) in series.items():
        fig = Figure(figsize=(5.6, 3.0))
        ax = fig.subplots()
        for j, label in enumerate(labels):
            y = values[:, j]
            if not np.isfinite(y).any():
                continue
            e = sigmas[:, j]
            ax.errorbar(when, y, yerr=np.where(np.isfinite(e), e, 0.0), fmt="o-", ms=4, lw=1, capsize=2, label=label)
        if rejected.any():
            for j in range(values.shape[1]):
                ax.plot([w for w, r in zip(when, rejected) if r], values[rejected, j], "x", color="#c00000", ms=8,
                        label="rejected" if j == 0 else None)
        ax.set(title=title, ylabel=unit)
        ax.title.set_fontsize(9)
        date_axis(ax, when)
        ax.grid(True, lw=0.4, alpha=0.6)
        ax.tick_params(labelsize=7)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="best")
        fig.tight_layout()
        out[key] = fig
    return out


def svg(fig: Figure, css_class: str, label: str) -> str:
    """An inline ``<svg>`` element of a figure for an HTML page: no XML prolog, the given class, an
    accessible label, scaled to its container. Text stays text (svg.fonttype none), so the page
    needs no embedded glyphs; a random hash salt keeps element ids unique among several figures."""
    import re
    from html import escape

    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": uuid.uuid4().hex}):
        fig.savefig(buf, format="svg", metadata={"Date": None})
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    text = re.sub(r"\s*<metadata>.*?</metadata>", "", text, count=1, flags=re.S)  # RDF boilerplate, no use inline
    head_end = text.index(">")
    head = text[:head_end]
    width = re.search(r'width="([\d.]+)pt"', head)
    head = re.sub(r'\s(width|height)="[^"]*"', "", head)
    style = f"width:100%;height:auto;max-width:{float(width.group(1)) * 4 / 3:.0f}px" if width else "width:100%;height:auto"
    head += f' class="{escape(css_class)}" role="img" aria-label="{escape(label)}" style="{style}"'
    return head + f"><title>{escape(label)}</title>" + text[head_end + 1:]


#: Colours of the verdicts on the certificate.
VERDICT_COLORS = {"PASS": "#1a7f37", "MARGINAL": "#b58100"}
#: Left margin and text width of a certificate page (figure fraction of A4).
PAGE_X, PAGE_W = 0.07, 0.86


def _line_h(fig: Figure, fontsize: float, spacing: float = 1.3) -> float:
    """The height of one line of text at ``fontsize`` in figure fraction."""
    return fontsize * spacing / (fig.get_figheight() * 72.0)


def _wrap(text: str, width_in: float, fontsize: float) -> list[str]:
    """``text`` broken into lines that fit ``width_in`` inches at ``fontsize`` (DejaVu Sans is about
    0.55 em per character on average)."""
    import textwrap
    chars = max(4, int(width_in * 72.0 / (fontsize * 0.55)))
    return textwrap.wrap(str(text), chars) or [""]


def _text_block(fig: Figure, y: float, lines: Sequence[str], fontsize: float = 8.5, x: float = PAGE_X,
                **kw: Any) -> float:
    """Lines of text from ``y`` (their top) down; returns the y below the last."""
    step = _line_h(fig, fontsize, 1.45)
    for line in lines:
        fig.text(x, y, line, fontsize=fontsize, va="top", **kw)
        y -= step
    return y


def _heading(fig: Figure, y: float, text: str, fontsize: float = 10.0, gap: float = 0.018) -> float:
    """A section heading ``gap`` below ``y``; returns the y below it."""
    y -= gap
    fig.text(PAGE_X, y, text, fontsize=fontsize, fontweight="bold", va="top")
    return y - _line_h(fig, fontsize, 1.55)


def _draw_table(fig: Figure, y: float, header: Sequence[str], rows: Sequence[Sequence[str]],
                widths: Sequence[float], numeric: Sequence[int] = (), fontsize: float = 8.0) -> float:
    """A table of text drawn from ``y`` (its top, figure fraction) down, sized to its content: a
    shaded header, thin rules between rows, each cell wrapped to its column (``widths``: fractions
    of the text width), ``numeric`` columns right-aligned. Returns the y just below it.

    (Drawn as text rather than with matplotlib's table in an axes of a guessed height: that left
    large blank gaps under short tables.)"""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    line, pad = _line_h(fig, fontsize), 0.45 * _line_h(fig, fontsize)
    edges = np.r_[0.0, np.cumsum(widths)] / max(sum(widths), 1e-9) * PAGE_W + PAGE_X
    cell_pad = 0.006

    def rule(at: float, lw: float = 0.4) -> None:
        fig.add_artist(Line2D([PAGE_X, PAGE_X + PAGE_W], [at, at], transform=fig.transFigure, lw=lw, color="0.55"))

    for r, row in enumerate([list(header), *[list(x) for x in rows]] if rows else [list(header), ["-"] * len(header)]):
        cells = [_wrap(c, (edges[j + 1] - edges[j] - 2 * cell_pad) * fig.get_figwidth(), fontsize)
                 for j, c in enumerate(row)]
        h = max(len(c) for c in cells) * line + 2 * pad
        if r == 0:
            fig.add_artist(Rectangle((PAGE_X, y - h), PAGE_W, h, transform=fig.transFigure, facecolor="#e8eef5",
                                     edgecolor="none", zorder=0))
            rule(y, 0.6)
        for j, c in enumerate(cells):
            right = j in numeric  # numbers (and their heads) right-aligned: decimals line up
            fig.text(edges[j + 1] - cell_pad if right else edges[j] + cell_pad, y - pad, "\n".join(c),
                     fontsize=fontsize, va="top", ha="right" if right else "left", linespacing=1.3,
                     fontweight="bold" if r == 0 else "normal")
        y -= h
        rule(y, 0.6 if r in (0, len(rows)) else 0.3)
    return y


def _footer(fig: Figure, cert: Mapping[str, Any], page: int, pages: int = 3) -> None:
    fig.text(PAGE_X, 0.03, f"compasscal {cert['software_version']} - certificate {cert['number']} - "
             f"page {page} of {pages}", fontsize=7, color="0.4")


def certificate_pages(cert: Mapping[str, Any], cal: Calibration, rec: Recording | None,
                      limits: Limits | None) -> list[Figure]:
    """The certificate's three A4 pages as figures (see :func:`certificate_pdf`); separate so that
    the layout can be checked, or drawn to PNG, without a PDF reader. Each page is laid out from
    the top down, every element right below the one before (no fixed slots to leave blank)."""
    a4 = (8.27, 11.69)
    verdict_color = VERDICT_COLORS.get(cert["verdict"], "#c00000")

    # --- page 1: who, what, where, and the parameters
    fig = Figure(figsize=a4)
    fig.text(PAGE_X, 0.955, "Calibration certificate", fontsize=18, fontweight="bold")
    fig.text(PAGE_X, 0.93, f"No. {cert['number']}  -  electronic compass, three-axis magnetometer", fontsize=10)
    fig.text(PAGE_X + PAGE_W, 0.955, cert["verdict"], fontsize=18, fontweight="bold", ha="right", color=verdict_color)
    y = 0.905
    step = _line_h(fig, 8.5, 1.6)
    for label, value in cert["info"]:
        fig.text(PAGE_X, y, label, fontsize=8.5, color="0.3", va="top")
        fig.text(0.32, y, str(value), fontsize=8.5, va="top")
        y -= step
    y = _heading(fig, y, "Table 1: angles between sensor axes and body axes (deg, +- 1 sigma)")
    y = _draw_table(fig, y, ["axis", "x_b", "y_b", "z_b"], cert["table1"], [0.16, 0.28, 0.28, 0.28], numeric=(1, 2, 3))
    y = _heading(fig, y, "Table 2: sensitivities and biases (LSB, +- 1 sigma) and model residuals")
    y = _draw_table(fig, y, ["axis", "sensitivity k", "bias b", "residual rms"], cert["table2"],
                    [0.16, 0.3, 0.3, 0.24], numeric=(1, 2, 3))
    y = _heading(fig, y, "Field and table")
    y = _text_block(fig, y, cert["field"])
    if cert.get("staged"):
        y = _heading(fig, y, "Staged heading error on the recording (max |error|, deg)")
        y = _draw_table(fig, y, ["correction stage", "max |heading error| (deg)"], cert["staged"], [0.6, 0.4],
                        numeric=(1,))
    _footer(fig, cert, 1)
    pages = [fig]

    # --- page 2: the curves (legends right of each plot, outside: see draw_staged)
    fig = Figure(figsize=a4)
    fig.text(PAGE_X, 0.955, f"Heading error - {cert['serial']}", fontsize=14, fontweight="bold")
    fig.text(PAGE_X, 0.935, "Lines: the calibration's model over a full level turn at each correction stage; "
             "markers: the recording's pose means.", fontsize=8, color="0.3")
    ax_a, ax_b, ax_c = fig.subplots(3, 1)
    draw_staged((ax_a, ax_b), cal, rec, limits)
    draw_tilted(ax_c, cal, rec, limits)
    fig.tight_layout(rect=(0.03, 0.05, 0.97, 0.925), h_pad=2.0)
    _footer(fig, cert, 2)
    pages.append(fig)

    # --- page 3: limits, verdict, notes, signature
    fig = Figure(figsize=a4)
    fig.text(PAGE_X, 0.955, "Acceptance", fontsize=14, fontweight="bold")
    y = _heading(fig, 0.935, "Acceptance limits (above marginal: MARGINAL; above fail: FAIL)", gap=0.0)
    # each figure by its description, as the HTML certificate says it; its value and limits in one
    # fixed-point format (service/web.py limit_rows)
    y = _draw_table(fig, y, ["figure", "value", "marginal above", "fail above", "unit", "result"],
                    [[r["description"] or r["name"], r["value_text"], r.get("marginal_text", f"{r['marginal']:g}"),
                      r.get("fail_text", f"{r['fail']:g}"), r["unit"], r["result"]] for r in cert["limits"]],
                    [0.43, 0.12, 0.13, 0.11, 0.08, 0.13], numeric=(1, 2, 3))
    y -= 0.025
    fig.text(PAGE_X, y, f"Verdict: {cert['verdict']}", fontsize=14, fontweight="bold", va="top", color=verdict_color)
    y -= _line_h(fig, 14, 1.5)
    y = _text_block(fig, y, [f"Calibration status: {cert['status']}"], fontsize=9)
    for reason in cert["reasons"] or ["every figure within its marginal limit"]:
        y = _text_block(fig, y, _wrap("- " + reason, PAGE_W * a4[0] - 0.3, 8.5), x=PAGE_X + 0.02)
    if cert.get("notes"):
        y = _heading(fig, y, "Notes")
        for note in cert["notes"]:
            lines = _wrap(note, PAGE_W * a4[0], 7.5)
            if y - len(lines) * _line_h(fig, 7.5, 1.45) < 0.16:  # the rest of the page is the signature's
                y = _text_block(fig, y, ["(more notes on the HTML certificate)"], fontsize=7.5, color="0.25")
                break
            y = _text_block(fig, y, lines, fontsize=7.5, color="0.25")
    y -= 0.03
    y = _text_block(fig, y, [f"Issued {cert['issued']} by compasscal {cert['software_version']}; "
                             f"calibration {cert['id']}, run {cert['run_id']}."], fontsize=8)
    fig.text(PAGE_X, y - 0.03, "Signature: ______________________________", fontsize=9, va="top")
    _footer(fig, cert, 3)
    pages.append(fig)
    return pages


def certificate_pdf(cert: Mapping[str, Any], cal: Calibration, rec: Recording | None, limits: Limits | None) -> bytes:
    """The calibration certificate as a PDF (A4, three pages): identification and parameters with
    their uncertainties; the heading-error curves; the acceptance limits and the verdict.

    ``cert`` is the context of the HTML certificate (service/web.py): strings, the two tables' rows
    (``table1``, ``table2``), ``info`` pairs, ``field`` lines, ``limits`` rows, verdict and reasons.
    """
    from matplotlib.backends.backend_pdf import PdfPages

    out = io.BytesIO()
    meta = {"Title": f"Calibration certificate {cert['number']}", "Author": "compasscal", "Subject": cert["serial"],
            "Creator": f"compasscal {cert['software_version']}"}
    with PdfPages(out, metadata=meta) as pdf:
        for fig in certificate_pages(cert, cal, rec, limits):
            pdf.savefig(fig)
        info = pdf.infodict()
        info["CreationDate"] = datetime.now()
    return out.getvalue()


# --------------------------------------------------------------------------- discrepancy analysis
#
# Figures of the HTML analysis report (service/report.py), from an analysis's ``result`` (JSON, as
# stored) and ``series`` (arrays, only right after the analysis ran). Object-oriented API, like the
# pages above: reports are rendered in worker threads too.

AXIS_NAMES = ("m_x", "m_y", "m_z")
BEFORE_COLOR, AFTER_COLOR = "#d62728", "#1f77b4"


def residual_names(result: Mapping[str, Any]) -> tuple[str, ...]:
    """Names of an analysis's residual columns: the sensor axes, or for the attitude-free model what
    its ``residual_columns`` say (the field magnitude first; empty for an unused column)."""
    if result.get("model") != "attitude_free":
        return AXIS_NAMES
    cols = list(result.get("residual_columns") or ["magnitude"])
    cols += [None] * (3 - len(cols))
    return tuple({"magnitude": "|m|"}.get(str(c), str(c)) if c else "" for c in cols[:3])


def _name(names: Sequence[str], i: int) -> str:
    return names[i] if i < len(names) and names[i] else f"column {i}"


def _residual_columns(series: Mapping[str, Any]) -> list[int]:
    """The residual columns that hold numbers (the attitude-free model fills column 0 only)."""
    r = np.asarray(series["residual_before"], dtype=float).reshape(len(series["t"]), -1)
    return [i for i in range(r.shape[1]) if np.isfinite(r[:, i]).any()]


#: Points per scatter panel at most: a longer recording is drawn every k-th sample (the picture is
#: the same, the report is rendered several times faster).
MAX_POINTS = 20_000


def _thin(n: int) -> np.ndarray:
    """Indices of the samples a scatter panel draws (every k-th, keeping at most MAX_POINTS)."""
    return np.arange(0, n, max(1, -(-n // MAX_POINTS)))


def _rms(r: np.ndarray) -> np.ndarray:
    """Per-column rms of the finite values (NaN for a column without any)."""
    ok = np.isfinite(r)
    n = ok.sum(axis=0)
    return np.where(n > 0, np.sqrt(np.where(ok, r * r, 0.0).sum(axis=0) / np.maximum(n, 1)), np.nan)


def _step_codes(steps: Any) -> tuple[np.ndarray, list[str]]:
    """Each sample's step as an integer in order of first appearance, and the step names."""
    names: dict[str, int] = {}
    codes = np.array([names.setdefault(str(s), len(names)) for s in np.asarray(steps, dtype=object)], dtype=int)
    return codes, list(names)


def _step_colors(codes: np.ndarray) -> np.ndarray:
    import matplotlib as mpl
    cmap = mpl.colormaps["tab20"]
    return cmap(codes % 20)


def residual_time_figure(series: Mapping[str, Any], names: Sequence[str] = AXIS_NAMES,
                         windows: Sequence[Sequence[float]] = ()) -> Figure | None:
    """Residuals against time, before (left) and after (right) the fitted effects, one row per sensor
    axis, coloured by step: where in the run the mismatch lives; ``windows`` (the time segments of the
    findings) shaded. Points are rasterised inside the SVG (a long run has tens of thousands). None when
    no residual is finite."""
    t = np.asarray(series["t"], dtype=float)
    before = np.asarray(series["residual_before"], dtype=float).reshape(len(t), -1)
    after = np.asarray(series["residual_after"], dtype=float).reshape(len(t), -1)
    cols = _residual_columns(series)
    if not cols:
        return None
    codes, steps = _step_codes(series["step"])
    rms = {"before": _rms(before), "after": _rms(after)}  # of every sample, before thinning
    keep = _thin(len(t))
    t, before, after, colors = t[keep], before[keep], after[keep], _step_colors(codes[keep])
    fig = Figure(figsize=(11, 1.0 + 2.1 * len(cols)))
    axes = np.asarray(fig.subplots(len(cols), 2, sharex=True, squeeze=False))
    for row, i in enumerate(cols):
        lim = np.nanmax(np.abs(np.r_[before[:, i], after[:, i]])) if np.isfinite(before[:, i]).any() else 1.0
        for col, (r, label) in enumerate(((before, "before"), (after, "after"))):
            ax = axes[row, col]
            for a, b in windows:  # when a discovered departure was present
                ax.axvspan(float(a), float(b), color="#f4c542", alpha=0.25, lw=0)
            ax.scatter(t, r[:, i], c=colors, s=2, lw=0, rasterized=True)
            ax.axhline(0, color="0.5", lw=0.6)
            ax.set_title(f"{_name(names, i)} {label} the fitted effects (rms {rms[label][i]:.3g} LSB)",
                         fontsize=9)
            ax.set_ylim(-1.05 * lim, 1.05 * lim)
            ax.grid(True, lw=0.4, alpha=0.6)
            ax.tick_params(labelsize=7)
            if col == 0:
                ax.set_ylabel("residual (LSB)", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time t (s)", fontsize=8)
    _step_legend(fig, steps)
    return fig


def _step_legend(fig: Figure, steps: Sequence[str]) -> None:
    """The colours of the steps (:func:`_step_colors`) as a legend under the panels, then the layout. A
    legend of a few steps helps; of fifty it hides the data: none beyond 16."""
    if len(steps) <= 16:
        import matplotlib.lines as mlines
        handles = [mlines.Line2D([], [], ls="", marker="o", ms=4, color=_step_colors(np.array([k]))[0], label=s)
                   for k, s in enumerate(steps)]
        fig.legend(handles=handles, loc="lower center", ncol=min(8, len(steps)), fontsize=7, frameon=False)
        fig.tight_layout(rect=(0, 0.06 if len(steps) <= 8 else 0.1, 1, 1))
    else:
        fig.tight_layout()


def samples_figure(rec: Recording) -> Figure:
    """A recording's magnetometer readings against time, one row per axis, coloured by step: what a run
    that ended without a calibration measured before it stopped (the steps it reached, where it stopped)."""
    codes, steps = _step_codes(rec.step)
    keep = _thin(len(rec))
    colors = _step_colors(codes[keep])
    fig = Figure(figsize=(11, 5.2))
    axes = fig.subplots(3, 1, sharex=True)
    for i, ax in enumerate(axes):
        ax.scatter(rec.t[keep], rec.mag[keep, i], c=colors, s=2, lw=0, rasterized=True)
        ax.set_ylabel(f"{AXIS_NAMES[i]} (LSB)", fontsize=8)
        ax.grid(True, lw=0.4, alpha=0.6)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time t (s)", fontsize=8)
    _step_legend(fig, steps)
    return fig


def residual_angle_figure(series: Mapping[str, Any], names: Sequence[str] = AXIS_NAMES) -> Figure | None:
    """Residuals against each table angle (columns psi_t, theta_t, phi_t), one row per sensor axis,
    before (red) and after (blue): the harmonics a stage magnet or an axis error leaves. None
    without table angles."""
    # heading on [0, 360), the gimbal angles on [-180, 180) as the tilted-pose plots show them
    angles = [(k, np.asarray(series.get(k, []), dtype=float)) for k in ("psi_t", "theta_t", "phi_t")]
    angles = [(k, a % 360.0 if k == "psi_t" else (a + 180.0) % 360.0 - 180.0) for k, a in angles]
    angles = [(k, a) for k, a in angles if len(a) and np.isfinite(a).any() and np.nanmax(a) - np.nanmin(a) > 1e-6]
    if not angles:
        return None
    n = len(series["t"])
    before = np.asarray(series["residual_before"], dtype=float).reshape(n, -1)
    after = np.asarray(series["residual_after"], dtype=float).reshape(n, -1)
    cols = _residual_columns(series)
    if not cols:
        return None
    keep = _thin(n)
    angles = [(k, a[keep]) for k, a in angles]
    before, after = before[keep], after[keep]
    symbols = {"psi_t": "$\\psi_t$", "theta_t": "$\\theta_t$", "phi_t": "$\\varphi_t$"}
    fig = Figure(figsize=(3.6 * len(angles) + 0.8, 0.8 + 2.0 * len(cols)))
    axes = np.asarray(fig.subplots(len(cols), len(angles), sharex="col", squeeze=False))
    for row, i in enumerate(cols):
        for col, (key, a) in enumerate(angles):
            ax = axes[row, col]
            ax.scatter(a, before[:, i], s=2, lw=0, color=BEFORE_COLOR, alpha=0.5, rasterized=True, label="before")
            ax.scatter(a, after[:, i], s=2, lw=0, color=AFTER_COLOR, alpha=0.7, rasterized=True, label="after")
            ax.axhline(0, color="0.5", lw=0.6)
            ax.grid(True, lw=0.4, alpha=0.6)
            ax.tick_params(labelsize=7)
            if col == 0:
                ax.set_ylabel(f"{_name(names, i)} residual (LSB)", fontsize=8)
            if row == len(cols) - 1:
                ax.set_xlabel(f"{symbols[key]} (deg)", fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="best", markerscale=3)
    fig.suptitle("Residuals against the table angles: red before, blue after the fitted effects", fontsize=9)
    fig.tight_layout()
    return fig


def _number_list(v: Any) -> np.ndarray | None:
    """A list (or list of lists) of numbers as a float array; None for anything else."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return None
    return a if a.ndim in (1, 2) and a.size else None


def _harmonic_rows(harmonics: Mapping[str, Any]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(against what, orders, amplitudes (orders x axes)) for each entry of ``locate.harmonics`` that
    holds amplitudes: ``{"psi_t": {"orders": [...], "amplitude_lsb": [[x, y, z], ...]}}`` or a bare
    list of amplitudes per order (a flat list is one axis)."""
    out = []
    for name, entry in harmonics.items():
        orders, amp = None, None
        if isinstance(entry, Mapping):
            for k, v in entry.items():
                if k.startswith("order") or k in ("k", "n"):
                    orders = _number_list(v)
                elif k.startswith("amplitude") or k.startswith("amp"):
                    amp = _number_list(v)
        else:
            amp = _number_list(entry)
        if amp is None:
            continue
        if amp.ndim == 1:
            amp = amp[:, None]
        if orders is not None and orders.ndim == 1 and amp.shape[0] != len(orders) and amp.shape[1] == len(orders):
            amp = amp.T  # axes x orders
        if orders is None or orders.ndim != 1 or len(orders) != amp.shape[0]:
            orders = np.arange(1, amp.shape[0] + 1, dtype=float)
        out.append((str(name), orders, amp))
    return out


def harmonics_figure(harmonics: Mapping[str, Any] | None, names: Sequence[str] = AXIS_NAMES) -> Figure | None:
    """Harmonic amplitudes of the residual against heading and each gimbal angle (bars per order and
    axis), from ``result["locate"]["harmonics"]``; None when it holds none."""
    rows = _harmonic_rows(harmonics or {})
    if not rows:
        return None
    fig = Figure(figsize=(min(3.4 * len(rows) + 0.6, 14), 3.0))
    axes = np.atleast_1d(fig.subplots(1, len(rows), squeeze=False)[0])
    colors = ("#1f77b4", "#2ca02c", "#9467bd")
    for ax, (name, orders, amp) in zip(axes, rows):
        width = 0.8 / amp.shape[1]
        for j in range(amp.shape[1]):
            ax.bar(np.arange(len(orders)) + (j - (amp.shape[1] - 1) / 2) * width, amp[:, j], width,
                   color=colors[j % 3], label=_name(names, j))
        ax.set_xticks(np.arange(len(orders)), [f"{o:g}" for o in orders])
        ax.set_title(f"against {name}", fontsize=9)
        ax.set_xlabel("harmonic order", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, axis="y", lw=0.4, alpha=0.6)
    axes[0].set_ylabel("amplitude (LSB)", fontsize=8)
    axes[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig


def by_step_figure(by_step: Sequence[Mapping[str, Any]] | None, noise: Sequence[Any] | None = None,
                   names: Sequence[str] = AXIS_NAMES) -> Figure | None:
    """Residual RMS of each step per sensor axis (``result["locate"]["by_step"]``), with the noise
    floor as dashed lines: the step where the model fails stands out. None without steps."""
    rows = [r for r in (by_step or []) if isinstance(r, Mapping) and _number_list(r.get("rms_lsb")) is not None]
    if not rows:
        return None
    rms = np.array([np.asarray(r["rms_lsb"], dtype=float).reshape(-1)[:3] for r in rows], dtype=float)
    cols = [j for j in range(rms.shape[1]) if np.isfinite(rms[:, j]).any()]
    colors = ("#1f77b4", "#2ca02c", "#9467bd")
    fig = Figure(figsize=(min(max(6.0, 0.28 * len(rows) * len(cols) + 1.5), 14), 3.4))
    ax = fig.subplots()
    width = 0.8 / max(len(cols), 1)
    x = np.arange(len(rows))
    for k, j in enumerate(cols):
        ax.bar(x + (k - (len(cols) - 1) / 2) * width, rms[:, j], width, color=colors[j % 3],
               label=_name(names, j))
        if noise is not None:
            nf = _number_list(noise)
            if nf is not None and nf.ndim == 1 and j < len(nf) and np.isfinite(nf[j]):
                ax.axhline(nf[j], color=colors[j % 3], ls="--", lw=0.8)
    ax.set_xticks(x, [str(r.get("step")) for r in rows], rotation=60 if len(rows) > 6 else 0, ha="right" if len(rows) > 6 else "center",
                  fontsize=7)
    ax.set(ylabel="residual rms (LSB)")
    ax.set_title("Residual rms by step before the fitted effects (dashed: noise floor)", fontsize=9)
    ax.grid(True, axis="y", lw=0.4, alpha=0.6)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig


def fit_summary_figure(result: Mapping[str, Any]) -> Figure:
    """The fit before and after per sensor axis: in-sample and held-out residual rms, with the noise
    floor. Held-out bars are the honest ones (each sample predicted by a fit that never saw it)."""
    names = residual_names(result)
    held = result.get("heldout") or {}
    bars = [("in-sample before", result.get("residual_rms_before_lsb"), "#f4a3a3"),
            ("in-sample after", result.get("residual_rms_after_lsb"), "#9ec5e8"),
            ("held-out before", held.get("rms_before_lsb"), BEFORE_COLOR),
            ("held-out after", held.get("rms_after_lsb"), AFTER_COLOR)]
    vals = [(label, np.asarray([np.nan if v is None else v for v in (x or [])], dtype=float), c) for label, x, c in bars]
    n_axes = max([len(v) for _, v, _ in vals] + [1])
    cols = [j for j in range(n_axes) if any(j < len(v) and np.isfinite(v[j]) for _, v, _ in vals)] or [0]
    fig = Figure(figsize=(max(5.5, 1.6 + 1.9 * len(cols)), 3.2))
    ax = fig.subplots()
    width = 0.8 / len(vals)
    for k, (label, v, color) in enumerate(vals):
        y = [v[j] if j < len(v) else np.nan for j in cols]
        ax.bar(np.arange(len(cols)) + (k - (len(vals) - 1) / 2) * width, y, width, color=color, label=label)
    nf = _number_list([np.nan if v is None else v for v in (result.get("noise_floor_lsb") or [])])
    if nf is not None and nf.ndim == 1 and result.get("model") != "attitude_free":  # there it is per axis, not per column
        for k, j in enumerate(cols):
            if j < len(nf) and np.isfinite(nf[j]):
                ax.plot([k - 0.45, k + 0.45], [nf[j], nf[j]], color="k", ls="--", lw=1,
                        label="noise floor" if k == 0 else None)
    ax.set_xticks(np.arange(len(cols)), [_name(names, j) for j in cols])
    ax.set(ylabel="residual rms (LSB)")
    imp = held.get("improvement_pct")
    ax.set_title("Fit before and after the fitted effects"
                 + (f"\nheld-out improvement {imp:.1f} %" if isinstance(imp, (int, float)) else ""), fontsize=9)
    ax.grid(True, axis="y", lw=0.4, alpha=0.6)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig


def heldout_figure(series: Mapping[str, Any], names: Sequence[str] = AXIS_NAMES) -> Figure | None:
    """Held-out prediction against time: how much the prediction of each sample (by a model fitted
    without that sample's fold) changes when the effects are added, per axis, coloured by fold.
    With the measurement (``series["mag"]``) the held-out residuals before and after instead."""
    if "heldout_pred_before" not in series or "heldout_pred_after" not in series:
        return None
    t = np.asarray(series["t"], dtype=float)
    n = len(t)
    pb = np.asarray(series["heldout_pred_before"], dtype=float).reshape(n, -1)
    pa = np.asarray(series["heldout_pred_after"], dtype=float).reshape(n, -1)
    fold = np.asarray(series.get("fold", np.zeros(n)), dtype=float).reshape(-1)
    cols = [i for i in range(pb.shape[1]) if np.isfinite(pb[:, i]).any() and np.isfinite(pa[:, i]).any()]
    if not cols:
        return None
    mag = series.get("mag")
    keep = _thin(n)
    t, pb, pa, fold = t[keep], pb[keep], pa[keep], fold[keep]
    if mag is not None:
        mag = np.asarray(mag, dtype=float).reshape(n, -1)[keep]
    fig = Figure(figsize=(11, 0.8 + 1.9 * len(cols)))
    axes = np.asarray(fig.subplots(len(cols), 1, sharex=True, squeeze=False))[:, 0]
    import matplotlib as mpl
    cmap = mpl.colormaps["tab10"]
    for ax, i in zip(axes, cols):
        label = _name(names, i)
        if mag is not None:
            m = mag[:, i]
            ax.scatter(t, m - pb[:, i], s=2, lw=0, color=BEFORE_COLOR, alpha=0.5, rasterized=True, label="before")
            ax.scatter(t, m - pa[:, i], s=2, lw=0, color=AFTER_COLOR, alpha=0.7, rasterized=True, label="after")
            ax.set_ylabel(f"{label} held-out\nresidual (LSB)", fontsize=8)
        else:
            ax.scatter(t, pa[:, i] - pb[:, i], s=2, lw=0, c=cmap(fold.astype(int) % 10), rasterized=True)
            ax.set_ylabel(f"{label} after - before\n(LSB)", fontsize=8)
        ax.axhline(0, color="0.5", lw=0.6)
        ax.grid(True, lw=0.4, alpha=0.6)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time t (s)", fontsize=8)
    if mag is not None:
        axes[0].legend(fontsize=7, loc="best", markerscale=3)
        axes[0].set_title("Held-out residuals (each sample predicted by a fit without its fold): red before, blue after",
                          fontsize=9)
    else:
        axes[0].set_title("What the fitted effects add to the held-out prediction of each sample (colour: fold)",
                          fontsize=9)
    fig.tight_layout()
    return fig
