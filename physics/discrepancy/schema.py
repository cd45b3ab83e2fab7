"""The analyser's result: the Analysis container."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from physics.effects import CATALOGUE, PARAMETER_SHIFT


@dataclass
class Analysis:
    """The analyser's output: ``result`` is the JSON report, ``series`` per-sample arrays for plots."""

    result: dict[str, Any]
    series: dict[str, np.ndarray] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The JSON report (already JSON-safe)."""
        return self.result



#: Where each effect lives in the one finding schema (frame, form, against): the catalogue's own entry
#: says it (physics/effects.py); a parameter shift is the platform's linear map. A ``stage`` effect takes
#: its frame from the fitted stage.
CATALOGUE_MODEL: dict[str, tuple[str | None, str | None, str | None]] = {
    **{e.id: e.model for e in CATALOGUE.values()}, PARAMETER_SHIFT: ("platform", "linear", None)}

#: The input a generic "unexplained structure against <input>" test is about, from its name.
_UNEXPLAINED_AGAINST = (("psi_t", "psi_t"), ("theta_t", "theta_t"), ("phi_t", "phi_t"), ("temperature", "temp_c"),
                        ("time", "time"), ("rate", "rate"), ("accelerometer", "acc"), ("direction", None))


def finding_model(finding: dict[str, Any]) -> dict[str, Any]:
    """The ``model`` of a finding in the one schema: frame, form, against and time segments."""
    effect = finding.get("effect")
    if effect in CATALOGUE_MODEL:
        frame, form, against = CATALOGUE_MODEL[effect]
        if frame == "stage":
            frame = (finding.get("parameters") or {}).get("stage", "outer")
        return {"frame": frame, "form": form, "against": against, "segments": []}
    against = None
    text = str((finding.get("where") or {}).get("against", "")).lower()
    for key, name in _UNEXPLAINED_AGAINST:
        if key in text:
            against = name
            break
    return {"frame": None, "form": None, "against": against, "segments": []}


def with_schema(findings: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every finding with ``model`` and ``plausible`` (filled from the catalogue's mapping when the
    analyser that made it did not set them). Plausibility is a gate: a catalogue effect whose fitted
    size is beyond its physical range is not reported as that effect, but as unexplained structure of
    its shape (``stands_in_for``), with the model term kept."""
    out = []
    for f in findings:
        f = dict(f)
        f.setdefault("model", finding_model(f))
        f.setdefault("plausible", True)
        if f["plausible"] is False and f.get("effect") in CATALOGUE_MODEL and f["effect"] != "parameter_shift":
            f["stands_in_for"] = f["effect"]
            f["effect"] = "unexplained"
            f["explanation"] = (f"Structure of the shape of {f['stands_in_for']}, but of a size no such cause "
                                "plausibly has: not that effect; something the model lacks. (The term's fit: "
                                + str(f.get("explanation", "")) + ")")
        out.append(f)
    return out


def _mean(values: Any) -> float:
    """Mean of the known numbers in a list (the attitude-free model leaves unused columns null)."""
    xs = [float(v) for v in (values or []) if v is not None and np.isfinite(float(v))]
    return float(np.mean(xs)) if xs else float("nan")


#: A figure after the fitted effects counts as worse beyond these (the residual's ratio; the level heading
#: error's ratio plus degrees): within them it is the scatter of the fit, not a worse model.
WORSE_RESIDUAL = 1.02
WORSE_HEADING, WORSE_HEADING_DEG = 1.2, 0.002


def summary(result: dict[str, Any]) -> str:
    """One plain sentence on whether the fitted model improves on the nominal one (in-sample, held-out and
    heading), or that nothing does."""
    ho = result.get("heldout") or {}
    before = _mean(ho.get("rms_before_lsb"))
    after = _mean(ho.get("rms_after_lsb"))
    modelled = [f for f in result.get("findings", []) if f.get("effect") not in ("unexplained", "parameter_shift")]
    # a recording that cannot determine the unit's nominal model says so first: its own fit is no unit's
    free = "" if result.get("nominal_determined", True) else (
        "These attitudes cannot determine the unit's nominal model (M, b and the field), so its parameters are "
        "neither the unit's nor judged against a calibration. ")
    return free + _verdict_sentence(result, modelled, before, after)


def _verdict_sentence(result: dict[str, Any], modelled: list[dict[str, Any]], before: float, after: float) -> str:
    """The summary's sentence on the findings (see :func:`summary`)."""
    kinds = {f.get("effect") for f in result.get("findings", [])}
    if result.get("verdict") == "consistent":
        # what this recording cannot show is part of the answer: a hold at one attitude tests almost nothing
        missing = sorted({u.get("effect", "") for u in result.get("untestable", []) if u.get("effect") != "discovered"})
        inputs = sum(1 for u in result.get("untestable", []) if u.get("effect") == "discovered")
        blind = ""
        if missing or inputs:
            parts = ([f"{len(missing)} catalogue effect(s) ({', '.join(missing)})"] if missing else []) + (
                [f"{inputs} of the dictionary's inputs or frames"] if inputs else [])
            blind = f" It cannot show {' and '.join(parts)}: see untestable for what each needs."
        unusual = "" if "parameter_shift" not in kinds else (
            " Its fitted parameters are unusual for one unit, though they fit the readings: see the parameter shift.")
        return "The recording is consistent with the nominal model: nothing departs from it beyond the noise." + unusual + blind
    shifted = ("The nominal parameters themselves depart from the unit's calibration or from a plausible unit: "
               "see the parameter shift, which the nominal model absorbs (nothing of it is left in the residual).")
    if kinds == {"parameter_shift"}:
        return shifted
    if not modelled or not np.isfinite(before) or not after < before:
        return ("Nothing we can model improves the fit held-out: the departures are reported as unexplained "
                "structure, and the nominal model stands." + (" " + shifted if "parameter_shift" in kinds else ""))
    head = result.get("heading_error_deg") or {}
    h = ""
    if head.get("rms_before") is not None and head.get("rms_after") is not None:
        h = f"; level heading error {head['rms_before']:.3g} -> {head['rms_after']:.3g} deg RMS"
    elif head.get("before") is not None and head.get("after") is not None:
        h = f"; level heading error {head['before']:.3g} -> {head['after']:.3g} deg (maximum)"
    if h and head.get("noise_rms") is not None:
        # below its noise a level heading error measures the hold means' noise, not the calibration
        h += f" (the readings' noise alone makes about {head['noise_rms']:.2g} deg)"
    rb = _mean(result.get("residual_rms_before_lsb"))
    ra = _mean(result.get("residual_rms_after_lsb"))
    floor = _mean(result.get("noise_floor_lsb"))
    figures = f"residual {rb:.3g} -> {ra:.3g} LSB rms (noise floor {floor:.3g}), held-out {before:.3g} -> {after:.3g} LSB{h}"
    hb, ha = head.get("rms_before", head.get("before")), head.get("rms_after", head.get("after"))
    # worse by more than the figures' own scatter (a heading error of 0.0140 -> 0.0141 deg is the same)
    worse = (["the residual"] if ra > WORSE_RESIDUAL * rb else []) + (
        ["the level heading error"] if hb is not None and ha is not None and ha > WORSE_HEADING * hb + WORSE_HEADING_DEG
        else [])
    if worse:
        # said as it is: "improves the fit" was printed over a residual and a heading error that grew
        return (f"The model with {len(modelled)} effect(s) predicts held-out data better but leaves "
                f"{' and '.join(worse)} worse: {figures}. Treat its findings with caution: the model misses part "
                "of what is there.")
    return f"The model with {len(modelled)} effect(s) improves the fit: {figures}."
