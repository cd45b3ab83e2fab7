"""The table model's analysis: compare, locate, name, model, fall back (physics/discrepancy/__init__.py)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any, Callable, NamedTuple

import numpy as np
from scipy import linalg, stats
from threadpoolctl import threadpool_limits

from physics import effects as fx
from physics.calibration import Calibration, json_safe
from physics.discrepancy.discovery import (MAX_BLOCKS, SAME_EVIDENCE, Dictionary, Found, confirming_experiment, describe,
                                          discovered_finding, merge_windows, rebuild, rows_of)
from physics.discrepancy.lrt import Test, _complement, _extend, _null_residuals, _orth, _score, line_search
from physics.discrepancy.noise import NoiseModel, estimate_noise, ljung_box, require_noise, whiten_all
from physics.discrepancy.registry import LINE, REGISTRY, effect_columns, frame_of, parameters, where_extra
from physics.discrepancy.schema import Analysis, summary, with_schema
from physics.discrepancy.twin import (ATTITUDE_SOURCE_KEY, Context, Nominal, context, decimate, fit_nominal, generic_columns,
                                     nominal_columns)
from physics.fit import (ANGLE_ADVICE, BAD_RUN, better_reading, consecutive_runs, fit, index_list, isolated_runs,
                         model_residuals, pose_groups, reason_kind, rejected_rows, screen_rows)
from physics.frames import SPECIFIC_FORCE_L, field_angles
from physics.heading import magnetic_heading, wrap180
from physics.recording import Recording, RecordingError, file_row
from physics.sensor import split_matrix

#: At most this many catalogue effects are added to one recording's model.
MAX_EFFECTS = 3
#: Alpha's shares (weighted Bonferroni, so the verdict's false-alarm rate stays alpha): the catalogue's
#: and the dictionary of generic blocks' in each round, and the fallback's, the generic tests on the
#: final residual ("unexplained structure against <input>"). Held at the whole alpha, that third family
#: doubled the false alarms: 2 of 300 nulls beside the first two families' 3.
CATALOGUE_SHARE = 0.6
DICTIONARY_SHARE = 0.3
FALLBACK_SHARE = 0.1
#: When a catalogue effect and a dictionary block are both significant, the catalogue effect is named
#: unless the block explains more by this much (in the statistic, twice the log-likelihood): a physics
#: people know to look for is likelier than a generic one of the same fit.
CATALOGUE_PRIOR = 2.0
#: Plausibility limits on the nominal fit: beyond these a unit is not what it claims to be.
MAX_MISALIGNMENT_DEG = 10.0
MAX_K_MISMATCH = 0.25
MAX_BIAS_FIELDS = 3.0
#: Longer recordings are block-averaged to this many samples (a hand-held IMU at 285 Hz) to keep the
#: analysis within seconds; the note says so.
MAX_SAMPLES = 20_000
#: Fewer samples cannot estimate the noise, let alone test anything against it.
MIN_SAMPLES = 200

Progress = Callable[[str, float], None]



# --------------------------------------------------------------------------------------------------
# The analysis
# --------------------------------------------------------------------------------------------------

def analyze(rec: Recording, calibration: Calibration | None = None, *, alpha: float = 0.01, null_sims: int = 200,
            seed: int | Sequence[int] | np.random.SeedSequence | None = None,
            progress: Progress | None = None) -> Analysis:
    """Locate, name and model where ``rec`` departs from the nominal twin (module docstring).

    ``calibration`` (optional) is the unit's calibration as the nominal model: its parameters are
    compared with this recording's fit ("parameter_shift"). ``null_sims`` simulated nulls calibrate
    the tests; ``alpha`` is the family-wise false-alarm rate of the verdict. ``seed`` seeds the null
    simulations; by default the recording's own fingerprint, so that the same recording gives the same
    analysis wherever it is analysed (the result's ``"seed"`` says which was used).
    """
    seed = rec.fingerprint() if seed is None else seed
    rng = np.random.default_rng(seed)
    rec, bad = _without_bad_samples(rec)
    rec, warm = _plausible_temperature(rec)
    # many small matrix products: several BLAS threads fight over the cores and run 5-10x slower
    with threadpool_limits(1):
        if not rec.has_angles:
            from physics.discrepancy.attitude_free import analyze_attitude_free
            a = analyze_attitude_free(rec, alpha=alpha, null_sims=null_sims, rng=rng, progress=progress)
        else:
            a = _analyze_table(rec, calibration, alpha, null_sims, rng, progress)
    if warm:
        a.result["notes"] = [warm, *a.result.get("notes", [])]
    if bad:
        a.result["notes"] = [bad[0], *a.result.get("notes", [])]
        a.result["rejected_rows"] = bad[1]
    a.result["findings"] = with_schema(a.result.get("findings", []))
    if not isinstance(seed, np.random.SeedSequence):  # a program's own stream is not repeatable from the JSON
        a.result["seed"] = seed if isinstance(seed, (int, np.integer)) else [int(s) for s in seed]
    a.result.setdefault("summary", summary(a.result))
    return a


#: A nominal fit leaving less than this many times the noise floor is not checked for a wrong convention.
CONVENTION_MISFIT = 20.0
#: The convention check fits the hold means when there are this many holds, else this many samples at
#: most (evenly spread): enough to tell the levels apart.
CONVENTION_HOLDS = 8
CONVENTION_SAMPLES = 300


def check_conventions(ctx: Context, y: np.ndarray, r0: np.ndarray, floor: np.ndarray) -> None:
    """Refuse (RecordingError) a recording whose table angles fit the nominal twin far better read
    another way (physics.fit.better_reading). A residual of hundreds of times the noise floor that such a
    reading removes is a mistake in the file, not physics, and every effect fitted to it would be
    invented (a 5,000-LSB offset "following the accelerometer")."""
    if not float(np.sqrt(np.mean(r0 ** 2))) > CONVENTION_MISFIT * float(np.mean(floor)):
        return
    held = ctx.hold >= 0
    if len(np.unique(ctx.hold[held])) >= CONVENTION_HOLDS:  # hold means: a few dozen rows, fitted in milliseconds
        yy, first = _hold_means(ctx, y, held)
        ang, rows = ctx.ang[first], "hold means"
    else:
        pick = np.unique(np.linspace(0, len(y) - 1, min(len(y), CONVENTION_SAMPLES)).astype(int))
        ang, yy, rows = ctx.ang[pick], y[pick], "samples"
    found = better_reading(ang, yy)
    if found is not None:
        here, best, how = found
        raise RecordingError(
            f"the table angles fit the nominal twin far better read {how} (the {rows} leave {here:.3g} LSB rms as "
            f"given, {best:.3g} so read; the noise floor is {float(np.mean(floor)):.2g} per sample): that is a mistake "
            f"in the file's convention, not physics, so nothing is analysed. {ANGLE_ADVICE}")


#: At most this share of a recording's holds may have a gross reading at their first or last rows for
#: those readings to count as garbage (a pattern over more holds is physics: `_without_bad_samples`).
EDGE_GARBAGE_SHARE = 0.25


def _ends_at_its_edge(rec: Recording, edge: np.ndarray, group: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """The rows of ``edge`` (runs at a hold's first or last rows) whose departure stops at the hold's edge:
    against the joint fit without the ``bad`` rows, the neighbouring hold across the edge does not share
    it (at most half of it, along the run's own departure from its hold). A recording the fit refuses
    keeps them all (nothing to judge by)."""
    out = np.zeros(len(rec), bool)
    try:
        r = model_residuals(rec, fit(rec.select(~bad), "joint", bootstrap=0))
    except ValueError:
        return out
    for run in consecutive_runs(edge):
        g = group[run[0]]
        own = (group == g) & ~bad
        across = g - 1 if run[0] == 0 or group[run[0] - 1] != g else g + 1
        near = (group == across) & ~bad
        d = np.median(r[run], axis=0) - np.median(r[own], axis=0)
        carried = float((np.median(r[near], axis=0) - np.median(r[own], axis=0)) @ d / (d @ d)) if near.any() else 0.0
        out[run] = carried <= 0.5
    return out


#: A temperature outside this range (deg C) is no compass's working temperature: a garbled field.
TEMP_RANGE_C = (-60.0, 150.0)
#: ... nor one this far (deg C) from the median of its neighbours (TEMP_NEIGHBOURS a side): a unit's
#: temperature follows its heat capacity, degrees per minute at most.
TEMP_JUMP_C = 5.0
TEMP_NEIGHBOURS = 4


def _plausible_temperature(rec: Recording) -> tuple[Recording, str | None]:
    """``rec`` with implausible ``temp_c`` values (outside :data:`TEMP_RANGE_C`, or :data:`TEMP_JUMP_C` off
    the median of their neighbours) interpolated in time from the others, and the note saying which rows
    (None when every value is plausible). The readings are kept: a garbled temperature field says nothing
    of the magnetometer, but as an input it made the temperature tests tests of those few rows (9999 deg C)."""
    temp = rec.temp_c
    if temp is None or len(temp) < 2 * TEMP_NEIGHBOURS + 1:
        return rec, None
    given = np.isfinite(temp)
    odd = given & ((temp < TEMP_RANGE_C[0]) | (temp > TEMP_RANGE_C[1]))
    sane = np.where(given & ~odd, temp, np.nan)
    k = TEMP_NEIGHBOURS
    padded = np.pad(sane, k, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * k + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a window of nothing but odd values: no median
        local = np.nanmedian(windows, axis=1)
    odd |= given & np.isfinite(local) & (np.abs(temp - local) > TEMP_JUMP_C)
    good = given & ~odd
    if not odd.any() or good.sum() < 2:
        return rec, None
    filled = np.interp(rec.t, rec.t[good], temp[good])
    out = rec.select(slice(None))
    out.temp_c = np.where(odd, filled, temp)
    rows = sorted(file_row(rec, int(i)) for i in np.flatnonzero(odd))
    worst = float(temp[odd][np.argmax(np.abs(temp - filled)[odd])])
    return out, (f"temp_c of {int(odd.sum())} row(s) is implausible (e.g. {worst:g} deg C: outside {TEMP_RANGE_C[0]:g} to "
                 f"{TEMP_RANGE_C[1]:g} deg C, or over {TEMP_JUMP_C:g} deg C from its neighbours'): interpolated from the "
                 f"rows around them for the temperature tests, the readings kept; data rows {index_list(rows)} (0-based)")


def _without_bad_samples(rec: Recording) -> tuple[Recording, tuple[str, list[dict[str, Any]]] | None]:
    """``rec`` without its bad samples, and the note and rows to report (None when there are none): rows
    whose three axes of a sensor read exactly 0 (a brown-out, a dropped frame), rows with a magnetometer
    axis at the int16 limit (saturated), rows that repeat the one before exactly (a sample written twice, or a
    frozen sensor's run of repeats), and,
    on a turntable, lone rows or short runs far off their hold (garbage that passed the checksum). Left in,
    each would be "structure" that no physics explains."""
    screened = screen_rows(rec)
    zero = {i for i, why in screened.items() if reason_kind(why) == "all zeros"}
    clipped = {i for i, why in screened.items() if reason_kind(why) == "saturated"}
    # a frozen sensor's repeats (physics.fit._screen_frozen): its last reading, not the field at these times
    frozen = {i for i, why in screened.items() if reason_kind(why) == "frozen"}
    # and an axis stuck on one reading while the others go on (physics.fit._screen_stuck): not the field either
    stuck = {i for i, why in screened.items() if reason_kind(why) == "stuck axis"}
    # a row that repeats the one before exactly (time stamp and readings): a logger that wrote a sample twice.
    # Kept, every row written twice was "unexplained structure in time" (Ljung-Box p 2e-284), a field "varying
    # too slowly for a hold to resolve"
    repeated = {i: why for i, why in screened.items() if reason_kind(why) == "written twice"}
    off = np.array(sorted(set(screened) - zero - clipped - frozen - stuck - set(repeated)), dtype=int)
    short: set[int] = set()
    # a pose is the table's hold; angles from an attitude reference repeat while the body moves on
    # (a stale reference), which says nothing of the magnetometer's rows
    if len(off) and rec.meta.get(ATTITUDE_SOURCE_KEY, "turntable") == "turntable":
        # rows off their hold (physics.fit.screen_rows) are bad samples when they come alone or in runs of
        # at most BAD_RUN with good rows of their own hold on both sides; a longer run is something that
        # happened, which is what the analysis is for. At a hold's first or last row the screen flags only
        # gross ones (5 % of k): garbage too (a flipped bit lands there one time in fifteen) unless the
        # departure carries on into the next hold (a magnet set down as the hold ends), or the pattern
        # comes at many holds (physics: a lag, a clock skew between samples and encoders)
        bad_rows = np.zeros(len(rec), bool)
        bad_rows[list(screened)] = True
        group = pose_groups(rec)
        lone = isolated_runs(bad_rows, group)
        edge = isolated_runs(bad_rows, group, at_edges=True) & ~lone
        holds = np.count_nonzero(np.bincount(group) >= 3)
        if edge.any() and len(np.unique(group[edge])) <= EDGE_GARBAGE_SHARE * holds:
            lone |= _ends_at_its_edge(rec, edge, group, bad_rows)
        short = {int(i) for i in off if lone[i]}
    bad = {**{i: screened[i] for i in sorted(zero | short | clipped | frozen | stuck)}, **repeated}
    bad = dict(sorted(bad.items()))
    if not bad:
        return rec, None
    keep = np.ones(len(rec), bool)
    keep[list(bad)] = False
    kinds = [f"{len(repeated)} repeating the row before exactly (a sample written twice)" if repeated else "",
             f"{len(zero)} with a sensor's three axes exactly 0" if zero else "",
             f"{len(frozen)} repeating the row before on all six axes in runs (a frozen sensor)" if frozen else "",
             f"{len(stuck)} with one axis stuck on one reading while the others go on" if stuck else "",
             f"{len(short)} far off their hold's median, alone or in runs of at most {BAD_RUN}" if short else "",
             (f"{len(clipped)} saturated, at t {rec.t[min(clipped)]:.1f}-{rec.t[max(clipped)]:.1f} s (a field beyond the "
              "sensor's range: a strong magnet near the unit?)") if clipped else ""]
    note = (f"{len(bad)} of {len(rec)} rows left out as bad samples ({'; '.join(k for k in kinds if k)}): "
            f"data rows {index_list(sorted(file_row(rec, i) for i in bad))} (0-based)")
    return rec.select(keep), (note, rejected_rows(rec, bad))


def _analyze_table(rec: Recording, calibration: Calibration | None, alpha: float, null_sims: int,
                   rng: np.random.Generator, progress: Progress | None) -> Analysis:
    if len(rec) < MIN_SAMPLES:
        raise RecordingError(f"the analysis needs at least {MIN_SAMPLES} samples (10 s at 20 Hz), got {len(rec)}")
    say = progress or (lambda stage, frac: None)
    notes: list[str] = []
    if len(rec) > MAX_SAMPLES:
        k = int(np.ceil(len(rec) / MAX_SAMPLES))
        rec = decimate(rec, k)
        notes.append(f"{k} consecutive samples averaged into one ({len(rec)} left) to keep the analysis fast")
    say("compare: nominal fit", 0.0)
    ctx = context(rec)
    y_raw = np.asarray(rec.mag, float)
    nom = fit_nominal(ctx, y_raw)
    r0 = y_raw - nom.predict(ctx)
    temp = rec.temp_c

    say("noise floor", 0.15)
    noise = estimate_noise(r0, ctx)
    require_noise(noise.floor)
    check_conventions(ctx, y_raw, r0, noise.floor)
    eff = effect_columns(ctx, nom, temp)
    gen = generic_columns(ctx, nom, temp)
    untestable = [{"effect": name.split(":")[0], "reason": why} for name, (_, _, why) in eff.items() if why]
    untestable = [dict(t) for t in {(u["effect"], u["reason"]): u for u in untestable}.values()]
    n_round1 = len([1 for X, _, why in eff.values() if not why]) + len(gen) + 1

    # Mains first: a line hides under the smooth effects' tests but biases the noise estimate they rely
    # on, so once found it is fitted and the noise re-estimated without it.
    say("spectral lines", 0.25)
    all_tests: list[dict[str, Any]] = []
    selected: list[str] = []
    mains_hz: float | None = None
    line = line_search(r0, ctx, noise)
    chosen = line["log_p"] + np.log(n_round1) < np.log(alpha * CATALOGUE_SHARE)  # the catalogue's share
    all_tests.append({"effect": LINE, "variant": f"line at {line['alias_hz']:.4f} Hz", "round": 1,
                      "statistic": line["statistic"], "df": 6, "bartlett": 1.0, "p_value": line["p_value"],
                      "p_adjusted": min(1.0, line["p_value"] * n_round1), "selected": bool(chosen), "generic": False})
    if chosen:
        mains_hz = line["alias_hz"]
        Xm = REGISTRY[LINE].line(ctx, mains_hz)
        coef_m, *_ = np.linalg.lstsq(Xm.transpose(1, 0, 2).reshape(-1, 6), r0.T.ravel(), rcond=None)
        noise = estimate_noise(r0 - np.einsum("nip,p->ni", Xm, coef_m), ctx)
        selected.append(LINE)

    r0, J0, A0, Q0, zr, z, raw_of, candidates = _linearise(ctx, y_raw, nom, eff, noise, mains_hz)
    generic_w = {name: whiten_all(X, noise, ctx.segment) for name, X in gen.items()}

    say("null simulations", 0.35)
    null = _null_residuals(ctx, noise, Q0, null_sims, rng) if null_sims > 0 else None

    say("tests", 0.55)
    always = list(selected)  # the mains line, found first
    gated: set[str] = set()  # catalogue variants refused: their fitted parameters are implausible
    generic_first: dict[str, dict[str, Any]] = {}
    found: list[Found] = []
    # the dictionary of generic blocks competes with the catalogue in every round of the forward selection
    dic = Dictionary(ctx, nom, temp, noise, Q0)
    discovery_untestable = dic.untestable
    for attempt in range(3):
        selected = list(always)
        found = []
        ties: dict[str, list[tuple[str, str]]] = {}  # catalogue effect -> blocks it won a near tie against
        rows = _forward(selected, found, candidates, eff, generic_w, dic, A0, Q0, z, zr, null, alpha, gated, say, ties)
        all_tests += rows
        if attempt == 0:
            generic_first = {row["variant"]: row for row in rows if row["generic"]}
        terms = {**{s: candidates[s] for s in selected}, **{f.name: f.Xw for f in found}}
        final = _backward(terms, Q0, z, null, alpha, n_round1, all_tests, _search_penalty(dic, found))
        selected = [s for s in selected if s in terms]
        found = [f for f in found if f.name in terms]
        if _refit_windows(dic, found, terms, Q0, z, null, alpha * DICTIONARY_SHARE):
            final = _backward(terms, Q0, z, null, alpha, n_round1, all_tests, _search_penalty(dic, found))
            found = [f for f in found if f.name in terms]
        found, terms = _reconsider(dic, found, terms, Q0, z, null, alpha)
        coef, _, offsets, _ = _fit_identified(A0, terms, found, zr)
        refused = [s for i, s in enumerate(terms) if s in selected and s != LINE
                   and _implausible(s, coef[offsets[i + 1]:offsets[i + 2]], eff)]
        if not refused:
            break
        for s in refused:  # the structure it stood in for goes to discovery on the next pass
            gated.add(s)
            all_tests.append({**_row(final[s], "joint fit"), "rejected": "implausible parameters"})

    say("model: refit with the effects", 0.7)
    raw_of.update({f.name: f.X for f in found})
    nom0, J00, r00 = nom, J0, r0  # the nominal model alone: the "before" of every figure
    def relinearise() -> None:
        """The twin is linear around a nominal fit that the departures themselves pulled: refit the nominal
        model on the readings with the fitted effects taken out and rebuild every term around it (a large
        departure otherwise leaves second-order residue that passes for more blocks). Again whenever a
        term leaves the model: the nominal fit had taken that term's share out too (a dropped offset
        following the accelerometer left the field's direction off, and 32 more in the residual's
        statistic passed for unexplained structure). With no term left, the nominal fit of the readings.
        ``selected`` and ``found`` keep only what is in ``terms``."""
        nonlocal nom, eff, r0, J0, A0, Q0, zr, z, raw_of, candidates, found, terms, selected
        selected = [s for s in selected if s in terms]
        coef, _, offsets, ident = _fit_identified(A0, terms, found, zr)
        contrib = sum(np.einsum("nip,p->ni", X, coef[offsets[i + 1]:offsets[i + 2]])
                      for i, X in enumerate(_fitted_columns(raw_of, terms, ident)))
        nom = fit_nominal(ctx, y_raw - contrib)
        # a fitted time lag's column is rebuilt as the exact shift by it (its derivative alone is first order)
        lag = float(coef[offsets[list(terms).index(TIME_LAG) + 1]]) if TIME_LAG in terms else 0.0
        eff = effect_columns(ctx, nom, temp, lag if abs(lag) <= MAX_LAG_S else 0.0)
        r0, J0, A0, Q0, zr, z, raw_of, candidates = _linearise(ctx, y_raw, nom, eff, noise, mains_hz)
        found = [rebuild(f, ctx, nom, temp, noise) for f in found if f.name in terms]
        raw_of.update({f.name: f.X for f in found})
        terms = {**{s: candidates[s] for s in selected}, **{f.name: f.Xw for f in found}}

    if terms:
        relinearise()  # and check every term again around it
        final = _backward(terms, Q0, z, null, alpha, n_round1, all_tests, _search_penalty(dic, found))
        selected = [s for s in selected if s in terms]
        found = [f for f in found if f.name in terms]
    # The periodogram found the line against a running median of the spectrum; the twin tests it at that
    # frequency against the noise model, null-calibrated. Both pay for the frequency search (the twin's
    # test alone knows the frequency: on a null it said 1e-4 to 4e-4 where the search's p was 0.03), and a
    # line the twin does not confirm is left out: on nulls with slow noise the periodogram's local level
    # ran low, and a line it called 3e-4 was 0.55 in the twin.
    p_twin = 1.0
    if LINE in terms and LINE in final:
        p_twin = min(1.0, final[LINE].p_value * line["independent"] * n_round1)
        if final[LINE].df > 0 and p_twin >= alpha * CATALOGUE_SHARE:
            del terms[LINE]
            notes.append(f"a line at {mains_hz:.4f} Hz in the spectrum is not confirmed by the twin's test at that "
                         f"frequency (p {p_twin:.2g} after the search): left out")
            relinearise()
    fold = _folds(ctx)
    pred_before = _heldout(ctx, y_raw, nom0, [J00], fold, noise.floor)
    rms = lambda r: np.sqrt(np.mean(r * r, axis=0))  # noqa: E731
    ho_before = rms(y_raw - pred_before)
    # The final model is never worse held-out than the nominal one: an effect whose removal improves the
    # held-out fit goes, the worst first, until the model does no harm.
    while True:
        pred_after = _heldout(ctx, y_raw, nom, [J0] + [raw_of[s] for s in terms], fold, noise.floor)
        ho_after = rms(y_raw - pred_after)
        if not terms or ho_after.mean() <= ho_before.mean():
            break
        trial = {s: rms(y_raw - _heldout(ctx, y_raw, nom, [J0] + [raw_of[o] for o in terms if o != s], fold,
                                          noise.floor)).mean() for s in terms}
        worst = min(trial, key=trial.get)
        notes.append(f"{worst} left out: with it the model predicted held-out data worse than without")
        del terms[worst]
        relinearise()  # with no term left: the nominal model alone, as before
    coef, cov, offsets, ident = _fit_identified(A0, terms, found, zr)
    raw_cols = [J0] + _fitted_columns(raw_of, terms, ident)
    Xraw = np.concatenate(raw_cols, axis=2)
    fitted = np.einsum("nip,p->ni", Xraw, coef)
    r_after = r0 - fitted
    if not terms:
        # nothing added: the model after is the nominal one (the twin's weighted refit of its parameters
        # alone, under a noise model that took in slow structure, made "after" worse than "before" with
        # no effect fitted: 9.96 -> 12.4 LSB, 0.25 -> 0.63 deg)
        r_after, pred_after, ho_after = r00, pred_before, ho_before

    # generic tests again on the final residual: what neither the catalogue nor discovery explains
    unexplained = [row for row in generic_first.values() if row["p_adjusted"] < alpha * FALLBACK_SHARE]
    zf = z
    if terms:
        Qf = _extend(Q0, *terms.values())
        zf = zr - Qf @ (Qf.T @ zr)
        gt = [Test(name, _complement(Xw, Qf)) for name, Xw in generic_w.items()]
        _score(gt, zf, null)
        unexplained = [_row(t, "final", generic=True) for t in gt if t.df > 0 and t.p_adjusted < alpha * FALLBACK_SHARE]
    # and whether what is left is the noise the model says: structure it took in as slow noise (a field
    # varying slower than a hold resolves) left "consistent" with the noise floor three times the white noise
    white = whiteness(zf, null)
    white["p_adjusted"] = float(min(1.0, white["p_value"] * (len(generic_w) + 1)))
    if white["p_adjusted"] < alpha * FALLBACK_SHARE:
        unexplained.append({**white, "variant": WHITENESS})

    say("name and rank", 0.9)
    findings = []
    by_name = {f.name: f for f in found}
    penalty = _search_penalty(dic, found)
    for i, name in enumerate(terms):
        c = coef[offsets[i + 1]:offsets[i + 2]]
        cv = cov[offsets[i + 1]:offsets[i + 2], offsets[i + 1]:offsets[i + 2]]
        contrib = np.einsum("nip,p->ni", raw_cols[i + 1], c)
        t = final.get(name) or Test(name, np.zeros((len(zr), 0)))  # the test given every other effect kept
        row = {"statistic": t.statistic, "df": t.df, "p_value": t.p_value, "p_adjusted": t.p_adjusted}
        if name in by_name:
            # found by a search: its p pays for the dictionary's size and for the window's fitted edges,
            # as when it was chosen (the backward test alone counts only the round's catalogue tests)
            row["p_adjusted"] = float(min(1.0, t.p_value * np.exp(penalty[name])))
            absorbed = 0
            if name in ident:  # back to the block's own coefficients, none along what is taken in
                T = ident[name]
                c, cv, absorbed = T @ c, T @ cv @ T.T, T.shape[0] - T.shape[1]
            findings.append(discovered_finding(by_name[name], c, cv, contrib, row, nom, ctx,
                                               _heading_impact(ctx, y_raw, nom, contrib), absorbed))
            continue
        if name == LINE:
            row["p_adjusted"] = float(p_twin)  # paying for the frequency search, as when it was confirmed
        confusable = _confusable(name, selected, candidates, A0, z, alpha) if name != LINE else []
        tied = ties.get(name, [])
        findings.append(_finding(name, c, cv, eff, row, contrib, nom, ctx, y_raw, confusable, mains_hz, tied))
    findings = merge_windows(findings)
    for row in unexplained:
        said = (f"unexplained structure against {row['variant']}: neither the catalogue nor the dictionary of generic "
                "blocks accounts for it") if row["variant"] != WHITENESS else (
                f"unexplained structure in time: the residual is not the noise the noise model describes (Ljung-Box "
                f"over {WHITE_LAGS} lags per axis, {row['statistic']:.0f} for {row['df']} df). The model took part of "
                f"it in as slow noise (lag-1 correlation {_fmt_axes(noise.phi, '.3f')}, floor "
                f"{_fmt_axes(noise.floor, '.3g')} LSB against {_fmt_axes(noise.white, '.3g')} LSB of white noise): a "
                "field varying too slowly for a hold to resolve (a periodic disturbance of a few seconds), or a "
                "disturbance that comes and goes")
        findings.append({"effect": fx.UNEXPLAINED, **{k: row[k] for k in ("statistic", "df", "p_value", "p_adjusted")},
                         "parameters": {}, "sigma": {}, "heading_impact_deg": None, "where": {"against": row["variant"]},
                         "explanation": said, "confusable_with": [],
                         "separating_experiment": "" if row["variant"] != WHITENESS else
                         "hold one pose for a minute (or record continuously) and look at the readings' spectrum"})
    findings.extend(_parameter_findings(nom, calibration, A0, ctx))
    findings.sort(key=lambda f: (f["effect"] in (fx.UNEXPLAINED, fx.PARAMETER_SHIFT), -(f["heading_impact_deg"] or 0.0)))

    heading_before, heading_rms_before = _heading_error(ctx, y_raw, nom0)
    # after: the nominal parameters as refitted together with the effects, on readings with the
    # fitted effects taken out (what a compass that also corrected them would report)
    v_after = nom.v + coef[12:14] @ nom.basis
    nom_after = Nominal(nom.M + coef[:9].reshape(3, 3), nom.b + coef[9:12], v_after / np.linalg.norm(v_after), nom.basis)
    heading_after, heading_rms_after = _heading_error(ctx, y_raw - (fitted - np.einsum("nip,p->ni", J0, coef[:14])), nom_after)
    if not terms:
        heading_after, heading_rms_after = heading_before, heading_rms_before
    result: dict[str, Any] = {
        "verdict": "discrepancy" if any(departs(f) for f in findings) else "consistent",
        "model": "table",
        "samples": int(len(rec)),
        "duration_s": float(np.ptp(ctx.t)),
        "alpha": alpha,
        "noise_floor_lsb": noise.floor.tolist(),
        "noise_ar1": noise.phi.tolist(),
        "noise_white_lsb": noise.white.tolist(),
        "residual_rms_before_lsb": rms(r00).tolist(),
        "residual_rms_after_lsb": rms(r_after).tolist(),
        "heldout": {"scheme": "4 folds: whole holds (or 1-s chunks with fewer than 8 holds) and 1-s chunks of motion, "
                           "interleaved in time",
                    "rms_before_lsb": ho_before.tolist(), "rms_after_lsb": ho_after.tolist(),
                    "improvement_pct": float(100.0 * (1.0 - ho_after.mean() / max(ho_before.mean(), 1e-300)))},
        "heading_error_deg": {"before": heading_before, "after": heading_after,
                              "rms_before": heading_rms_before, "rms_after": heading_rms_after,
                              "noise_rms": _heading_noise(ctx, y_raw, nom0, noise)},
        "nominal": _nominal_json(nom),
        "findings": findings,
        "tests": all_tests,
        "untestable": untestable + discovery_untestable,
        "locate": locate(ctx, r00, noise.floor, candidates, Q0, z, null, generic_first),
        "notes": notes,
        "nominal_determined": not _free_nominal(A0),
    }
    if not result["nominal_determined"]:
        notes.append(f"these attitudes leave {_free_nominal(A0)} of the nominal model's 14 parameters (M, b, the field's "
                     "direction) free (a calibration needs turns about more than one axis): the nominal shown is not "
                     "the unit's, and it is neither judged nor compared with a calibration")
    result["summary"] = summary(result)
    say("done", 1.0)
    # the rows analysed (the recording's, or their block averages when it was decimated)
    series = {"t": ctx.t, "step": rec.step, "psi_t": rec.psi_t, "theta_t": rec.theta_t, "phi_t": rec.phi_t, "mag": y_raw,
              "residual_before": r00, "residual_after": r_after, "heldout_pred_before": pred_before,
              "heldout_pred_after": pred_after, "fold": fold}
    return Analysis(json_safe(result), series)


#: The catalogue's time lag, whose column a fitted lag rebuilds (`relinearise`), up to a lag of this size.
TIME_LAG = "time_lag"
MAX_LAG_S = 2.0

#: The fallback's test of the final residual against the noise model (`whiteness`), and its lags per axis.
WHITENESS = "whiteness (Ljung-Box on the prewhitened residual)"
WHITE_LAGS = 10


def _ljung_box(z: np.ndarray, lags: int) -> np.ndarray:
    """The Ljung-Box statistic summed over the three axes of each whitened residual in ``z`` ((3N,) or
    (K, 3N), axis-major as `whiten_all` stacks them)."""
    zz = np.atleast_2d(z)
    k = len(zz)
    return ljung_box(zz.reshape(3 * k, -1).T, lags).reshape(k, 3).sum(axis=1)


def whiteness(z: np.ndarray, null: np.ndarray | None, lags: int = WHITE_LAGS) -> dict[str, Any]:
    """Whether the whitened residual ``z`` is white, as the noise model says: Ljung-Box over ``lags`` lags
    on each axis, summed, scaled by its mean on the null residuals (which the noise model made and
    whitened as the data: the same estimate, the same segments), never lighter-tailed than chi-square."""
    df = 3 * lags
    q = float(_ljung_box(z, lags)[0])
    scale = max(1.0, float(np.mean(_ljung_box(null, lags))) / df) if null is not None and len(null) else 1.0
    return {"statistic": q, "df": df, "bartlett": scale, "p_value": float(stats.chi2.sf(q / scale, df))}


def _fmt_axes(v: Sequence[float], spec: str) -> str:
    return "(" + ", ".join(format(float(x), spec) for x in v) + ")"


def _row(t: Test, round_: int | str, selected: bool = False, generic: bool = False, **extra: Any) -> dict[str, Any]:
    """One test as the report lists it."""
    return {"effect": t.name.split(":")[0], "variant": t.name, "round": round_, "statistic": t.statistic, "df": t.df,
            "bartlett": t.bartlett, "p_value": t.p_value, "p_adjusted": t.p_adjusted, "selected": selected,
            "generic": generic, **extra}


class _Twin(NamedTuple):
    """The linear twin around one nominal fit: residual, nominal columns (raw and whitened), the whitened
    data (and with the nominal model projected out), and every testable effect's columns."""

    r0: np.ndarray
    J0: np.ndarray
    A0: np.ndarray
    Q0: np.ndarray
    zr: np.ndarray
    z: np.ndarray
    raw_of: dict[str, np.ndarray]
    candidates: dict[str, np.ndarray]


def _linearise(ctx: Context, y: np.ndarray, nom: Nominal, eff: dict, noise: NoiseModel, mains_hz: float | None) -> _Twin:
    """The twin linearised around ``nom`` and whitened with ``noise`` (the mains line's columns too, when
    one was found): once around the first fit, once again around the fit without the effects."""
    r0 = y - nom.predict(ctx)
    J0 = nominal_columns(ctx, nom)
    A0 = whiten_all(J0, noise, ctx.segment)
    Q0 = _orth(A0)
    zr = whiten_all(r0, noise, ctx.segment)
    raw_of = {name: X for name, (X, _, why) in eff.items() if not why}
    if mains_hz is not None:
        raw_of[LINE] = REGISTRY[LINE].line(ctx, mains_hz)
    candidates = {name: whiten_all(X, noise, ctx.segment) for name, X in raw_of.items()}
    return _Twin(r0, J0, A0, Q0, zr, zr - Q0 @ (Q0.T @ zr), raw_of, candidates)


def _forward(selected: list[str], found: list[Found], candidates: dict[str, np.ndarray], eff: dict,
             generic_w: dict[str, np.ndarray], dic: Dictionary, A0: np.ndarray, Q0: np.ndarray, z: np.ndarray,
             zr: np.ndarray,
             null: np.ndarray | None, alpha: float, gated: set[str], say: Progress,
             ties: dict[str, list[tuple[str, str]]] | None = None) -> list[dict[str, Any]]:
    """Forward selection (in place on ``selected`` catalogue effects and ``found`` discovered blocks);
    returns the test rows of every round. ``ties`` (in place): for a catalogue effect that won within
    :data:`CATALOGUE_PRIOR` over a significant discovered block, that block and those it could not be told
    from, each as its description and the experiment that would confirm it (the finding lists them as
    confusable).

    Each round the catalogue's tests (Bonferroni at its share of alpha) and the dictionary's (Bonferroni
    at the rest, its window search corrected on the nulls) say whether anything is there; of the
    significant candidates the one with the most evidence (`Test.evidence`) joins, a catalogue effect
    winning within :data:`CATALOGUE_PRIOR`. Plausibility is a gate: a significant catalogue effect whose
    fitted parameters (given the model so far) exceed the catalogue's plausible range is refused (added
    to ``gated``) and the next one is considered, so that the structure it would stand in for is left
    to discovery."""
    rows: list[dict[str, Any]] = []
    # alpha is shared between the two families (weighted Bonferroni): each is held to its share, so the
    # round's false-alarm rate stays alpha
    a_cat, a_dic = alpha * CATALOGUE_SHARE, alpha * DICTIONARY_SHARE
    for round_no in range(MAX_EFFECTS + MAX_BLOCKS):
        say(f"tests: round {round_no + 1}", min(0.55 + 0.03 * round_no, 0.69))
        Q = _extend(Q0, *[candidates[s] for s in selected], *[f.Xw for f in found])
        resid = z - Q @ (Q.T @ z)
        tests: dict[str, Test] = {}
        gtests: dict[str, Test] = {}
        best_name = None
        if sum(1 for s in selected if s != LINE) < MAX_EFFECTS:
            tests = {name: Test(name, _complement(Xw, Q)) for name, Xw in candidates.items()
                     if name not in selected and name not in gated}
            gtests = {name: Test(name, _complement(Xw, Q)) for name, Xw in generic_w.items()} if round_no == 0 else {}
            # round 1's family also holds the line search
            _score(list(tests.values()) + list(gtests.values()), resid, null, extra=1 if round_no == 0 else 0)
            for name in sorted((n for n, t in tests.items() if t.df > 0 and t.log_p < np.log(a_cat)),
                               key=lambda n: -tests[n].evidence):
                if name != LINE:
                    coef, _, off = _fit_terms(A0, [candidates[s] for s in selected] + [f.Xw for f in found]
                                              + [candidates[name]], zr)
                    if _implausible(name, coef[off[-2]:off[-1]], eff):
                        gated.add(name)
                        rows.append({**_row(tests[name], round_no + 1), "rejected": "implausible parameters"})
                        continue
                best_name = name
                break
            if best_name is not None:
                best_name = _simplest(best_name, {n: t for n, t in tests.items() if n not in gated}, candidates, Q,
                                      resid, null, a_cat, len(tests) + len(gtests) + 1)
        disc, cands = None, []
        if len(found) < MAX_BLOCKS:
            cands = dic.round(Q, resid, null, a_dic)
            disc = dic.choose(cands, Q, resid, null, a_dic)
        # both significant: the data's preference decides (evidence), a named effect winning a near tie
        if disc is not None and best_name is not None and tests[best_name].evidence + CATALOGUE_PRIOR >= disc.test.evidence:
            if ties is not None and tests[best_name].evidence < disc.test.evidence + CATALOGUE_PRIOR:
                # a near tie, not a clear win: the generic block explains it as well, and the finding says so
                # (a sensitivity following the temperature, 1.9 ahead, went unsaid behind a field drift)
                ties[best_name] = [(describe(c.block), confirming_experiment(c.block, c.segments))
                                   for c in [disc, *(c for c in cands if describe(c.block) in disc.alike)]]
            disc = None
        elif disc is not None:
            best_name = None
        rows += [_row(t, round_no + 1, selected=name == best_name, generic=name in gtests)
                 for name, t in {**tests, **gtests}.items() if name not in gated]
        rows += rows_of(cands, f"{round_no + 1} (dictionary)", disc)
        if best_name is not None:
            selected.append(best_name)
        elif disc is not None:
            found.append(disc)
        else:
            break
    return rows


def _refit_windows(dic: Dictionary, found: list[Found], terms: dict[str, np.ndarray], Q0: np.ndarray, z: np.ndarray,
                   null: np.ndarray | None, alpha: float, sweeps: int = 2) -> bool:
    """Each discovered window searched again given every other term (in place on ``found`` and ``terms``):
    forward selection takes the strongest window first, and where two departures overlap in time that
    is their union, which the next rounds then cancel piece by piece (a magnet on the unit and steel
    by the table made an outer-stage offset over both and middle-stage pieces undoing it). With the
    others in the model, the search on what is left finds the window the term stood in for; it
    replaces the term where its evidence is clearly larger (:data:`SAME_EVIDENCE`), and the backward
    check then drops the terms it made redundant. Whether anything changed."""
    changed = False
    searched: list[tuple[list[np.ndarray], Found | None]] = []  # the others' columns, what the search chose
    for _ in range(sweeps):
        moved = False
        for i, f in enumerate(found):
            if not f.block.windowed or f.name not in terms:
                continue
            Qo, y = _given_others(Q0, z, terms, f.name)
            mine = Test(f.name, _complement(f.Xw, Qo))
            mine.statistic, mine.search = float(np.sum((mine.basis.T @ y) ** 2)), f.test.search
            # given the same others the search finds the same block: a second sweep searches again only
            # where an earlier replacement changed what the term is fitted with
            others = [Xw for name, Xw in terms.items() if name != f.name]
            seen = [g for cols, g in searched if len(cols) == len(others) and all(a is b for a, b in zip(cols, others))]
            if seen:
                g = seen[0]
            else:
                g = dic.choose(dic.round(Qo, y, null, alpha), Qo, y, null, alpha)
                searched.append((others, g))
            if g is None or g.name in terms or g.test.evidence <= mine.evidence + SAME_EVIDENCE:
                continue
            renamed = _replaced(terms, f.name, g)
            terms.clear()
            terms.update(renamed)
            found[i] = g
            moved = changed = True
        if not moved:
            break
    return changed


def _reconsider(dic: Dictionary, found: list[Found], terms: dict[str, np.ndarray], Q0: np.ndarray, z: np.ndarray,
                null: np.ndarray | None, alpha: float) -> tuple[list[Found], dict[str, np.ndarray]]:
    """Each discovered window's frame and form chosen again given every other term (``Dictionary.reconsider``),
    once all are in: departures that overlap in time were each first seen with the other's share in the
    residual. ``terms`` keeps its order, a reconsidered block in its predecessor's place."""
    if len(terms) < 2:
        return found, terms
    out = list(found)
    for i, f in enumerate(found):
        g = dic.reconsider(f, *_given_others(Q0, z, terms, f.name), null, alpha)
        if g.block != f.block:
            terms = _replaced(terms, f.name, g)
            out[i] = g
    return out, terms


def _given_others(Q0: np.ndarray, z: np.ndarray, terms: dict[str, np.ndarray], name: str) -> tuple[np.ndarray, np.ndarray]:
    """The span of the nominal model and every term but ``name`` (orthonormal), and ``z``'s residual off it."""
    Qo = _extend(Q0, *(Xw for other, Xw in terms.items() if other != name))
    return Qo, z - Qo @ (Qo.T @ z)


def _replaced(terms: dict[str, np.ndarray], name: str, g: Found) -> dict[str, np.ndarray]:
    """``terms`` with ``g`` in the place of term ``name`` (the order kept: the fit's offsets follow it)."""
    return {(g.name if other == name else other): (g.Xw if other == name else Xw) for other, Xw in terms.items()}


def _search_penalty(dic: Dictionary, found: list[Found]) -> dict[str, float]:
    """Each discovered block's log Bonferroni correction: the dictionary's size (by prior weight) and
    its window search, as when it was chosen."""
    return {f.name: float(np.log(dic.cost(f.block)) + f.test.search) for f in found}


def _backward(terms: dict[str, np.ndarray], Q0: np.ndarray, z: np.ndarray, null: np.ndarray | None, alpha: float,
              m: int, rows: list[dict[str, Any]], penalty: dict[str, float] | None = None) -> dict[str, Test]:
    """Backward check (in place on ``terms``): forward selection can take a many-parameter effect first
    that only stands in for a simpler one chosen after it, or a catalogue effect that stands in for a
    discovered block. Each term must stay significant given all the others (corrected over ``m``
    tests; a term in ``penalty`` by its own log correction instead: a discovered block pays for the
    dictionary and its window's fitted edges, as its report does); the weakest that does not is
    dropped, until all do. Returns each kept term's test."""
    penalty = penalty or {}
    final: dict[str, Test] = {}
    while terms:
        final = {}
        # every test's bases within the span of the whole model, in its orthonormal coordinates: the
        # same numbers as a tall decomposition per term (each term's columns lie in that span), at the
        # cost of one
        Qf = _extend(Q0, *terms.values())
        coords = {name: Qf.T @ Xw for name, Xw in terms.items()}
        q0 = Q0.shape[1]
        for name in terms:
            others = [C for o, C in coords.items() if o != name]
            Qo = _extend(np.eye(Qf.shape[1], q0), *others)
            t = Test(name, Qf @ _complement(coords[name], Qo))
            _score([t], z - Qf @ (Qo @ (Qo.T @ (Qf.T @ z))), null, extra=m - 1)
            if name in penalty and t.df > 0:  # its own correction in place of the catalogue's m
                t.log_p = float(min(0.0, t.log_p - np.log(m) + penalty[name]))
                t.p_adjusted = float(min(1.0, t.p_value * np.exp(penalty[name])))
            final[name] = t
        weakest = max(terms, key=lambda nm: final[nm].log_p)
        if final[weakest].log_p < np.log(alpha):
            break
        del terms[weakest]
        rows.append(_row(final[weakest], "backward", dropped=True))
    return final


#: A block's coefficient combination whose whitened column keeps less than this share of its squared norm
#: beyond the other columns is taken in by them (the tests' :func:`_complement` threshold).
ABSORBED_RCOND = 1e-6


def _identifiable(terms: dict[str, np.ndarray], name: str, A0: np.ndarray) -> np.ndarray:
    """The map T (p, q) from the q coefficient combinations of term ``name`` that the data determine beyond
    the nominal columns ``A0`` and the other terms to its p coefficients (``c = T @ c_q``): the
    combinations its test counted as degrees of freedom. q == p when nothing of it is taken in."""
    X = terms[name]
    norm = np.linalg.norm(X, axis=0)
    nz = norm > 0
    Q = _orth(np.column_stack([A0] + [Xw for other, Xw in terms.items() if other != name]))
    Xn = X[:, nz] / norm[nz]
    Xp = Xn - Q @ (Q.T @ Xn)
    lam, V = np.linalg.eigh(Xp.T @ Xp)
    keep = lam > ABSORBED_RCOND
    T = np.zeros((X.shape[1], int(keep.sum())))
    T[nz] = V[:, keep] / norm[nz][:, None]
    return T


def _fit_identified(A0: np.ndarray, terms: dict[str, np.ndarray], found: list[Found], zr: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """:func:`_fit_terms` with each discovered block reduced to the combinations the data determine
    (:func:`_identifiable`), and the maps T of the blocks reduced (their coefficients are ``T @ c``).

    The combinations the other columns take in (its test counted none of them) are left out: fitted, they
    came out at hundreds of LSB +- as much (an offset following the accelerometer of 8 LSB per g was
    reported as 1800 LSB with 9.3 deg of heading impact), and the nominal model refitted without them was
    pulled as far the other way (its heading 15 deg off), so the twin linearised there made the level
    heading after worse."""
    ident = {f.name: _identifiable(terms, f.name, A0) for f in found if f.name in terms}
    ident = {name: T for name, T in ident.items() if T.shape[1] < T.shape[0]}
    coef, cov, offsets = _fit_terms(A0, [Xw if name not in ident else Xw @ ident[name] for name, Xw in terms.items()], zr)
    return coef, cov, offsets, ident


def _fitted_columns(raw_of: dict[str, np.ndarray], terms: dict[str, np.ndarray], ident: dict[str, np.ndarray]
                    ) -> list[np.ndarray]:
    """Each term's raw columns (N, 3, p) as :func:`_fit_identified` fitted them (a reduced block's: ``X @ T``)."""
    return [raw_of[s] if s not in ident else raw_of[s] @ ident[s] for s in terms]


def _fit_terms(A0: np.ndarray, parts: list[np.ndarray], zr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened least squares of the nominal columns and ``parts``: coefficients, covariance, and the
    offset of each part's coefficients (part i: offsets[i + 1]:offsets[i + 2])."""
    coef, cov = _lstsq_cov(np.column_stack([A0] + parts), zr)
    return coef, cov, np.cumsum([0, A0.shape[1]] + [p.shape[1] for p in parts])


def _implausible(name: str, c: np.ndarray, eff: dict) -> list[str]:
    """The parameters of catalogue effect ``name`` (coefficients ``c``) beyond its plausible range."""
    params, _ = parameters(name, c, np.zeros_like(c), eff[name][1])  # sizes only: the sigma is not needed
    return _beyond_plausible(name, params)


def _beyond_plausible(name: str, params: dict[str, Any]) -> list[str]:
    """The named parameters of effect variant ``name`` beyond the catalogue's plausible range."""
    entry = fx.CATALOGUE[name.split(":")[0]]
    return [k for k, lim in entry.plausible.items()
            if k in params and np.max(np.abs(np.asarray(params[k], float))) > lim]


def _simplest(best: str, tests: dict[str, "Test"], candidates: dict[str, np.ndarray], Q: np.ndarray, resid: np.ndarray,
              null: np.ndarray | None, alpha: float, m: int) -> str:
    """The effect to add: ``best`` (smallest corrected p), unless an effect with fewer parameters is
    significant too and, once in the model, leaves nothing significant for ``best`` to add; then the
    simplest such one. Smallest p alone favours the effect with more parameters whenever it contains a
    simpler one (soft iron on a stage spans a magnet on it at one azimuth)."""
    simpler = sorted((t.df, t.log_p, name) for name, t in tests.items()
                     if 0 < t.df < tests[best].df and t.log_p < np.log(alpha))
    for _, _, name in simpler:
        Qs = _extend(Q, candidates[name])
        given = Test(best, _complement(candidates[best], Qs))
        _score([given], resid - Qs @ (Qs.T @ resid), null, extra=m - 1)
        if given.df == 0 or given.log_p >= np.log(alpha):
            return name
    return best


def _lstsq_cov(A: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares on whitened data with the coefficients' covariance. A combination the design
    cannot determine (e.g. an effect's component the nominal model absorbs) gets the minimum-norm
    estimate and infinite variance on every coefficient it involves."""
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    An = A / scale
    # An = Q R (Q^T y without forming Q), then R's small SVD: An's singular values and right vectors
    # for half the cost of An's own SVD
    (Qty,), R = linalg.qr_multiply(An, y[None, :], mode="right")
    U, s, Vt = np.linalg.svd(R)
    keep = s > 1e-9 * s[0]
    inv = np.zeros_like(s)
    inv[keep] = 1.0 / s[keep]
    coef = (Vt.T * inv) @ (U.T @ Qty) / scale
    cov = (Vt.T * inv ** 2) @ Vt / np.outer(scale, scale)
    if not keep.all():
        lost = np.max(np.abs(Vt[~keep]), axis=0) > 0.05
        cov[lost, :] = cov[:, lost] = 0.0
        cov[lost, lost] = np.inf
    return coef, cov


def _confusable(name: str, selected: list[str], candidates: dict[str, np.ndarray], A0: np.ndarray, z: np.ndarray,
                alpha: float) -> list[str]:
    """Other effects that, put in the model instead, leave ``name`` insignificant while being
    significant themselves: this recording cannot tell them apart."""
    out = []
    others = [s for s in selected if s != name]
    base = np.column_stack([A0] + [candidates[s] for s in others]) if others else A0
    Qb = _orth(base)
    zb = z - Qb @ (Qb.T @ z)
    own = Test(name, _complement(candidates[name], Qb))
    _score([own], zb, None)
    for other, Xw in candidates.items():
        if other in selected or other.split(":")[0] == name.split(":")[0] or other == LINE:
            continue
        alone = Test(other, _complement(Xw, Qb))
        if alone.df == 0:
            continue
        _score([alone], zb, None)
        if alone.p_value > alpha / 10:
            continue
        Qo = _extend(Qb, Xw)
        given = Test(name, _complement(candidates[name], Qo))
        _score([given], z - Qo @ (Qo.T @ z), None)
        if given.df == 0 or given.p_value > alpha:
            out.append(other.split(":")[0])
    return sorted(set(out))


def _finding(name: str, c: np.ndarray, cv: np.ndarray, eff: dict, row: dict, contrib: np.ndarray, nom: Nominal,
             ctx: Context, y: np.ndarray, confusable: list[str], mains_hz: float | None,
             tied: Sequence[tuple[str, str]] = ()) -> dict[str, Any]:
    """A catalogue effect's finding. ``tied``: discovered blocks it won a near tie against (:func:`_forward`),
    each (description, the experiment that would confirm it), listed as confusable."""
    effect = name.partition(":")[0]
    entry = fx.CATALOGUE[effect]
    sd = np.sqrt(np.maximum(np.diag(cv), 0.0))  # inf: not determined by this recording (absorbed)
    # the line effect has no columns in eff (a search found its frequency): no labels
    params, sigma = parameters(name, c, sd, eff[name][1] if name in eff else [], mains_hz)
    impact = _heading_impact(ctx, y, nom, contrib)
    implausible = _beyond_plausible(name, params)
    where = _where(name, ctx, contrib)
    explanation = f"{entry.title}: {entry.description} Signature: {entry.signature}."
    frame, form, against = entry.model
    tied = [(d, e) for d, e in dict(tied).items() if d != f"{form} in the {frame} frame against {against}"]  # not itself
    if np.isinf(sd).any():
        labels = eff[name][1] if name in eff else []
        lost = [labels[i] for i in np.flatnonzero(np.isinf(sd))] if labels else []
        explanation += (f" This recording cannot determine {', '.join(lost)} (the nominal model absorbs that part; "
                        f"sigma null): {entry.needs}.")
    if implausible:
        explanation += f" The fitted {', '.join(implausible)} exceed what is plausible for this effect."
    return {"effect": effect, "statistic": row["statistic"], "df": row["df"], "p_value": row["p_value"],
            "p_adjusted": row["p_adjusted"], "parameters": params, "sigma": sigma, "heading_impact_deg": impact,
            "where": where, "explanation": explanation,
            "confusable_with": [*confusable, *(d for d, _ in tied if d not in confusable)], "plausible": not implausible,
            "separating_experiment": "; ".join([fx.separating_experiment(effect, o) for o in confusable]
                                               + ([f"to tell it from {tied[0][0]}: {tied[0][1]}"] if tied else []))}


def _where(name: str, ctx: Context, contrib: np.ndarray) -> dict[str, Any]:
    """Where the fitted effect (variant ``name``) acts: axis, steps, frame, and what its registry entry adds
    (a lag's direction of travel)."""
    rms_axis = np.sqrt(np.mean(contrib ** 2, axis=0))
    steps = {}
    for s in np.unique(ctx.rec.step):
        m = ctx.rec.step == s
        steps[str(s)] = float(np.sqrt(np.mean(contrib[m] ** 2)))
    out: dict[str, Any] = {"axis": "xyz"[int(np.argmax(rms_axis))], "rms_lsb": rms_axis.tolist(),
                           "steps": dict(sorted(steps.items(), key=lambda kv: -kv[1])[:5]), "frame": frame_of(name)}
    return {**out, **where_extra(name, ctx, contrib)}


def _level(ctx: Context) -> np.ndarray:
    return (np.abs(wrap180(ctx.ang[:, 1])) < 0.01) & (np.abs(wrap180(ctx.ang[:, 2])) < 0.01)


def _corrected_heading(raw: np.ndarray, nom: Nominal, R: np.ndarray) -> np.ndarray:
    """Heading with the nominal calibration, levelled with the table's attitude R."""
    if np.linalg.cond(nom.M) > 1e8:  # attitudes that cannot determine M (e.g. one pose): no heading
        return np.full(len(raw), np.nan)
    h = np.linalg.solve(nom.M, (raw - nom.b).T).T
    return magnetic_heading(h, np.einsum("nji,j->ni", R, SPECIFIC_FORCE_L))


def _heading_impact(ctx: Context, y: np.ndarray, nom: Nominal, contrib: np.ndarray) -> float | None:
    """Largest heading change the fitted effect makes, over the recording's attitudes within 60 deg of level."""
    ok = np.all(np.abs(wrap180(ctx.ang[:, 1:])) <= 60.0, axis=1)
    if not ok.any():
        return 0.0
    d = wrap180(_corrected_heading(y[ok], nom, ctx.R[ok]) - _corrected_heading(y[ok] - contrib[ok], nom, ctx.R[ok]))
    return float(np.max(np.abs(d))) if np.isfinite(d).all() else None


def _hold_means(ctx: Context, y: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``y`` over each hold among ``rows`` (a mask of samples in holds), and each hold's first sample."""
    g = ctx.hold[rows]
    n = np.bincount(g)
    keep = n > 0
    mean = np.column_stack([np.bincount(g, y[rows][:, j])[keep] / n[keep] for j in range(3)])
    return mean, np.flatnonzero(rows)[[np.flatnonzero(g == i)[0] for i in np.flatnonzero(keep)]]


def _heading_error(ctx: Context, y: np.ndarray, nom: Nominal) -> tuple[float | None, float | None]:
    """Level heading error of hold means, with the nominal calibration, against the table: its maximum
    and its RMS over the level holds (PHYSICS.md reports both)."""
    lev = _level(ctx) & (ctx.hold >= 0)
    if not lev.any():
        return None, None
    mean, first = _hold_means(ctx, y, lev)
    _, dec = field_angles(nom.v)
    err = wrap180(_corrected_heading(mean, nom, ctx.R[first]) - (ctx.ang[first, 0] - dec))
    if not np.isfinite(err).all():
        return None, None
    return float(np.max(np.abs(err))), float(np.sqrt(np.mean(err * err)))


def _mean_variance(n: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """Variance of the mean of ``n`` consecutive samples (holds, (H,)) per axis under the AR(1)-plus-white
    noise model: (H, 3). The AR part's sum over all pairs, sum_ij phi^|i-j|, in closed form."""
    n = np.asarray(n, float)[:, None]
    p = np.clip(noise.phi, 0.0, 0.999999)[None, :]
    pairs = n * (1 + p) / (1 - p) - 2 * p * (1 - p ** n) / (1 - p) ** 2
    return noise.sigma[None, :] ** 2 * pairs / n ** 2 + noise.white[None, :] ** 2 / n


def _heading_noise(ctx: Context, y: np.ndarray, nom: Nominal, noise: NoiseModel) -> float | None:
    """RMS over the level holds of the heading error that the readings' noise alone makes in each hold's
    mean (deg): the scale below which a level heading error measures the noise, not the calibration, and
    a change between two models is no improvement one could show. Each hold's heading is linearised in
    its mean reading; the mean's variance is the noise model's for that many consecutive samples."""
    lev = _level(ctx) & (ctx.hold >= 0)
    if not lev.any():
        return None
    mean, first = _hold_means(ctx, y, lev)
    n = np.bincount(ctx.hold[lev])
    n = n[n > 0]
    R = ctx.R[first]
    step = 0.5
    grad = np.stack([wrap180(_corrected_heading(mean + step * e, nom, R) - _corrected_heading(mean - step * e, nom, R))
                     / (2 * step) for e in np.eye(3)], axis=1)  # deg per LSB, (H, 3)
    var = np.sum(grad ** 2 * _mean_variance(n, noise), axis=1)
    return float(np.sqrt(np.mean(var))) if np.all(np.isfinite(var)) else None


def level_heading_error(rec: Recording) -> tuple[float | None, float | None]:
    """The level heading error (maximum, RMS over the level holds, deg) of the nominal model fitted to
    ``rec`` alone: what an analysis of ``rec`` reports as "before". The blind proof computes it on a
    recording without its concealed effect (the same noise) to measure what a perfect model of the
    effect could bring the level heading error down to."""
    ctx = context(rec)
    y = np.asarray(rec.mag, float)
    return _heading_error(ctx, y, fit_nominal(ctx, y))


def _folds(ctx: Context) -> np.ndarray:
    """Fold of each sample: whole holds interleaved (a hold is predicted from the others), motion in
    1-s chunks; a recording of fewer than 8 holds is cut into 1-s chunks throughout."""
    chunk = np.floor((ctx.t - ctx.t[0]) / 1.0).astype(int)
    if ctx.hold.max() < 7:
        return chunk % 4
    fold = np.empty(len(ctx.t), int)
    h = ctx.hold >= 0
    fold[h] = ctx.hold[h] % 4
    fold[~h] = (chunk[~h] + 1) % 4
    return fold


def _heldout(ctx: Context, y: np.ndarray, nom: Nominal, cols: list[np.ndarray], fold: np.ndarray,
             sigma: np.ndarray) -> np.ndarray:
    """Each sample predicted by the linear twin fitted to the other folds (axis-weighted least squares)."""
    X = np.concatenate(cols, axis=2)
    base = nom.predict(ctx)
    r0 = y - base
    pred = np.empty_like(y)
    for f in np.unique(fold):
        train = fold != f
        A = np.concatenate([X[train, j, :] / sigma[j] for j in range(3)], axis=0)
        b = np.concatenate([r0[train, j] / sigma[j] for j in range(3)])
        coef, _ = _lstsq_cov(A, b)
        test = ~train
        pred[test] = base[test] + np.einsum("nip,p->ni", X[test], coef)
    return pred


def _nominal_json(nom: Nominal) -> dict[str, Any]:
    M_o, k = split_matrix(nom.M)
    inc, dec = field_angles(nom.v)
    return {"M_o": M_o.tolist(), "k": k.tolist(), "bias": nom.b.tolist(), "inclination_deg": inc,
            "declination_deg": dec}


def _free_nominal(A0: np.ndarray) -> int:
    """How many of the nominal model's parameters (M, b, the field's direction) the recording's attitudes
    leave free (0: all determined; a level turn alone leaves the z axis's)."""
    return int(A0.shape[1] - np.linalg.matrix_rank(A0 / np.maximum(np.linalg.norm(A0, axis=0), 1e-300), tol=1e-6))


def _parameter_findings(nom: Nominal, cal: Calibration | None, A0: np.ndarray, ctx: Context) -> list[dict[str, Any]]:
    """Absorbed effects show as implausible nominal parameters, or as shifts from the unit's calibration."""
    if _free_nominal(A0):
        return []  # the attitudes cannot determine M, b and the field: nothing to judge them by
    M_o, k = split_matrix(nom.M)
    problems: dict[str, Any] = {}
    mis = np.degrees(np.arccos(np.clip(np.abs(np.diag(M_o)), -1, 1)))
    if mis.max() > MAX_MISALIGNMENT_DEG:
        problems["misalignment_deg"] = mis.tolist()
    if np.ptp(k) / np.median(k) > MAX_K_MISMATCH:
        problems["k_mismatch"] = float(np.ptp(k) / np.median(k))
    if np.max(np.abs(nom.b) / k) > MAX_BIAS_FIELDS:
        problems["bias_in_fields"] = (np.abs(nom.b) / k).tolist()
    shifts: dict[str, Any] = {}
    if cal is not None:
        _, cov0 = _lstsq_cov(A0, np.zeros(A0.shape[0]))
        sd_b = np.sqrt(np.maximum(np.diag(cov0)[9:12], 0.0))
        cal_sd_b = np.asarray(cal.sigma.get("bias", np.zeros(3)) if cal.sigma.get("bias") is not None else np.zeros(3), float)
        db = nom.b - cal.mag.bias
        z_b = db / np.sqrt(sd_b ** 2 + cal_sd_b ** 2 + 1.0)  # +1 LSB^2: quantisation of the stored numbers
        dk = k / cal.mag.k - 1.0
        dang = M_o_angle_change(M_o, cal.mag.M_o)
        if np.any(np.abs(z_b) > 5) and np.max(np.abs(db)) > 5:
            shifts["bias_lsb"] = db.tolist()
        if np.max(np.abs(dk)) > 0.005:
            shifts["k_relative"] = dk.tolist()
        if np.max(dang) > 0.2:
            shifts["axis_change_deg"] = dang.tolist()
    if not problems and not shifts:
        return []
    what = []
    if "bias_lsb" in shifts or "bias_in_fields" in problems:
        what.append("a magnet on the platform or near the unit, or a temperature offset, moves the bias")
    if {"k_relative", "axis_change_deg", "k_mismatch", "misalignment_deg"} & (shifts.keys() | problems.keys()):
        what.append("soft iron on the platform, or a changed mounting, moves the matrix M")
    unusual = [text for key, text in (
        ("k_mismatch", f"axis sensitivities {100 * problems.get('k_mismatch', 0.0):.0f} % apart (beyond {100 * MAX_K_MISMATCH:.0f} %)"),
        ("misalignment_deg", f"an axis {max(problems.get('misalignment_deg', [0.0])):.1f} deg off its body axis (beyond {MAX_MISALIGNMENT_DEG:g})"),
        ("bias_in_fields", f"a bias of {max(problems.get('bias_in_fields', [0.0])):.1f} times the field (beyond {MAX_BIAS_FIELDS:g})"))
        if key in problems]
    said = ("The nominal model absorbs this completely, so it shows as parameters, not residuals: " + "; ".join(what) + ".")
    if not shifts:
        # no calibration to compare with: the model fits these readings, the parameters are only unusual for a unit
        said = ("The recording's own fit is unusual for one unit (" + "; ".join(unusual) + "), though it fits the "
                "readings to their noise: discrete sensors, or a unit assembled so, give it; or " + "; or ".join(what)
                + ". Not a departure by itself: compare with the unit's calibration (--calibration) to see whether it changed.")
    return [{"effect": fx.PARAMETER_SHIFT, "statistic": None, "df": None, "p_value": None, "p_adjusted": None,
             "parameters": {**problems, **shifts}, "sigma": {}, "heading_impact_deg": None,
             "where": {"frame": "platform (absorbed by the nominal model)"},
             "explanation": said,
             "confusable_with": [], "separating_experiment":
                 "calibrate again with the suspected part removed, or compare with the unit's calibration on another station"}]


#: A parameter shift's parameters that compare the recording's fit with the unit's own calibration.
SHIFT_KEYS = ("bias_lsb", "k_relative", "axis_change_deg")


def departs(finding: dict[str, Any]) -> bool:
    """Whether a finding is a departure from the model or the unit (what makes the verdict a discrepancy): every
    finding but a parameter shift that only says the recording's own fit is unusual for a unit (its axes'
    sensitivities far apart, say), which the nominal model fits to the noise. Discrete sensors differ by more
    than one chip's axes do; a unit's departure from its own calibration is a departure."""
    return finding["effect"] != fx.PARAMETER_SHIFT or any(k in finding["parameters"] for k in SHIFT_KEYS)


def M_o_angle_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (deg) between corresponding sensor axes of two M_o."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def locate(ctx: Context, r0: np.ndarray, sigma: np.ndarray, candidates: dict, Q0: np.ndarray, z: np.ndarray,
           null: np.ndarray | None, generic: dict[str, dict]) -> dict[str, Any]:
    """Where the nominal residual lives: axis, step, harmonics against each angle, time, direction, frame,
    whiteness, witness channels."""
    rms = np.sqrt(np.mean(r0 ** 2, axis=0))
    by_step = []
    for s in dict.fromkeys(ctx.rec.step.tolist()):
        m = ctx.rec.step == s
        by_step.append({"step": str(s), "samples": int(m.sum()), "rms_lsb": np.sqrt(np.mean(r0[m] ** 2, axis=0)).tolist(),
                        "mean_lsb": r0[m].mean(axis=0).tolist()})
    harmonics: dict[str, Any] = {}
    for j, name in enumerate(("psi_t", "theta_t", "phi_t")):
        if np.ptp(ctx.ang[:, j]) < 30.0:
            continue
        a = np.radians(ctx.ang[:, j])
        amp = []
        for m in (1, 2, 3, 4):
            F = np.column_stack([np.cos(m * a), np.sin(m * a), np.ones_like(a)])
            coef, *_ = np.linalg.lstsq(F, r0, rcond=None)
            amp.append(np.hypot(coef[0], coef[1]).tolist())
        harmonics[name] = {"orders": [1, 2, 3, 4], "amplitude_lsb": amp}
    time: dict[str, Any] = {}
    tt = ctx.t - ctx.t.mean()
    slope = (tt @ r0) / max(tt @ tt, 1e-300)
    time["trend_lsb_per_min"] = (60.0 * slope).tolist()
    hold_keys = {}
    for h in np.unique(ctx.hold[ctx.hold >= 0]):
        i = np.flatnonzero(ctx.hold == h)
        hold_keys.setdefault(tuple(np.round(ctx.ang[i[0]], 2)), []).append(i)
    repeats = [v for v in hold_keys.values() if len(v) >= 2]
    if repeats:
        first, last = repeats[0][0], repeats[0][-1]
        time["repeated_pose"] = {"angles": list(np.round(ctx.ang[first[0]], 2)), "dt_s": float(ctx.t[last[0]] - ctx.t[first[0]]),
                                 "difference_lsb": (r0[last].mean(axis=0) - r0[first].mean(axis=0)).tolist()}
    hm = ctx.hold >= 0
    if hm.sum() > 10:
        g = ctx.hold[hm]
        n = np.bincount(g)
        ok = n > 0
        means = np.column_stack([np.bincount(g, r0[hm][:, j])[ok] / n[ok] for j in range(3)])
        c = np.cumsum(means - means.mean(axis=0), axis=0)
        k = int(np.argmax(np.sum(c ** 2, axis=1)))
        t_hold = np.bincount(g, ctx.t[hm])[ok] / n[ok]
        time["change_point_t_s"] = float(t_hold[k])
    direction: dict[str, Any] = {}
    if ctx.moving.sum() >= 20:
        w = ctx.rate
        for j, name in enumerate(("psi", "theta", "phi")):
            pos, neg = ctx.moving & (w[:, j] > 1), ctx.moving & (w[:, j] < -1)
            if pos.any() and neg.any():
                direction[name] = {"positive_mean_lsb": r0[pos].mean(axis=0).tolist(),
                                   "negative_mean_lsb": r0[neg].mean(axis=0).tolist(),
                                   "speeds_dps": sorted({float(np.round(abs(x), 0)) for x in w[ctx.moving, j] if abs(x) > 1})[:6]}
    frame = {}
    for name in ("stage_hard_iron:outer", "stage_hard_iron:middle", "field_drift", "temperature_drift"):
        if name in candidates:
            t = Test(name, _complement(candidates[name], Q0))
            _score([t], z, null)
            frame[{"stage_hard_iron:outer": "fixed in the outer stage", "stage_hard_iron:middle": "fixed in the middle stage",
                   "field_drift": "drifting in the lab frame", "temperature_drift": "drifting in the sensor frame"}[name]] = {
                "statistic": t.statistic, "df": t.df, "p_value": t.p_value}
    lb = [{"ljung_box_q": float(q), "lags": 10, "p_value": float(stats.chi2.sf(q, 10))}
          for q in ljung_box(z.reshape(3, -1).T, 10)]
    witness = {name: {"statistic": row["statistic"], "df": row["df"], "p_value": row["p_value"]}
               for name, row in generic.items()}
    return {"by_axis": {"rms_lsb": rms.tolist(), "dominant": "xyz"[int(np.argmax(rms / sigma))]},
            "by_step": by_step, "harmonics": harmonics, "time": time, "direction": direction, "frame": frame,
            "whiteness": {"per_axis": lb}, "witness": witness}
