"""The discrepancy analysis as a self-contained HTML page: where the recording departs from the
nominal model, what the analyser named, and the fit before and after.

Everything is inline (CSS and matplotlib figures as SVG, their dense scatter layers as embedded
PNG): the file opens from a mail attachment or an archive with no network and no server. Works from
a stored result alone (``series=None``, as the database keeps it): then the tables and the figures
that need no per-sample arrays (by-step rms, harmonics, before/after rms).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from jinja2 import Environment, FileSystemLoader, select_autoescape

from service import plots

_env = Environment(loader=FileSystemLoader(str(Path(__file__).parent / "templates")),
                   autoescape=select_autoescape(default=True, default_for_string=True))

#: Finding keys shown in their own columns (in this order); any other key goes to "other".
FINDING_COLUMNS = ("effect", "statistic", "df", "p_value", "p_adjusted", "parameters", "sigma", "heading_impact_deg",
                   "where", "explanation", "confusable_with", "separating_experiment", "model", "plausible")
#: Test keys of the contract (columns of the tests table, in this order).
TEST_COLUMNS = ("effect", "variant", "statistic", "df", "p_value", "p_adjusted", "selected")


def num(v: Any, digits: int = 4) -> str:
    """A number for people: ``digits`` significant digits, small p-values in e-notation, "-" for none."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not math.isfinite(f):
        return "-"
    return f"{f:.{digits}g}"


def text(v: Any) -> str:
    """Any JSON value as one line of text (dicts as ``key: value; ...``)."""
    if isinstance(v, Mapping):
        return "; ".join(f"{k}: {text(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(text(x) for x in v) + "]" if any(isinstance(x, (list, tuple, Mapping)) for x in v) \
            else ", ".join(text(x) for x in v)
    if isinstance(v, str):
        return v
    return num(v)


def with_sigma(value: Any, sigma: Any) -> str:
    """``value ± sigma``, element by element for lists (a 3-vector stays one cell)."""
    if isinstance(value, (list, tuple)):
        sig = sigma if isinstance(sigma, (list, tuple)) and len(sigma) == len(value) else [None] * len(value)
        return "[" + ", ".join(with_sigma(v, s) for v, s in zip(value, sig)) + "]"
    if isinstance(value, (int, float)) and not isinstance(value, bool) and isinstance(sigma, (int, float)) \
            and not isinstance(sigma, bool) and math.isfinite(float(sigma)):
        return f"{num(value)} ± {num(sigma, 2)}"
    return text(value)


def parameter_rows(finding: Mapping[str, Any]) -> list[tuple[str, str]]:
    """A finding's parameters as (name, "value ± sigma") rows."""
    params = finding.get("parameters") or {}
    sigma = finding.get("sigma") or {}
    if not isinstance(params, Mapping):
        return [("", text(params))]
    return [(str(k), with_sigma(v, sigma.get(k) if isinstance(sigma, Mapping) else None)) for k, v in params.items()]


def parameter_cells(finding: Mapping[str, Any]) -> list[tuple[str, list[str]]]:
    """A finding's parameters for the page: (name, one "value ± sigma" string per element)."""
    params = finding.get("parameters") or {}
    sigma = finding.get("sigma") or {}
    if not isinstance(params, Mapping):
        return [("", [text(params)])]
    out = []
    for k, v in params.items():
        s = sigma.get(k) if isinstance(sigma, Mapping) else None
        if isinstance(v, (list, tuple)) and not any(isinstance(x, (list, tuple, Mapping)) for x in v):
            sig = s if isinstance(s, (list, tuple)) and len(s) == len(v) else [None] * len(v)
            out.append((str(k), [with_sigma(x, e) for x, e in zip(v, sig)]))
        else:
            out.append((str(k), [with_sigma(v, s)]))
    return out


def tree(v: Any, depth: int = 0) -> dict[str, Any]:
    """A nested JSON value as a render tree for the template: a dict becomes key/value rows, a list
    of dicts a table with the union of their keys, anything else one line of text."""
    if isinstance(v, Mapping) and v and depth < 4:
        return {"kind": "dict", "rows": [(str(k), tree(x, depth + 1)) for k, x in v.items()]}
    if isinstance(v, (list, tuple)) and v and all(isinstance(x, Mapping) for x in v) and depth < 4:
        keys: list[str] = []
        for x in v:
            keys += [str(k) for k in x if str(k) not in keys]
        return {"kind": "table", "keys": keys, "rows": [[text(x.get(k)) for k in keys] for x in v]}
    return {"kind": "text", "text": text(v) if v not in (None, {}, []) else "-"}


def model_text(finding: Mapping[str, Any]) -> str:
    """A finding's model in one line: form, frame, what it follows and when (the one finding schema)."""
    m = finding.get("model") or {}
    if not isinstance(m, Mapping) or not any(m.get(k) for k in ("frame", "form", "against", "segments")):
        return "-"
    parts = [str(m.get("form") or "structure"), f"in the {m['frame']} frame" if m.get("frame") else ""]
    if m.get("against"):
        parts.append(f"against {m['against']}")
    segs = m.get("segments") or []
    if segs:
        parts.append("during " + ", ".join(f"{num(a, 4)}-{num(b, 4)} s" for a, b in segs))
    if finding.get("plausible") is False:
        parts.append("(implausible size)")
    return " ".join(p for p in parts if p)


def per_axis(values: Any, digits: int = 4) -> list[str]:
    """Three per-axis numbers as strings (missing ones "-")."""
    vals = list(values) if isinstance(values, (list, tuple)) else []
    return [num(vals[i], digits) if i < len(vals) else "-" for i in range(3)]


def analysis_figures(result: Mapping[str, Any], series: Mapping[str, Any] | None) -> list[dict[str, str]]:
    """The report's figures as inline SVG with captions, in reading order (skipping those the
    available data cannot draw)."""
    names = plots.residual_names(result)
    # the noise floor is per sensor axis; without angles the residual columns are no axes
    noise = result.get("noise_floor_lsb") if result.get("model") != "attitude_free" else None
    locate = result.get("locate") or {}
    out: list[tuple[str, Any, str]] = [
        ("fit", plots.fit_summary_figure(result),
         "Residual rms per sensor axis before and after the fitted effects, in-sample and held out (each sample "
         "predicted by a fit that never saw it), with the noise floor estimated from the static holds."),
    ]
    if series is not None and len(series.get("t", [])):
        windows = [seg for f in result.get("findings") or [] if isinstance(f, Mapping)
                   for seg in ((f.get("model") or {}).get("segments") or [])]
        out.append(("time", plots.residual_time_figure(series, names, windows),
                    "Residuals against time, coloured by step: left with the nominal model, right with the fitted "
                    "effects. A drift, a jump or one bad step shows here; the shaded spans are the time windows "
                    "of the findings (when a discovered departure was present)."))
        out.append(("angles", plots.residual_angle_figure(series, names),
                    "Residuals against each table angle: structure that repeats with an angle (a harmonic) belongs "
                    "to something fixed in a table stage or to the table's geometry."))
    out.append(("by_step", plots.by_step_figure(locate.get("by_step"), noise, names),
                "Residual rms of each step with the nominal model; dashed lines are the noise floor."))
    out.append(("harmonics", plots.harmonics_figure(locate.get("harmonics"), names),
                "Harmonic amplitudes of the residual against heading and each gimbal angle."))
    if series is not None and len(series.get("t", [])):
        out.append(("heldout", plots.heldout_figure(series, names),
                    "Held-out predictions: each sample predicted by a model fitted without that sample's fold."))
    figs = []
    for key, fig, caption in out:
        if fig is None:
            continue
        figs.append({"key": key, "svg": plots.svg(fig, f"figure-{key}", caption), "caption": caption})
    return figs


def analysis_html(result: Mapping[str, Any], series: Mapping[str, Any] | None, title: str) -> str:
    """The analysis report as one self-contained HTML page (see the module docstring)."""
    held = result.get("heldout") or {}
    he = result.get("heading_error_deg") or {}
    attitude_free = result.get("model") == "attitude_free"
    # noise is per sensor axis for both models; the attitude-free residual is the field magnitude's alone
    names = plots.residual_names(result)
    fit_cells = (lambda v: [f"{x} ({n})" if n else "" for x, n in zip(per_axis(v), names)]) if attitude_free else per_axis
    summary = [
        ("noise floor (LSB, 1σ per sample)", per_axis(result.get("noise_floor_lsb"), 3)),
        ("noise lag-1 autocorrelation", per_axis(result.get("noise_ar1"), 3)),
        ("residual rms before (LSB, in-sample)", fit_cells(result.get("residual_rms_before_lsb"))),
        ("residual rms after (LSB, in-sample)", fit_cells(result.get("residual_rms_after_lsb"))),
        ("held-out rms before (LSB)", fit_cells(held.get("rms_before_lsb"))),
        ("held-out rms after (LSB)", fit_cells(held.get("rms_after_lsb"))),
    ]
    findings = []
    for rank, f in enumerate(result.get("findings") or [], start=1):
        extra = {k: v for k, v in f.items() if k not in FINDING_COLUMNS}
        findings.append({
            "rank": rank, "effect": str(f.get("effect", "?")), "statistic": num(f.get("statistic")), "df": num(f.get("df")),
            "p_value": num(f.get("p_value"), 3), "p_adjusted": num(f.get("p_adjusted"), 3),
            "parameters": parameter_cells(f), "heading_impact": num(f.get("heading_impact_deg"), 3),
            "where": tree(f.get("where")), "explanation": text(f.get("explanation") or ""), "model": model_text(f),
            "confusable_with": ", ".join(str(x) for x in f.get("confusable_with") or []) or "-",
            "separating_experiment": text(f.get("separating_experiment") or "") or "-",
            "other": tree(extra) if extra else None,
        })
    test_rows = [t for t in result.get("tests") or [] if isinstance(t, Mapping)]
    test_extra: list[str] = []  # any key beyond the contract's (e.g. the selection round), in first-seen order
    for t in test_rows:
        test_extra += [str(k) for k in t if k not in TEST_COLUMNS and str(k) not in test_extra]
    tests = [{"effect": str(t.get("effect")), "variant": text(t.get("variant")), "statistic": num(t.get("statistic")),
              "df": num(t.get("df")), "p_value": num(t.get("p_value"), 3), "p_adjusted": num(t.get("p_adjusted"), 3),
              "selected": bool(t.get("selected")), "extra": [text(t.get(k)) for k in test_extra]} for t in test_rows]
    locate = result.get("locate") or {}
    known = {"verdict", "model", "samples", "duration_s", "alpha", "noise_floor_lsb", "noise_ar1",
             "residual_rms_before_lsb", "residual_rms_after_lsb", "heldout", "heading_error_deg", "findings", "tests",
             "untestable", "locate", "notes", "summary"}
    other = {k: v for k, v in result.items() if k not in known}
    return _env.get_template("analysis_report.html").render(
        title=title, r=result, summary_sentence=text(result.get("summary") or ""), verdict=str(result.get("verdict", "?")), model=str(result.get("model", "?")),
        samples=num(result.get("samples")), duration=num(result.get("duration_s"), 5), alpha=num(result.get("alpha"), 3),
        axes=("m_x", "m_y", "m_z"), summary=summary, heldout_scheme=text(held.get("scheme") or "not given"),
        improvement=num(held.get("improvement_pct"), 3), heading_before=num(he.get("before"), 3),
        heading_after=num(he.get("after"), 3), findings=findings, tests=tests, test_extra=test_extra,
        untestable=[(str(u.get("effect")), text(u.get("reason"))) for u in result.get("untestable") or []
                    if isinstance(u, Mapping)],
        notes=[text(n) for n in result.get("notes") or []],
        locate=[(k, tree(v)) for k, v in locate.items() if k not in ("by_step", "harmonics")]
        + [(k, tree(locate[k])) for k in ("by_step", "harmonics") if k in locate],
        other=tree(other) if other else None, figures=analysis_figures(result, series),
        has_series=series is not None)


__all__ = ["analysis_html", "analysis_figures", "model_text", "num", "text", "tree"]
