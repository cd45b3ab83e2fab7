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

import numpy as np
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


def _same(a: Any, b: Any) -> bool:
    """Two lists of the same numbers (to rounding; None and NaN alike)."""
    if not isinstance(a, (list, tuple)) or not isinstance(b, (list, tuple)):
        return False
    try:
        x, y = np.array(a, dtype=float), np.array(b, dtype=float)
    except (TypeError, ValueError):
        return False
    return x.shape == y.shape and bool(np.allclose(x, y, rtol=1e-9, atol=1e-12, equal_nan=True))


def shown_parameters(finding: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """A finding's parameters and sigma as shown to a person. A discovered block keeps its raw
    coefficients for programs ("values", named by "labels"): shown once, under their names, and not at
    all where a named parameter repeats them (an offset's "offset_lsb")."""
    params = dict(finding.get("parameters") or {})
    sigma = dict(finding.get("sigma") or {}) if isinstance(finding.get("sigma"), Mapping) else {}
    labels = params.pop("labels", None)
    if "values" in params and labels is not None:
        values, sd = params.pop("values"), sigma.pop("values", None)
        if not any(_same(values, v) for v in params.values()):
            names = [str(x) for x in labels] if isinstance(labels, (list, tuple)) else [str(labels)]
            key = f"values ({', '.join(names)})" if len(names) <= 6 else "values"
            params = {key: values, **params}
            sigma[key] = sd
    return params, sigma


def parameter_rows(finding: Mapping[str, Any]) -> list[tuple[str, str]]:
    """A finding's parameters as (name, "value ± sigma") rows."""
    if not isinstance(finding.get("parameters") or {}, Mapping):
        return [("", text(finding.get("parameters")))]
    params, sigma = shown_parameters(finding)
    return [(str(k), with_sigma(v, sigma.get(k))) for k, v in params.items()]


def parameter_cells(finding: Mapping[str, Any]) -> list[tuple[str, list[str]]]:
    """A finding's parameters for the page: (name, one "value ± sigma" string per element)."""
    if not isinstance(finding.get("parameters") or {}, Mapping):
        return [("", [text(finding.get("parameters"))])]
    params, sigma = shown_parameters(finding)
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


# --------------------------------------------------------------------------- where the mismatch lives

def _axis_head(unit: str) -> list[str]:
    return [f"{a} ({unit})" for a in ("m_x", "m_y", "m_z")]


#: Known ``locate`` parts in reading order: (heading, what the part tells the reader).
LOCATE_PARTS: dict[str, tuple[str, str]] = {
    "by_axis": ("By sensor axis",
                "Which sensor axis carries the mismatch: the residual rms of the nominal model on each axis."),
    "by_step": ("By step",
                "Which step of the procedure carries the mismatch: residual rms and mean of each step with the nominal "
                "model; one step far above the others points to that step."),
    "harmonics": ("Against the table angles",
                  "How much of the residual repeats 1, 2, 3 or 4 times per turn of each table angle: structure that "
                  "repeats with an angle belongs to something fixed in a table stage or to the table's geometry."),
    "time": ("In time",
             "Whether the mismatch changes during the run: its linear trend, and the difference between two visits "
             "to the same pose."),
    "direction": ("By direction of turning",
                  "Mean residual while each angle turns one way and the other: a difference between the two rows "
                  "points to a lag or hysteresis that depends on the direction of turning."),
    "frame": ("By frame",
              "Tests of structure anchored in each frame: a small p says the residual holds structure of that kind."),
    "whiteness": ("Whiteness of the residual",
                  "Whether the whitened residual is still correlated from sample to sample (Ljung-Box test): a small "
                  "p says structure is left that the noise model does not explain."),
    "witness": ("Further structure",
                "Tests of the residual against further structure (higher harmonics of each angle, a slow change in "
                "time, other recorded quantities): a small p says the residual holds that structure."),
}

_ANGLE_NAMES = {"psi_t": "psi_t (ψ)", "theta_t": "theta_t (θ)", "phi_t": "phi_t (φ)",
                "psi": "psi (ψ)", "theta": "theta (θ)", "phi": "phi (φ)"}


def _table(head: list[str], rows: list[list[str]], title: str | None = None) -> dict[str, Any]:
    """One labelled table for the template: its first column holds the row labels."""
    return {"title": title, "head": head, "rows": rows}


def _is_vector(v: Any) -> bool:
    return isinstance(v, (list, tuple)) and not any(isinstance(x, (list, tuple, Mapping)) for x in v)


def _test_row(label: str, v: Mapping[str, Any]) -> list[str]:
    return [label, num(v.get("statistic")), num(v.get("df")), num(v.get("p_value"), 3)]


def _is_test(v: Any) -> bool:
    return isinstance(v, Mapping) and any(k in v for k in ("statistic", "df", "p_value"))


def _as_came(key: str, title: str, v: Any) -> dict[str, Any]:
    """A ``locate`` part shown as it came (the generic tree), without a caption that might not fit."""
    return {"key": key, "title": title, "caption": "", "tables": [], "sentences": [], "empty": None, "extra": tree(v)}


def _locate_part(key: str, v: Any) -> dict[str, Any]:
    """One part of ``result["locate"]`` as {key, title, caption, tables, sentences, empty, extra}: the
    known shapes (physics.discrepancy.analysis.locate) as labelled tables, anything else (other keys,
    other shapes, e.g. the attitude-free model's) under ``extra`` as the generic tree."""
    title, caption = LOCATE_PARTS.get(key, (key.replace("_", " "), ""))
    part: dict[str, Any] = {"key": key, "title": title, "caption": caption, "tables": [], "sentences": [],
                            "empty": None, "extra": None}
    rest: dict[str, Any] = {}
    try:
        if key == "by_axis" and isinstance(v, Mapping):
            rest = {k: x for k, x in v.items() if k not in ("rms_lsb", "dominant")}
            if "rms_lsb" in v:
                part["tables"].append(_table(["", *_axis_head("LSB")],
                                             [["residual rms, nominal model", *per_axis(v.get("rms_lsb"))]]))
            dom = v.get("dominant")
            if isinstance(dom, str) and dom in ("x", "y", "z"):
                part["sentences"].append(f"Largest against its noise floor: m_{dom}.")
            elif dom is not None:
                rest["dominant"] = dom
        elif key == "by_step" and isinstance(v, (list, tuple)) and all(isinstance(x, Mapping) for x in v):
            if not v:
                part["empty"] = "No steps recorded."
            else:
                means = any("mean_lsb" in x for x in v)
                others: list[str] = []
                for x in v:
                    others += [str(k) for k in x if k not in ("step", "samples", "rms_lsb", "mean_lsb")
                               and str(k) not in others]
                head = ["step", "samples", *[f"rms {h}" for h in _axis_head("LSB")]] \
                    + ([f"mean {h}" for h in _axis_head("LSB")] if means else []) + others
                rows = [[text(x.get("step")) if x.get("step") is not None else "-", num(x.get("samples")),
                         *per_axis(x.get("rms_lsb"))] + (per_axis(x.get("mean_lsb")) if means else [])
                        + [text(x.get(k)) for k in others] for x in v]
                part["tables"].append(_table(head, rows))
        elif key == "harmonics" and isinstance(v, Mapping):
            for name, h in v.items():
                amp = h.get("amplitude_lsb") if isinstance(h, Mapping) else None
                if not isinstance(amp, (list, tuple)):
                    rest[str(name)] = h
                    continue
                orders = h.get("orders") if isinstance(h.get("orders"), (list, tuple)) else []
                rows = [[f"{num(orders[i]) if i < len(orders) else i + 1} × per turn", *per_axis(a, 3)]
                        for i, a in enumerate(amp)]
                part["tables"].append(_table(["order", *[f"amplitude {x}" for x in _axis_head("LSB")]], rows,
                                             f"against {_ANGLE_NAMES.get(str(name), str(name))}"))
                extra = {k: x for k, x in h.items() if k not in ("orders", "amplitude_lsb")}
                if extra:
                    rest[str(name)] = extra
            if not v:
                part["empty"] = "No table angle turned by 30 degrees or more: no harmonics to show."
        elif key == "time" and isinstance(v, Mapping):
            rest = {k: x for k, x in v.items() if k not in ("trend_lsb_per_min", "repeated_pose", "change_point_t_s")}
            rows = []
            if "trend_lsb_per_min" in v:
                rows.append(["linear trend over the run (LSB/min)", *per_axis(v.get("trend_lsb_per_min"), 3)])
            rp = v.get("repeated_pose")
            if isinstance(rp, Mapping):
                rows.append(["same pose again: last minus first visit (LSB)", *per_axis(rp.get("difference_lsb"), 3)])
                ang = rp.get("angles")
                pose = ", ".join(f"{n} {num(a, 4)}" for n, a in zip(("ψ", "θ", "φ"), ang)) if _is_vector(ang) else text(ang)
                part["sentences"].append(f"Repeated pose: {pose} deg, visited again after {num(rp.get('dt_s'), 4)} s.")
            elif rp is not None:
                rest["repeated_pose"] = rp
            if rows:
                part["tables"].append(_table(["", "m_x", "m_y", "m_z"], rows))
            if v.get("change_point_t_s") is not None:
                part["sentences"].append(f"Most likely change point of the hold means: t = {num(v.get('change_point_t_s'), 4)} s "
                                         "(where the mismatch shifts, if it does).")
        elif key == "direction" and isinstance(v, Mapping):
            rows = []
            for name, d in v.items():
                if not isinstance(d, Mapping) or not ("positive_mean_lsb" in d or "negative_mean_lsb" in d):
                    rest[str(name)] = d
                    continue
                speeds = d.get("speeds_dps")
                sp = ", ".join(num(s, 3) for s in speeds) if _is_vector(speeds) and speeds else text(speeds) if speeds else "-"
                label = _ANGLE_NAMES.get(str(name), str(name))
                rows.append([label, "turning +", *per_axis(d.get("positive_mean_lsb"), 3), sp])
                rows.append(["", "turning −", *per_axis(d.get("negative_mean_lsb"), 3), ""])
                extra = {k: x for k, x in d.items() if k not in ("positive_mean_lsb", "negative_mean_lsb", "speeds_dps")}
                if extra:
                    rest[str(name)] = extra
            if rows:
                part["tables"].append(_table(["angle", "direction", *[f"mean {h}" for h in _axis_head("LSB")],
                                              "speeds (deg/s)"], rows))
            if not v:
                part["empty"] = "No turns in both directions were recorded: the direction of turning cannot be compared."
        elif key in ("frame", "witness") and isinstance(v, Mapping):
            rows = []
            for name, t in v.items():
                if _is_test(t):
                    rows.append(_test_row(str(name), t))
                    extra = {k: x for k, x in t.items() if k not in ("statistic", "df", "p_value")}
                    if extra:
                        rest[str(name)] = extra
                else:
                    rest[str(name)] = t
            if rows:
                part["tables"].append(_table(["the residual is…" if key == "frame" else "witness", "statistic", "df",
                                              "p"], rows))
            if not v:
                part["empty"] = "No frame could be tested." if key == "frame" else "No witness channel was tested."
        elif key == "whiteness" and isinstance(v, Mapping) and isinstance(v.get("per_axis"), (list, tuple)) \
                and all(isinstance(x, Mapping) for x in v["per_axis"]):
            rest = {k: x for k, x in v.items() if k != "per_axis"}
            pa = list(v["per_axis"])[:3]
            lags = {x.get("lags") for x in pa if x.get("lags") is not None}
            q_label = "Ljung-Box Q" + (f" ({num(next(iter(lags)))} lags)" if len(lags) == 1 else "")
            rows = [[q_label, *per_axis([x.get("ljung_box_q") for x in pa])],
                    ["p", *per_axis([x.get("p_value") for x in pa], 3)]]
            if len(lags) > 1:
                rows.append(["lags", *per_axis([x.get("lags") for x in pa])])
            part["tables"].append(_table(["", "m_x", "m_y", "m_z"], rows))
        else:  # a key or a shape this page does not know: as it came
            return _as_came(key, title, v)
    except Exception:  # an odd value: never lose the page for it, show it as it came
        return _as_came(key, title, v)
    if rest:
        part["extra"] = tree(rest)
    elif not part["tables"] and not part["sentences"] and part["empty"] is None:
        part["extra"] = tree(v)
    if not part["tables"] and not part["sentences"] and part["empty"] is None:
        part["caption"] = ""  # nothing of it understood: no caption that might not fit
    return part


def locate_parts(locate: Any, generic: bool = False) -> list[dict[str, Any]]:
    """``result["locate"]`` for the page: the known parts in reading order, then any other key.
    ``generic``: every part as it came (the attitude-free model's locate has the same keys with other
    contents: magnitude residuals, a spectrum, time bins)."""
    if not isinstance(locate, Mapping):
        return [_locate_part("locate", locate)] if locate not in (None, {}, []) else []
    keys = [k for k in LOCATE_PARTS if k in locate] + [k for k in locate if k not in LOCATE_PARTS]
    if generic:
        return [_as_came(str(k), str(k).replace("_", " "), locate[k]) for k in keys]
    return [_locate_part(str(k), locate[k]) for k in keys]


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
        # in the recording's own t, to 0.1 s (an epoch-based t reads 1700000018.8, not 1.7e+09)
        t = lambda x: f"{x:.1f}" if isinstance(x, (int, float)) else num(x)  # noqa: E731
        parts.append("during " + ", ".join(f"{t(a)}-{t(b)} s" for a, b in segs))
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


def analysis_html(result: Mapping[str, Any], series: Mapping[str, Any] | None, title: str,
                  run_url: str | None = None) -> str:
    """The analysis report as one self-contained HTML page (see the module docstring); ``run_url``, when
    the analysis belongs to a stored run, links the page back to that run's page."""
    held = result.get("heldout") or {}
    he = result.get("heading_error_deg") or {}
    attitude_free = result.get("model") == "attitude_free"
    # noise is per sensor axis for both models; the attitude-free residual is the field magnitude's alone
    names = plots.residual_names(result)
    fit_cells = (lambda v: [f"{x} ({n})" if n else "" for x, n in zip(per_axis(v), names)]) if attitude_free else per_axis
    summary = [
        ("noise floor (LSB, 1σ per sample)", per_axis(result.get("noise_floor_lsb"), 3)),
        ("noise slow part: AR(1) phi", per_axis(result.get("noise_ar1"), 3)),
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
    locate = result.get("locate")
    known = {"verdict", "model", "samples", "duration_s", "alpha", "noise_floor_lsb", "noise_ar1",
             "residual_rms_before_lsb", "residual_rms_after_lsb", "heldout", "heading_error_deg", "findings", "tests",
             "untestable", "locate", "notes", "summary"}
    other = {k: v for k, v in result.items() if k not in known}
    return _env.get_template("analysis_report.html").render(
        title=title, r=result, summary_sentence=text(result.get("summary") or ""), verdict=str(result.get("verdict", "?")), model=str(result.get("model", "?")),
        samples=num(result.get("samples")), duration=num(result.get("duration_s"), 5), alpha=num(result.get("alpha"), 3),
        axes=("m_x", "m_y", "m_z"), summary=summary, heldout_scheme=text(held.get("scheme") or "not given"),
        improvement=num(held.get("improvement_pct"), 3), heading_before=num(he.get("before"), 3),
        heading_after=num(he.get("after"), 3), heading_rms_before=num(he.get("rms_before"), 3),
        heading_rms_after=num(he.get("rms_after"), 3),
        heading_noise=None if he.get("noise_rms") is None else num(he.get("noise_rms"), 2), findings=findings, tests=tests, test_extra=test_extra,
        untestable=[(str(u.get("effect")), text(u.get("reason"))) for u in result.get("untestable") or []
                    if isinstance(u, Mapping)],
        notes=[text(n) for n in result.get("notes") or []],
        locate=locate_parts(locate, generic=attitude_free), run_url=run_url,
        other=tree(other) if other else None, figures=analysis_figures(result, series),
        has_series=series is not None)


__all__ = ["analysis_html", "analysis_figures", "locate_parts", "model_text", "num", "text", "tree"]
