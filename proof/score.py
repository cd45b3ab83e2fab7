"""The blind proof's scorer and report: each analysis against the truth of its case.

Catalogue cases (issue 6) are scored on detection against lambda, false alarms on nulls, naming,
confusion, parameter recovery and held-out RMS (:func:`score`). Open-world cases (issue 12) are scored
on whether the analyser says where the departure lives and models it away (:func:`score_open`): the
right frame, the right time windows or input, the residual down to the noise floor and the level
heading error lower after than before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.stats import beta, chi2, ncx2

from proof.concealments import OPEN_KINDS
from proof.generator import EFFECTS, LARGE_NC_RANGE, NC_RANGE, Case

#: Bins of the detection and success tables (lower edges inclusive; the first bin also takes values a
#: little under 3, the last a little over 300).
NC_BINS = ((3.0, 6.0), (6.0, 14.0), (14.0, 35.0), (35.0, 100.0), (100.0, 300.0))

#: Parameters whose recovery is scored (vectors compared as a whole; the others have ambiguities:
#: soft iron's isotropic part is the unit's k, a gradient trades against its offset, mains against its phase).
RECOVERED = {
    "stage_hard_iron": ("m",), "field_drift": ("rate_per_s",), "temperature_drift": ("bias_per_c",),
    "nonlinearity": ("c3",), "hysteresis": ("offset",), "time_lag": ("lag_s",),
    "table_axis_error": ("nonperp_deg", "encoder_zero_deg"),
}

#: The issues' targets, printed next to each figure (open_*: issue 12's open-world success criteria).
TARGETS = {"detect_at_10": 0.50, "detect_at_25": 0.90, "false_alarm": 0.01, "min_nulls": 300,
           "right_first": 0.90, "right_set": 0.98, "pairs_both": 0.80, "heldout": 1.05, "seconds": 30.0,
           "coverage": 0.95, "open_success": 0.90, "open_nc": 25.0, "open_residual": 1.3, "open_edge": 0.05}

NOT_DETECTED = "(none)"


@dataclass
class Outcome:
    """What the scorer needs of one analysis."""

    result: dict[str, Any] | None  # Analysis.result (None when the analyser raised)
    heldout_ratio: float | None = None  # RMS(rec.mag - heldout_pred_after) / RMS(rec.mag - clean.mag)
    seconds: float | None = None
    error: str | None = None
    heldout_before: float | None = None  # the same with heldout_pred_before (the nominal model)
    #: open world: the level heading error (RMS) of the nominal model fitted to the same recording without
    #: its effect (the same noise), what a perfect model of the effect could bring it down to
    heading_free: float | None = None


def clopper_pearson_upper(k: int, n: int, confidence: float = 0.95) -> float:
    """One-sided upper confidence bound of a binomial rate with k successes in n trials."""
    if n == 0:
        return 1.0
    return 1.0 if k >= n else float(beta.ppf(confidence, k + 1, n - k))


def logistic_fit(nc: Sequence[float], detected: Sequence[bool], at: Sequence[float] = (10.0, 25.0),
                 ridge: float = 0.01) -> dict[str, float] | None:
    """Detection probability at non-centralities ``at`` from a logistic fit against log(lambda).

    A weak ridge keeps the fit finite when the classes separate (all detected above some size).
    None with fewer than 3 cases.
    """
    x = np.log(np.asarray(nc, dtype=float) / 20.0)
    y = np.asarray(detected, dtype=float)
    if len(x) < 3:
        return None

    def nll(b: np.ndarray) -> tuple[float, np.ndarray]:
        z = b[0] + b[1] * x
        p = 1.0 / (1.0 + np.exp(-z))
        f = float(np.sum(np.logaddexp(0.0, z) - y * z) + 0.5 * ridge * (b @ b))
        g = np.array([np.sum(p - y), np.sum((p - y) * x)]) + ridge * b
        return f, g

    b = minimize(nll, np.zeros(2), jac=True, method="BFGS").x
    return {f"{a:g}": float(1.0 / (1.0 + np.exp(-(b[0] + b[1] * np.log(a / 20.0))))) for a in at}


def _outcome(a: Outcome | dict[str, Any]) -> Outcome:
    return a if isinstance(a, Outcome) else Outcome(a)  # a bare Analysis.result (hand-made analyses in tests)


def _named(finding: dict[str, Any]) -> set[str]:
    return {finding.get("effect", "")} | set(finding.get("confusable_with", []) or [])


def _bin(nc: float) -> int:
    for i, (lo, hi) in enumerate(NC_BINS):
        if nc < hi:
            return i
    return len(NC_BINS) - 1


def _flat(params: dict[str, Any], names: Sequence[str]) -> np.ndarray | None:
    try:
        return np.concatenate([np.ravel(np.asarray(params[k], dtype=float)) for k in names])
    except (KeyError, TypeError, ValueError):
        return None


def _pct(xs: Sequence[float], q: float) -> float | None:
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return float(np.percentile(xs, q)) if xs else None


def score(cases: Sequence[Case], analyses: Sequence[Outcome | dict[str, Any]]) -> dict[str, Any]:
    """Score analyses against the truth of their cases (same order).

    An analysis is an :class:`Outcome` or a bare ``Analysis.result`` dict. Detected means verdict
    "discrepancy". Figures (all JSON-safe):

    - ``detection[effect]``: per non-centrality bin [detected, cases] of the single-effect cases, and
      the logistic-fit rate at lambda 10 and 25;
    - ``false_alarms``: nulls, false alarms, rate, one-sided 95 % Clopper-Pearson upper bound;
    - ``confusion[true][first finding]`` over single-effect cases and nulls (``(none)`` when not detected);
    - ``naming``: among detected single-effect cases, "right" when the true effect is the first
      finding or in its confusable_with; split into identifiable (first finding has no
      confusable_with: right name first) and confusable (the true effect is in the named set);
    - ``pairs``: both effects named (each is some finding's effect or in its confusable_with);
    - ``recovery[effect]``: for the finding naming the true effect (same stage for stage effects),
      median |est - true| / |true| of the :data:`RECOVERED` vector and the coverage of its 1.96-sigma
      intervals (fraction of components);
    - ``heldout``: RMS(rec - held-out prediction after) / RMS(rec - clean truth), median and 90th
      percentile, for effect cases, detected effect cases and nulls;
    - ``seconds``: per analysis, median and max; ``errors``: analyses that raised;
    - ``open``: the open-world cases (kinds of proof.concealments.OPEN_KINDS), scored by
      :func:`score_open`; every figure above leaves them out except ``errors``.
    """
    if len(cases) != len(analyses):
        raise ValueError(f"score: {len(cases)} cases but {len(analyses)} analyses")
    is_open = [c.kind in OPEN_KINDS for c in cases]
    open_part = score_open([c for c, o in zip(cases, is_open) if o], [a for a, o in zip(analyses, is_open) if o])
    cases = [c for c, o in zip(cases, is_open) if not o]
    analyses = [a for a, o in zip(analyses, is_open) if not o]
    det: dict[str, list[tuple[float, bool]]] = {e: [] for e in EFFECTS}
    confusion: dict[str, dict[str, int]] = {}
    naming: dict[str, dict[str, int]] = {e: {"detected": 0, "right": 0, "identifiable": 0, "identifiable_right": 0,
                                             "confusable": 0, "confusable_right": 0} for e in EFFECTS}
    pairs = {"cases": 0, "both_named": 0, "detected": 0}
    pair_nc: list[float] = []
    recovery: dict[str, dict[str, Any]] = {e: {"cases": 0, "rel_err": [], "covered": 0, "components": 0,
                                               "wrong_stage": 0} for e in RECOVERED}
    nulls = {"cases": 0, "false_alarms": 0}
    by_generator: dict[str, dict[str, int]] = {}  # nulls of the catalogue's and of the open world's draw
    held: dict[str, list[float]] = {"effects": [], "detected": [], "nulls": []}
    held_before: dict[str, list[float]] = {"effects": [], "detected": [], "nulls": []}
    removed: list[float] = []  # share of the held-out excess over the truth that the fitted effects remove
    held_by_effect: dict[str, list[float]] = {e: [] for e in EFFECTS}
    seconds: list[float] = []
    errors: list[dict[str, Any]] = []
    nc_floor: list[float] = []
    design: dict[str, Any] = {"df": {}, "tests": [], "alpha": None}  # round-1 tests, for the ideal power

    for case, a in zip(cases, analyses):
        o = _outcome(a)
        result, ratio, secs, error, before = o.result, o.heldout_ratio, o.seconds, o.error, o.heldout_before
        round1 = [t for t in (result or {}).get("tests", []) or [] if t.get("round") == 1 and (t.get("df") or 0) > 0]
        if round1:
            design["tests"].append(len(round1))
            design["alpha"] = (result or {}).get("alpha", design["alpha"])
            for t in round1:
                if not t.get("generic") and t.get("effect") in EFFECTS:
                    design["df"][t["effect"]] = max(design["df"].get(t["effect"], 0), int(t["df"]))
        if secs is not None:
            seconds.append(secs)
        if error is not None or result is None:
            errors.append({"kind": case.kind, "seed": case.seed, "error": error})
        result = result or {}
        detected = result.get("verdict") == "discrepancy"
        findings = list(result.get("findings", []) or [])
        first = findings[0].get("effect", NOT_DETECTED) if detected and findings else NOT_DETECTED
        nc_floor.append(case.nc_floor)
        if case.kind == "null":
            nulls["cases"] += 1
            nulls["false_alarms"] += int(detected)
            g = by_generator.setdefault(case.generator, {"nulls": 0, "false_alarms": 0})
            g["nulls"] += 1
            g["false_alarms"] += int(detected)
            confusion.setdefault("null", {}).setdefault(first, 0)
            confusion["null"][first] += 1
            for store, x in ((held, ratio), (held_before, before)):
                if x is not None:
                    store["nulls"].append(x)
            continue
        for store, x in ((held, ratio), (held_before, before)):
            if x is not None:
                store["effects"].append(x)
                if detected:
                    store["detected"].append(x)
        if detected and ratio is not None and before is not None and before > 1.0:
            removed.append(1.0 - (ratio ** 2 - 1.0) / (before ** 2 - 1.0))
        if len(case.effects) == 2:
            pairs["cases"] += 1
            pairs["detected"] += int(detected)
            pair_nc += list(case.nc.values())
            named = set().union(*(_named(f) for f in findings)) if findings else set()
            pairs["both_named"] += int(detected and set(case.effects) <= named)
            continue
        (true,) = case.effects
        det[true].append((case.nc[true], detected))
        confusion.setdefault(true, {}).setdefault(first, 0)
        confusion[true][first] += 1
        if ratio is not None:
            held_by_effect[true].append(ratio)
        if detected and findings:
            nm = naming[true]
            f0 = findings[0]
            right = true in _named(f0)
            nm["detected"] += 1
            nm["right"] += int(right)
            if f0.get("confusable_with"):
                nm["confusable"] += 1
                nm["confusable_right"] += int(right)
            else:
                nm["identifiable"] += 1
                nm["identifiable_right"] += int(f0.get("effect") == true)
        if true in RECOVERED:
            match = [f for f in findings if f.get("effect") == true]
            if not match:
                continue
            f, truth = match[0], case.params[true]
            est_p, sig_p = f.get("parameters", {}) or {}, f.get("sigma", {}) or {}
            rec = recovery[true]
            if "stage" in truth and est_p.get("stage") not in (None, truth["stage"]):
                rec["wrong_stage"] += 1
                continue
            names = RECOVERED[true]
            est, tru, sig = _flat(est_p, names), _flat(truth, names), _flat(sig_p, names)
            if est is None or tru is None or est.shape != tru.shape:
                continue
            # a component the recording cannot determine (the nominal model absorbs it) comes with a
            # null sigma: it is neither recovered nor covered, and is counted apart
            ok = np.isfinite(sig) if sig is not None and sig.shape == est.shape else np.ones(est.shape, bool)
            rec["cases"] += 1
            rec["undetermined"] = rec.get("undetermined", 0) + int((~ok).sum())
            rec["rel_err"].append(float(np.linalg.norm((est - tru)[ok]) / max(np.linalg.norm(tru[ok]), 1e-300)))
            if sig is not None and sig.shape == est.shape:
                rec["components"] += int(ok.sum())
                rec["covered"] += int(np.sum(np.abs(est - tru)[ok] <= 1.96 * sig[ok]))

    # the best any single test could do: one chi-square test of the effect's own df at the family's
    # corrected level (what the detection targets ask of a test that also has to tell effects apart)
    m = float(np.median(design["tests"])) if design["tests"] else None
    ideal: dict[str, dict[str, float]] = {}
    if m and design["alpha"]:
        for e, df in design["df"].items():
            c = chi2.isf(design["alpha"] / m, df)
            ideal[e] = {"df": df, "10": float(ncx2.sf(c, df, 10.0)), "25": float(ncx2.sf(c, df, 25.0))}
    detection = {}
    for e, rows in det.items():
        bins = [[0, 0] for _ in NC_BINS]
        for nc, d in rows:
            b = bins[_bin(nc)]
            b[0] += int(d)
            b[1] += 1
        fitted = logistic_fit([r[0] for r in rows], [r[1] for r in rows]) if rows else None
        detection[e] = {"bins": bins, "cases": len(rows), "detected": sum(d for _, d in rows),
                        "rate_at_10": fitted["10"] if fitted else None, "rate_at_25": fitted["25"] if fitted else None,
                        "heldout_median": _pct(held_by_effect[e], 50), "ideal": ideal.get(e)}
    k, n = nulls["false_alarms"], nulls["cases"]
    false_alarms = {"nulls": n, "false_alarms": k, "rate": k / n if n else None,
                    "upper95": clopper_pearson_upper(k, n) if n else None,
                    "nc_floor_median": _pct([c.nc_floor for c in cases if c.kind == "null"], 50),
                    "nc_floor_max": _pct([c.nc_floor for c in cases if c.kind == "null"], 100),
                    "by_generator": by_generator}

    def rate(a: int, b: int) -> float | None:
        return a / b if b else None

    tot = {k2: sum(v[k2] for v in naming.values()) for k2 in next(iter(naming.values()))}
    naming_out = {"by_effect": naming, "detected": tot["detected"], "right": tot["right"],
                  "right_rate": rate(tot["right"], tot["detected"]),
                  "identifiable": tot["identifiable"], "right_first_rate": rate(tot["identifiable_right"], tot["identifiable"]),
                  "confusable": tot["confusable"], "right_set_rate": rate(tot["confusable_right"], tot["confusable"])}
    recovery_out = {e: {"cases": r["cases"], "rel_err_median": _pct(r["rel_err"], 50),
                        "coverage": rate(r["covered"], r["components"]), "components": r["components"],
                        "wrong_stage": r["wrong_stage"]} for e, r in recovery.items()}
    return {
        "detection": detection,
        "false_alarms": false_alarms,
        "confusion": confusion,
        "naming": naming_out,
        "pairs": {**pairs, "both_named_rate": rate(pairs["both_named"], pairs["cases"]),
                  "nc_min": min(pair_nc, default=None), "nc_max": max(pair_nc, default=None)},
        "recovery": recovery_out,
        "heldout": {k2: {"cases": len(v), "median": _pct(v, 50), "p90": _pct(v, 90),
                         "before_median": _pct(held_before[k2], 50), "before_p90": _pct(held_before[k2], 90)}
                    for k2, v in held.items()},
        "heldout_excess_removed": {"cases": len(removed), "median": _pct(removed, 50), "p10": _pct(removed, 10)},
        "seconds": {"analyses": len(seconds), "median": _pct(seconds, 50), "max": _pct(seconds, 100)},
        "errors": errors + open_part["errors"],
        "open": open_part,
    }


# --------------------------------------------------------------------------------------------------
# Open world (issue 12)
# --------------------------------------------------------------------------------------------------

#: Frames that are one and the same for the scorer: the unit's own frame, called "sensor" by the
#: concealments and "platform" (the inner stage it is fixed to) by the analyser when it cannot tell them apart.
SAME_FRAME = {"platform": "sensor"}

#: Why an open-world case failed, in the order the report lists them.
OPEN_FAILURES = ("frame", "where", "residual", "heading")


def _frame(name: Any) -> Any:
    return SAME_FRAME.get(name, name)


def merge_segments(segments: Sequence[Sequence[float]], gap: float = 0.0) -> list[list[float]]:
    """Union of time segments ``[[t0, t1], ...]``, joining two that overlap or lie at most ``gap`` apart
    (a segment a finding split at an unrecorded move is one window)."""
    rows = sorted([float(a), float(b)] for a, b in segments)
    out: list[list[float]] = []
    for a, b in rows:
        if out and a <= out[-1][1] + gap:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def residual_ratio(result: dict[str, Any]) -> float | None:
    """Largest ratio over the axes of ``residual_rms_after_lsb`` to ``noise_floor_lsb`` (None if either is
    missing or malformed). The attitude-free model's columns are the magnitude and the dip
    (``residual_columns``): only the magnitude compares with the magnetometer's floor (the dip's noise is the
    accelerometer's as well)."""
    try:
        after = np.array([np.nan if x is None else x for x in result["residual_rms_after_lsb"]], dtype=float)
        floor = np.asarray(result["noise_floor_lsb"], dtype=float)
        r = after / floor
    except (KeyError, TypeError, ValueError):
        return None
    named = result.get("residual_columns")
    r = r[[c == "magnitude" for c in named]] if named else r[~np.isnan(after)]
    return float(np.max(r)) if r.size and np.all(np.isfinite(r)) else None


def _heading(result: dict[str, Any], which: str = "rms") -> tuple[float | None, float | None]:
    """The level heading error before and after: its RMS over the level holds (``which="rms"``; the
    maximum when a result gives no RMS) or its maximum (``"max"``). The maximum of a few holds is one
    hold's noise as much as the model's error; the RMS is the figure a comparison can trust."""
    h = result.get("heading_error_deg") or {}
    num = lambda x: float(x) if isinstance(x, (int, float)) and np.isfinite(x) else None  # noqa: E731
    if which == "rms" and num(h.get("rms_before")) is not None and num(h.get("rms_after")) is not None:
        return num(h.get("rms_before")), num(h.get("rms_after"))
    return num(h.get("before")), num(h.get("after"))


def complement_segments(segments: Sequence[Sequence[float]], span: Sequence[float], tol: float = 0.0) -> list[list[float]]:
    """The parts of ``span`` not covered by ``segments`` (sorted, non-overlapping), longer than ``tol``."""
    out, start = [], float(span[0])
    for a, b in sorted((float(a), float(b)) for a, b in segments):
        if a - start > tol:
            out.append([start, a])
        start = max(start, b)
    if float(span[1]) - start > tol:
        out.append([start, float(span[1])])
    return out


#: The ceiling's test told where to look (:func:`ceiling_power`): every open-world kind has 3 parameters
#: (an offset, a gain per axis, a small rotation), tested at the verdict's alpha.
CEILING_DF = 3
CEILING_ALPHA = 0.01


def ceiling_power(nc: float, df: int = CEILING_DF, alpha: float = CEILING_ALPHA) -> float:
    """Detection probability of a departure of non-centrality ``nc`` by one likelihood-ratio test that is
    told its frame, form and window (``df`` parameters, level ``alpha``): no search, so an upper bound on
    what any analysis that must also search can detect."""
    return float(ncx2.sf(chi2.isf(alpha, df), df, nc))


def judge_open(case: Case, result: dict[str, Any] | None, heading_free: float | None = None) -> dict[str, Any]:
    """Whether the analysis of one open-world case succeeded, and why not (issue 12, item 6).

    Success = a finding in the true frame ("sensor" and "platform" the same; so is any frame the
    recording cannot tell from the true one where the effect is present, ``case.frames``, e.g. the
    middle and outer stage while theta holds still), and for a windowed kind
    the segments of the findings in that frame (merged) cover each true window with both edges within
    5 % of the recording's duration, for an input kind one of them modelled against the true input
    (``model.against``); AND the largest residual RMS after over the noise floor <= 1.3 AND the level
    heading error lower after than before (when both are known). The form (offset, gain, rotation) is
    reported but not required. For a departure in a frame whose constant the nominal model absorbs
    (the unit's own, or the lab field), the complement of the found windows counts as well: the data
    cannot tell "present in W" from "present outside W" (the bias or the field takes the constant).

    ``heading_free`` (:attr:`Outcome.heading_free`) says whether any analysis could pass on the heading:
    ``heading_reachable`` is whether a perfect model of the effect (the same recording without it) has its
    level heading error lower than the nominal model's on the recording (None when either is unknown).
    """
    return judge_model(case.model or {}, case.span_s or (0.0, 0.0), case.frames, result, heading_free)


def judge_model(truth: dict[str, Any], span: Sequence[float], frames: Sequence[str] | None,
                result: dict[str, Any] | None, heading_free: float | None = None) -> dict[str, Any]:
    """:func:`judge_open` on a truth in the finding["model"] schema, the recording's time span and the
    frames it cannot tell from the true one (None: the true frame alone), for any recording: the table
    proof's cases and the hand-held ones (proof/handheld.py, whose results have no heading figures)."""
    result = result or {}
    tol = TARGETS["open_edge"] * (span[1] - span[0])
    # a parameter shift is the nominal model's own parameter out of its range, not a model of the departure
    findings = [f for f in result.get("findings", []) or [] if isinstance(f, dict) and f.get("effect") != "parameter_shift"]
    models = [f.get("model") or {} for f in findings]
    # the true frame, or one the recording cannot tell from it where the effect is present (frames)
    right = {_frame(f) for f in (frames or [truth.get("frame")])}
    same = [m for m in models if isinstance(m, dict) and _frame(m.get("frame")) in right]
    frame_right = bool(same)
    true_segments = truth.get("segments") or []
    if true_segments:
        try:
            merged = merge_segments([s for m in same for s in (m.get("segments") or [])], tol)
        except (TypeError, ValueError):
            merged = []
        def covers(found: list[list[float]]) -> bool:
            return all(any(abs(a - c) <= tol and abs(b - d) <= tol for c, d in found) for a, b in true_segments)

        # Where the nominal model absorbs the departure held constant (the unit's bias, sensitivity or
        # axes; the lab field), "present in W" and "present outside W" are the same data: the bias
        # takes the constant. Then the change points are what can be found, and the complement counts.
        absorbed = _frame(truth.get("frame")) in ("sensor", "lab")
        where_right = frame_right and (covers(merged) or (absorbed and covers(complement_segments(merged, span, tol))))
    else:
        where_right = any(m.get("against") == truth.get("against") for m in same)
    ratio = residual_ratio(result)
    before, after = _heading(result)
    max_before, max_after = _heading(result, "max")
    ok = {"frame": frame_right, "where": bool(where_right),
          "residual": ratio is not None and ratio <= TARGETS["open_residual"],
          "heading": before is None or after is None or after < before}
    return {"success": all(ok.values()), "failed": [k for k in OPEN_FAILURES if not ok[k]],
            "frame_right": frame_right, "where_right": bool(where_right),
            "form_right": any(m.get("form") == truth.get("form") for m in same),
            "detected": result.get("verdict") == "discrepancy", "residual_ratio": ratio,
            "heading_before": before, "heading_after": after, "heading_free": heading_free,
            "heading_reachable": None if before is None or heading_free is None else heading_free < before,
            "heading_max_better": None if max_before is None or max_after is None else max_after < max_before}


def score_open(cases: Sequence[Case], analyses: Sequence[Outcome | dict[str, Any]]) -> dict[str, Any]:
    """Score the open-world cases (same order): per kind, success by non-centrality bin
    ([successes, cases] per :data:`NC_BINS`), the share with the frame right, the windows or input
    right, the form right, detected; the median residual ratio (after / noise floor, largest axis),
    median level heading error before and after and the share made better, seconds per analysis;
    overall success at lambda >= 25 (the issue's 90 % target) and at any lambda, with the failures'
    reasons. Large departures (a target above the main range, proof.generator.LARGE_NC_RANGE) are scored
    apart ("large", per kind and in all), so that they never lift the figure at lambda >= 25. JSON-safe."""
    if len(cases) != len(analyses):
        raise ValueError(f"score_open: {len(cases)} cases but {len(analyses)} analyses")
    rows: dict[str, list[tuple[float, dict[str, Any], float | None]]] = {}
    large: dict[str, list[tuple[dict[str, Any], float | None]]] = {}  # departures above the main range
    errors: list[dict[str, Any]] = []
    for case, a in zip(cases, analyses):
        o = _outcome(a)
        if o.error is not None or o.result is None:
            errors.append({"kind": case.kind, "seed": case.seed, "error": o.error})
        j = judge_open(case, o.result, o.heading_free)
        if (case.target_nc or {}).get(case.kind, 0.0) > NC_RANGE[1]:
            large.setdefault(case.kind, []).append((j, o.seconds))
            continue
        rows.setdefault(case.kind, []).append((case.nc.get(case.kind, case.nc_total), j, o.seconds))

    def share(js: list[dict[str, Any]], key: str) -> float | None:
        return sum(bool(j[key]) for j in js) / len(js) if js else None

    by_kind: dict[str, dict[str, Any]] = {}
    kinds = set(rows) | set(large)
    for kind in [k for k in OPEN_KINDS if k in kinds] + sorted(kinds - set(OPEN_KINDS)):
        r = rows.get(kind, [])
        bins = [[0, 0] for _ in NC_BINS]
        for nc, j, _ in r:
            b = bins[_bin(nc)]
            b[0] += int(j["success"])
            b[1] += 1
        js = [j for _, j, _ in r]
        hb = [j["heading_before"] for j in js if j["heading_before"] is not None and j["heading_after"] is not None]
        ha = [j["heading_after"] for j in js if j["heading_before"] is not None and j["heading_after"] is not None]
        by_kind[kind] = {"cases": len(r), "bins": bins, "success": sum(j["success"] for j in js),
                         "success_rate": share(js, "success"), "frame_right": share(js, "frame_right"),
                         "where_right": share(js, "where_right"), "form_right": share(js, "form_right"),
                         "detected": share(js, "detected"),
                         "residual_ratio_median": _pct([j["residual_ratio"] for j in js], 50),
                         "heading_before_median": _pct(hb, 50), "heading_after_median": _pct(ha, 50),
                         "heading_better": sum(a < b for a, b in zip(ha, hb)) / len(hb) if hb else None,
                         "heading_max_better": share([j for j in js if j["heading_max_better"] is not None],
                                                     "heading_max_better"),
                         "seconds_median": _pct([s for _, _, s in r if s is not None], 50),
                         "seconds_max": _pct([s for _, _, s in r if s is not None], 100),
                         "large": [sum(j["success"] for j, _ in large.get(kind, [])), len(large.get(kind, []))]}

    def total(keep: Any) -> dict[str, Any]:
        kept = [(nc, j) for r in rows.values() for nc, j, _ in r if keep(nc)]
        js = [j for _, j in kept]
        failed = {k: sum(k in j["failed"] for j in js) for k in OPEN_FAILURES}
        n, k = len(js), sum(j["success"] for j in js)
        known = [j for j in js if j["heading_reachable"] is not None]
        # what no analysis can beat: the heading criterion where a perfect model of the effect passes it,
        # times the power of a test told the frame, form and window (an unknown heading counts as passable)
        bound = sum(ceiling_power(nc) * (j["heading_reachable"] is not False) for nc, j in kept)
        return {"cases": n, "success": k, "rate": k / n if n else None, "failed": failed,
                "ceiling": {"heading_known": len(known), "heading_reachable": sum(bool(j["heading_reachable"]) for j in known),
                            "rate": bound / n if n else None}}

    secs = [s for r in rows.values() for _, _, s in r if s is not None]
    secs += [s for r in large.values() for _, s in r if s is not None]
    lj = [j for r in large.values() for j, _ in r]
    return {"by_kind": by_kind, "at_target": {"nc_min": TARGETS["open_nc"], **total(lambda nc: nc >= TARGETS["open_nc"])},
            "overall": total(lambda nc: True),
            "large": {"cases": len(lj), "success": sum(j["success"] for j in lj),
                      "rate": sum(j["success"] for j in lj) / len(lj) if lj else None,
                      "failed": {k: sum(k in j["failed"] for j in lj) for k in OPEN_FAILURES}},
            "seconds": {"analyses": len(secs), "median": _pct(secs, 50), "max": _pct(secs, 100)},
            "errors": errors}


# --------------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------------

def _f(x: float | None, fmt: str = "{:.0%}") -> str:
    return "-" if x is None else fmt.format(x)


def _mark(ok: bool | None) -> str:
    return "" if ok is None else (" ok" if ok else " MISSED")


def _bin_labels() -> list[str]:
    """The non-centrality bins (:data:`NC_BINS`) as column heads."""
    return ["[{:g},{:g})".format(*b) if i < len(NC_BINS) - 1 else "[{:g},{:g}]".format(*b) for i, b in enumerate(NC_BINS)]


def _bin_cells(bins: Sequence[Sequence[int]]) -> str:
    """[successes, cases] per bin as right-aligned cells ("-" for an empty bin)."""
    return "".join(f"{f'{k}/{n}' if n else '-':>10}" for k, n in bins)


def format_report(sc: dict[str, Any]) -> str:
    """The score as plain-text tables, each figure next to the issue's target: the catalogue's tables
    when there are catalogue cases (else only the false alarms, when there are nulls), then the
    open-world table when there are open-world cases, then the analyses that raised."""
    out: list[str] = []
    if any(d["cases"] for d in sc["detection"].values()) or sc["pairs"]["cases"]:
        out.append(_format_catalogue(sc))
    elif sc["false_alarms"]["nulls"]:
        out.append("\n".join(_format_false_alarms(sc["false_alarms"])))
    so = sc.get("open") or {}
    if so.get("overall", {}).get("cases") or so.get("large", {}).get("cases"):
        out.append(format_open_report(so))
    text = "\n\n".join(out)
    if sc["errors"]:
        text += f"\nAnalyses that raised: {len(sc['errors'])}"
        for e in sc["errors"][:10]:
            text += f"\n  {e['kind']} (seed {e['seed']}): {e['error']}"
    return text


def _format_false_alarms(fa: dict[str, Any]) -> list[str]:
    T = TARGETS
    ok = None if fa["upper95"] is None else (fa["upper95"] <= T["false_alarm"] and fa["nulls"] >= T["min_nulls"])
    out = [f"False alarms on nulls: {fa['false_alarms']}/{fa['nulls']} = {_f(fa['rate'], '{:.2%}')}, one-sided 95 % "
           f"upper bound {_f(fa['upper95'], '{:.2%}')} (target <= {T['false_alarm']:.0%} on >= {T['min_nulls']} nulls)"
           + _mark(ok),
           f"  encoder rounding alone (nc_floor, not an effect): median {_f(fa['nc_floor_median'], '{:.2f}')}, "
           f"max {_f(fa['nc_floor_max'], '{:.2f}')}"]
    gens = fa.get("by_generator") or {}
    if len(gens) > 1:
        out.append("  by draw (each with its own plan and noise): " + ", ".join(
            f"{g} {v['false_alarms']}/{v['nulls']}" for g, v in gens.items()))
    return out


def _format_catalogue(sc: dict[str, Any]) -> str:
    """The catalogue cases' tables (issue 6)."""
    T = TARGETS
    out: list[str] = []
    bins = _bin_labels()
    head = (f"{'effect':<20}{'n':>4}" + "".join(f"{b:>10}" for b in bins) + f"{'@10':>7}{'@25':>7}{'held-out':>10}"
            + f"{'ideal@10':>10}{'ideal@25':>10}")
    out += ["Detection rate by non-centrality (detected/cases; logistic fit at lambda 10 and 25; "
            f"targets >= {T['detect_at_10']:.0%} at 10, >= {T['detect_at_25']:.0%} at 25). ideal: one chi-square "
            "test of the effect's df at the family's corrected level, the best a test could do", head, "-" * len(head)]
    missed, fitted = [], []
    for e, d in sc["detection"].items():
        cells = _bin_cells(d["bins"])
        r10, r25 = d["rate_at_10"], d["rate_at_25"]
        if r10 is not None:
            fitted.append(e)
            if r10 < T["detect_at_10"] or r25 < T["detect_at_25"]:
                missed.append(e)
        idl = d.get("ideal") or {}
        out.append(f"{e:<20}{d['cases']:>4}{cells}{_f(r10):>7}{_f(r25):>7}{_f(d['heldout_median'], '{:.3f}'):>10}"
                   f"{_f(idl.get('10')):>10}{_f(idl.get('25')):>10}")
    out.append(f"effects meeting both detection targets: {len(fitted) - len(missed)}/{len(fitted)} with a fit "
               f"(3 cases or more)" + (f"; missed: {', '.join(missed)}" if missed else ""))
    out.append("")

    out += _format_false_alarms(sc["false_alarms"])
    out.append("")

    nm = sc["naming"]
    out.append("Naming, among detected single-effect cases:")
    out.append(f"  right name first (first finding has no confusable): {nm['identifiable']} cases, "
               f"{_f(nm['right_first_rate'])} (target >= {T['right_first']:.0%})"
               + _mark(None if nm["right_first_rate"] is None else nm["right_first_rate"] >= T["right_first"]))
    out.append(f"  right set when reported confusable: {nm['confusable']} cases, {_f(nm['right_set_rate'])} "
               f"(target >= {T['right_set']:.0%})"
               + _mark(None if nm["right_set_rate"] is None else nm["right_set_rate"] >= T["right_set"]))
    out.append(f"  overall (first finding or its confusable_with): {nm['right']}/{nm['detected']} = {_f(nm['right_rate'])}")
    head = f"  {'effect':<20}{'detected':>9}{'right':>7}{'ident.':>8}{'right':>7}{'confus.':>9}{'right':>7}"
    out += [head]
    for e, r in nm["by_effect"].items():
        out.append(f"  {e:<20}{r['detected']:>9}{r['right']:>7}{r['identifiable']:>8}{r['identifiable_right']:>7}"
                   f"{r['confusable']:>9}{r['confusable_right']:>7}")
    out.append("")

    p = sc["pairs"]
    span = f" (each effect at lambda {p['nc_min']:.0f}-{p['nc_max']:.0f})" if p.get("nc_min") is not None else ""
    out.append(f"Pairs{span}: both effects named in {p['both_named']}/{p['cases']} = {_f(p['both_named_rate'])} "
               f"(target >= {T['pairs_both']:.0%}){_mark(None if p['both_named_rate'] is None else p['both_named_rate'] >= T['pairs_both'])}; "
               f"detected {p['detected']}/{p['cases']}")
    out.append("")

    conf = sc["confusion"]
    cols = [c for c in [*EFFECTS, "unexplained", "parameter_shift", NOT_DETECTED]
            if any(c in row for row in conf.values())]
    cols += sorted({c for row in conf.values() for c in row} - set(cols))
    short = {c: c[:7] for c in cols}
    out.append("Confusion matrix (rows: true effect; columns: first finding; (none): not detected)")
    out.append(f"{'':<20}" + "".join(f"{short[c]:>8}" for c in cols))
    for true in [*EFFECTS, "null"]:
        if true in conf:
            out.append(f"{true:<20}" + "".join(f"{conf[true].get(c, 0) or '.':>8}" for c in cols))
    out.append("")

    out.append(f"Parameter recovery (finding naming the true effect; coverage of 1.96-sigma intervals, "
               f"target ~{T['coverage']:.0%})")
    out.append(f"  {'effect':<20}{'cases':>6}{'median rel. err':>17}{'coverage':>10}{'wrong stage':>13}")
    for e, r in sc["recovery"].items():
        out.append(f"  {e:<20}{r['cases']:>6}{_f(r['rel_err_median'], '{:.3f}'):>17}{_f(r['coverage']):>10}"
                   f"{r['wrong_stage']:>13}")
    out.append("")

    h = sc["heldout"]
    out.append(f"Held-out residual RMS over the true model's (target <= {T['heldout']:.2f}), after the fitted effects "
               f"(before: the nominal model):")
    for k, v in h.items():
        ok = None if v["median"] is None else v["median"] <= T["heldout"]
        out.append(f"  {k:<9} {v['cases']:>4} cases: median {_f(v['median'], '{:.3f}')}, 90th percentile "
                   f"{_f(v['p90'], '{:.3f}')}{_mark(ok)}   (before: {_f(v['before_median'], '{:.3f}')}, "
                   f"{_f(v['before_p90'], '{:.3f}')})")
    x = sc.get("heldout_excess_removed", {})
    if x.get("cases"):
        out.append(f"  share of the held-out excess over the truth removed by the fitted effects (detected cases, "
                   f"(before^2 - after^2) / (before^2 - 1)): median {_f(x['median'])}, 10th percentile {_f(x['p10'])}")
    s = sc["seconds"]
    ok = None if s["max"] is None else s["max"] <= T["seconds"]
    out.append(f"Seconds per analysis: median {_f(s['median'], '{:.1f}')}, max {_f(s['max'], '{:.1f}')} "
               f"(target < {T['seconds']:.0f}){_mark(ok)}")
    return "\n".join(out)


def format_open_report(so: dict[str, Any]) -> str:
    """The open-world score (:func:`score_open`) as a plain-text table, next to the issue's targets."""
    T = TARGETS
    bins = _bin_labels()
    with_large = bool(so.get("large", {}).get("cases"))
    if with_large:
        bins = bins + ["large"]
    head = (f"{'kind':<26}{'n':>4}" + "".join(f"{b:>10}" for b in bins) + f"{'frame':>7}{'where':>7}{'form':>6}"
            f"{'resid':>7}{'heading rms before->after':>27}{'better':>8}{'max':>6}{'s':>6}")
    out = [f"Out-of-catalogue cases: success by non-centrality (successes/cases). Success = a finding in the true "
           f"frame, covering each true window (edges within {T['open_edge']:.0%} of the duration) or modelled against "
           f"the true input, the residual down to <= {T['open_residual']:g}x the noise floor (largest axis), and the "
           f"level heading error (RMS over the level holds) lower after than before. frame/where/form: share right; "
           f"resid: median residual over the noise floor; heading: medians (deg); better: share with the RMS lower "
           f"after, max: with the maximum lower; s: median seconds per analysis", head, "-" * len(head)]
    for kind, d in so["by_kind"].items():
        cells = _bin_cells(list(d["bins"]) + ([d["large"]] if with_large else []))
        heading = f"{_f(d['heading_before_median'], '{:.3f}')} -> {_f(d['heading_after_median'], '{:.3f}')}"
        out.append(f"{kind:<26}{d['cases']:>4}{cells}{_f(d['frame_right']):>7}{_f(d['where_right']):>7}"
                   f"{_f(d['form_right']):>6}{_f(d['residual_ratio_median'], '{:.2f}'):>7}{heading:>27}"
                   f"{_f(d['heading_better']):>8}{_f(d.get('heading_max_better')):>6}{_f(d['seconds_median'], '{:.1f}'):>6}")
    a, o = so["at_target"], so["overall"]
    ok = None if a["rate"] is None else a["rate"] >= T["open_success"]
    out.append(f"success at lambda >= {a['nc_min']:g}: {a['success']}/{a['cases']} = {_f(a['rate'])} "
               f"(target >= {T['open_success']:.0%}){_mark(ok)}; at any lambda {o['success']}/{o['cases']} = {_f(o['rate'])}")
    c = a.get("ceiling") or {}
    if a["cases"] and c.get("heading_known"):
        out.append(f"  ceiling: a perfect model of each effect (the same recording without it) leaves the level heading "
                   f"error lower than the nominal fit's in {c['heading_reachable']}/{c['heading_known']} cases (in the "
                   f"rest the effect moved it by less than the readings' noise: an analysis passes there only by its own "
                   f"fit's chance); with a test "
                   f"told each effect's frame, form and window (alpha {CEILING_ALPHA:g}) as well, any analysis could "
                   f"expect at most {_f(c['rate'])}")
    if a["cases"]:
        out.append(f"  failed at lambda >= {a['nc_min']:g} on: " + ", ".join(
            f"{k} {v}" for k, v in a["failed"].items()) + "  (frame: no finding in the true frame; where: windows or "
            "input wrong; residual: over the floor; heading: not better; a case can fail on several)")
    if with_large:
        lg = so["large"]
        out.append(f"large departures (lambda {LARGE_NC_RANGE[0]:g}-{LARGE_NC_RANGE[1]:g}, column 'large'; not counted above): "
                   f"{lg['success']}/{lg['cases']} = {_f(lg['rate'])}; failed on: "
                   + ", ".join(f"{k} {v}" for k, v in lg["failed"].items()))
    s = so["seconds"]
    ok = None if s["max"] is None else s["max"] <= T["seconds"]
    out.append(f"Seconds per open-world analysis: median {_f(s['median'], '{:.1f}')}, max {_f(s['max'], '{:.1f}')} "
               f"(target < {T['seconds']:.0f}){_mark(ok)}")
    return "\n".join(out)


# --------------------------------------------------------------------------------------------------
# The proof without table angles (proof.runner.run_handheld_proof)
# --------------------------------------------------------------------------------------------------

def score_handheld(cases: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Score the hand-held cases (records of :func:`proof.runner.run_handheld_case`): per kind, success
    by non-centrality bin ([successes, cases] per :data:`NC_BINS`) and the shares with the frame and the
    windows or input right; success at lambda >= the open-world target's and its failures' reasons; false
    alarms on the nulls (with the one-sided 95 % upper bound); seconds per analysis; crashes. JSON-safe."""
    by_kind: dict[str, dict[str, Any]] = {}
    for c in cases:
        if c["kind"] is None:
            continue
        d = by_kind.setdefault(c["kind"], {"cases": 0, "bins": [[0, 0] for _ in NC_BINS], "frame": 0, "windows": 0})
        b = d["bins"][_bin(c["lambda"])]
        b[0] += int(bool(c["success"]))
        b[1] += 1
        d["cases"] += 1
        d["frame"] += int(bool(c["frame"]))
        d["windows"] += int(bool(c["windows"]))
    for d in by_kind.values():
        d["frame_right"] = d.pop("frame") / d["cases"]
        d["where_right"] = d.pop("windows") / d["cases"]
    big = [c for c in cases if c["kind"] is not None and c["lambda"] >= TARGETS["open_nc"]]
    failed = {k: sum(k in (c.get("failed") or []) for c in big) for k in OPEN_FAILURES}
    nulls = [c for c in cases if c["kind"] is None and c.get("error") is None]
    alarms = sum(bool(c["alarm"]) for c in nulls)
    secs = [c["seconds"] for c in cases if c.get("seconds") is not None]
    return {"by_kind": by_kind,
            "at_target": {"nc_min": TARGETS["open_nc"], "cases": len(big), "success": sum(bool(c["success"]) for c in big),
                          "rate": sum(bool(c["success"]) for c in big) / len(big) if big else None, "failed": failed},
            "false_alarms": {"nulls": len(nulls), "alarms": alarms, "rate": alarms / len(nulls) if nulls else None,
                             "upper95": clopper_pearson_upper(alarms, len(nulls)) if nulls else None},
            "seconds": {"analyses": len(secs), "median": _pct(secs, 50), "max": _pct(secs, 100)},
            "errors": [{"kind": c["kind"], "seed": c["seed"], "error": c["error"]} for c in cases if c.get("error")]}


def format_handheld_report(sh: dict[str, Any]) -> str:
    """The hand-held score (:func:`score_handheld`) as a plain-text table, next to the issue's targets."""
    T = TARGETS
    bins = _bin_labels()
    head = f"{'kind':<28}{'n':>4}" + "".join(f"{b:>10}" for b in bins) + f"{'frame':>7}{'where':>7}"
    out = [f"Hand-held cases without table angles (attitude-free model): success by non-centrality (successes/cases). "
           f"Success = a finding in the true frame covering each true window (edges within {T['open_edge']:.0%} of the "
           f"duration) or modelled against the true input, and the residual's magnitude down to <= "
           f"{T['open_residual']:g}x the noise floor (no heading criterion: a hand-held recording has no heading "
           f"reference). frame/where: share right", head, "-" * len(head)]
    for kind, d in sh["by_kind"].items():
        cells = _bin_cells(d["bins"])
        out.append(f"{kind:<28}{d['cases']:>4}{cells}{_f(d['frame_right']):>7}{_f(d['where_right']):>7}")
    a = sh["at_target"]
    ok = None if a["rate"] is None else a["rate"] >= T["open_success"]
    out.append(f"success at lambda >= {a['nc_min']:g}: {a['success']}/{a['cases']} = {_f(a['rate'])} "
               f"(target >= {T['open_success']:.0%}){_mark(ok)}")
    if a["cases"]:
        out.append(f"  failed at lambda >= {a['nc_min']:g} on: "
                   + ", ".join(f"{k} {v}" for k, v in a["failed"].items() if k != "heading"))
    fa = sh["false_alarms"]
    if fa["nulls"]:
        ok = fa["rate"] <= T["false_alarm"] if fa["nulls"] >= T["min_nulls"] else None
        out.append(f"false alarms on hand-held nulls: {fa['alarms']}/{fa['nulls']} = {_f(fa['rate'], '{:.1%}')} "
                   f"(95 % upper bound {_f(fa['upper95'], '{:.1%}')}; target <= {T['false_alarm']:.0%} on >= "
                   f"{T['min_nulls']}){_mark(ok)}")
    s = sh["seconds"]
    ok = None if s["max"] is None else s["max"] <= T["seconds"]
    out.append(f"Seconds per hand-held analysis: median {_f(s['median'], '{:.1f}')}, max {_f(s['max'], '{:.1f}')} "
               f"(target < {T['seconds']:.0f}){_mark(ok)}")
    if sh["errors"]:
        out.append(f"Analyses that raised: {len(sh['errors'])}")
        out += [f"  {e['kind'] or 'null'} (seed {e['seed']}): {e['error']}" for e in sh["errors"]]
    return "\n".join(out)
