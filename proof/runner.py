"""The blind proof's runner: the cases as picklable tasks, each generated and analysed in a worker
process that sees only the noisy recording, and the whole proof (:func:`run_proof`).

This is the only module of the proof that imports the analyser (physics.discrepancy), and only inside
:func:`run_task`, in the worker: the generator never sees it. It spawns processes and sets the BLAS
thread variables of their environment, which is why the proof lives outside physics/.
"""

from __future__ import annotations

import os
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from itertools import combinations
from multiprocessing import get_context
from typing import Any, Callable, Sequence

import numpy as np

from physics.calibration import json_safe
from physics.simulate import Pose, Scan
from physics.table import Motion
from proof.concealments import OPEN_KINDS
from proof.generator import (EFFECTS, LARGE_NC_RANGE, NC_RANGE, PAIR_NC_RANGE, Case, log_uniform, make_case,
                             make_open_case, ordinary_plan)
from proof.handheld import HANDHELD_KINDS, handheld_jobs, make_handheld_case
from proof.score import Outcome, judge_model, judge_open, score, score_handheld


def heldout_ratio(case: Case, series: dict[str, np.ndarray], key: str = "heldout_pred_after") -> float | None:
    """Held-out residual RMS of the analyser's final model (``key``: or of its nominal model) over
    that of the true model (1: as good as the truth), over all rows and axes."""
    if case.rec is None or case.clean is None or key not in series:
        return None
    pred = np.asarray(series[key], dtype=float)
    if pred.shape != case.rec.mag.shape:
        return None
    ok = np.all(np.isfinite(pred), axis=1)
    if not ok.any():
        return None
    ours = np.sqrt(np.mean((case.rec.mag[ok] - pred[ok]) ** 2))
    true = np.sqrt(np.mean((case.rec.mag[ok] - case.clean.mag[ok]) ** 2))
    return float(ours / true) if true > 0 else None


@dataclass(frozen=True)
class Task:
    """One case to generate and analyse (everything a worker process needs; picklable)."""

    index: int
    kind: str
    seed: int
    target_nc: dict[str, float] | None
    plan: tuple[Pose | Scan, ...]
    motion: Motion
    analyze_kwargs: dict[str, Any] = field(default_factory=dict)
    generator: str = "catalogue"  # "catalogue" (proof.generator.make_case) or "open" (make_open_case)


def make_task_case(task: Task, rng: np.random.Generator) -> Case:
    """The case of ``task`` from its generator's draw (the generation half of :func:`run_task`)."""
    if task.generator == "open":
        target = None if task.target_nc is None else task.target_nc.get(task.kind)
        return make_open_case(task.kind, rng, task.plan, target, task.motion, seed=task.seed)
    return make_case(task.kind, rng, task.plan, task.target_nc, task.motion, seed=task.seed)


def run_task(task: Task) -> tuple[int, Case, Outcome]:
    """Generate one case, hand its noisy recording (only) to the analyser, time it. Top level for spawn.

    For an open-world case, also the level heading error of the nominal model fitted to the same recording
    without the effect (``Outcome.heading_free``): what a perfect model of the effect could bring it down to."""
    from physics.discrepancy import analyze, level_heading_error  # imported here only, never by the generator

    gen, ana = np.random.SeedSequence(task.seed).spawn(2)
    case = make_task_case(task, np.random.default_rng(gen))
    assert case.rec is not None
    rec = case.rec.select(slice(None))  # a copy: nothing the analyser does can touch the truth
    t0 = time.perf_counter()
    try:
        a = analyze(rec, seed=ana, **task.analyze_kwargs)
    except Exception as e:  # noqa: BLE001 - a crash is a result of the proof, scored and reported
        out = Outcome(None, None, time.perf_counter() - t0, f"{type(e).__name__}: {e}")
    else:
        secs = time.perf_counter() - t0
        out = Outcome(a.result, heldout_ratio(case, a.series), secs, None,
                      heldout_ratio(case, a.series, "heldout_pred_before"))
    if case.generator == "open" and case.effects and case.free is not None:
        out = replace(out, heading_free=level_heading_error(case.free)[1])
    return task.index, replace(case, rec=None, clean=None, free=None), out


def _stratified(rng: np.random.Generator, n: int, nc_range: tuple[float, float] = NC_RANGE) -> list[float]:
    """``n`` non-centralities log-uniform over ``nc_range``, one in each of n equal log-intervals, shuffled."""
    lo, hi = np.log(nc_range[0]), np.log(nc_range[1])
    u = (np.arange(n) + rng.uniform(0.0, 1.0, n)) / max(n, 1)
    return [float(np.exp(lo + x * (hi - lo))) for x in rng.permutation(u)]


def proof_tasks(n: int, seed: int, plan: Sequence[Pose | Scan], nulls: int | None = None, pairs: int | None = None,
                motion: Motion = Motion(), analyze_kwargs: dict[str, Any] | None = None,
                pair_nc: tuple[float, float] = PAIR_NC_RANGE, open_n: int = 0,
                open_plan: Sequence[Pose | Scan] | None = None, open_nulls: int = 0,
                open_kinds: Sequence[str] = OPEN_KINDS, open_large: int = 0) -> list[Task]:
    """The proof's cases: ``n`` per catalogue effect at non-centralities spread log-uniformly over
    [3, 300] (stratified: one draw in each of n equal log-intervals), ``nulls`` nulls (default
    max(3 n, 20)), ``pairs`` pairs (default n // 2) of different effects drawn from all pairs, each
    effect at its own target log-uniform in ``pair_nc`` (see :data:`PAIR_NC_RANGE`), all on ``plan``;
    then ``open_n`` per open-world kind of ``open_kinds`` (stratified the same way), ``open_nulls``
    nulls of the open world's draw, and ``open_large`` per kind stratified over :data:`LARGE_NC_RANGE`,
    on ``open_plan`` (default: proof.generator.ordinary_plan).

    The catalogue tasks do not depend on the open-world arguments (their targets and seeds come
    first and from their own streams), so adding open-world cases leaves the catalogue figures as they
    were; the large departures come last and from a stream of their own, so adding them leaves the
    other open-world cases as they were.
    """
    nulls = max(3 * n, 20) if nulls is None else nulls
    pairs = n // 2 if pairs is None else pairs
    rng = np.random.default_rng(np.random.SeedSequence([seed, 6]))
    specs: list[tuple[str, dict[str, float] | None, str]] = []
    for e in EFFECTS:
        specs += [(e, {e: x}, "catalogue") for x in _stratified(rng, n)]
    specs += [("null", None, "catalogue")] * nulls
    all_pairs = list(combinations(EFFECTS, 2))
    order = np.concatenate([rng.permutation(len(all_pairs)) for _ in range(pairs // len(all_pairs) + 1)])[:pairs]
    for i in order:
        a, b = all_pairs[int(i)]
        specs.append((f"{a}+{b}", {a: log_uniform(rng, *pair_nc), b: log_uniform(rng, *pair_nc)}, "catalogue"))
    catalogue = len(specs)
    orng = np.random.default_rng(np.random.SeedSequence([seed, 12]))  # the open world's own stream
    for k in open_kinds:
        if k not in OPEN_KINDS:
            raise ValueError(f"open_kinds: expected some of {', '.join(OPEN_KINDS)}, got {k!r}")
        specs += [(k, {k: x}, "open") for x in _stratified(orng, open_n)]
    specs += [("null", None, "open")] * open_nulls
    lrng = np.random.default_rng(np.random.SeedSequence([seed, 13]))  # the large departures' own stream
    for k in open_kinds if open_large else ():
        specs += [(k, {k: x}, "open") for x in _stratified(lrng, open_large, LARGE_NC_RANGE)]
    # generate_state is prefix-stable: the catalogue tasks keep their seeds whatever follows them
    seeds = np.random.SeedSequence(seed).generate_state(len(specs), dtype=np.uint64)
    oplan = tuple(open_plan) if open_plan is not None else (tuple(ordinary_plan()) if len(specs) > catalogue else ())
    return [Task(i, kind, int(s), target, tuple(plan) if gen == "catalogue" else oplan, motion,
                 dict(analyze_kwargs or {}), gen)
            for i, ((kind, target, gen), s) in enumerate(zip(specs, seeds))]


class _SingleThreadedBLAS:
    """Each worker on one BLAS thread (set in the environment the spawned workers inherit)."""

    VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

    def __enter__(self) -> None:
        self.saved = {k: os.environ.get(k) for k in self.VARS}
        for k in self.VARS:
            os.environ[k] = "1"

    def __exit__(self, *exc: object) -> None:
        for k, v in self.saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _map(fn: Callable[[Any], Any], jobs: Sequence[Any], workers: int,
         progress: Callable[[int, int, str], None] | None, label: Callable[[Any], str]) -> list[Any]:
    """``fn`` over ``jobs`` in a spawn pool of ``workers`` processes (in this process when ``workers`` <= 1),
    calling ``progress(done, total, label(result))`` after each; results in job order."""
    results: dict[int, Any] = {}
    total = len(jobs)
    if workers <= 1:
        for i, job in enumerate(jobs):
            results[i] = fn(job)
            if progress:
                progress(len(results), total, label(results[i]))
    else:
        with _SingleThreadedBLAS(), ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(fn, job): i for i, job in enumerate(jobs)}
            for f in as_completed(futures):
                results[futures[f]] = f.result()
                if progress:
                    progress(len(results), total, label(results[futures[f]]))
    return [results[i] for i in range(total)]


def run_tasks(tasks: Sequence[Task], workers: int = 2,
              progress: Callable[[int, int, str], None] | None = None) -> tuple[list[Case], list[Outcome]]:
    """Run tasks (in a spawn pool of ``workers`` processes; in this process when ``workers`` <= 1),
    calling ``progress(done, total, kind)`` after each; results in task order."""
    ordered = _map(run_task, tasks, workers, progress, lambda r: r[1].kind)
    return [c for _, c, _ in ordered], [o for _, _, o in ordered]


#: What each case's record keeps of a finding.
FINDING_KEYS = ("effect", "p_value", "p_adjusted", "parameters", "sigma", "confusable_with", "model", "plausible")


def run_proof(n: int, seed: int, workers: int = 2, progress: Callable[[int, int, str], None] | None = None, *,
              plan: Sequence[Pose | Scan], nulls: int | None = None, pairs: int | None = None,
              motion: Motion = Motion(), analyze_kwargs: dict[str, Any] | None = None,
              pair_nc: tuple[float, float] = PAIR_NC_RANGE, open_n: int = 0,
              open_plan: Sequence[Pose | Scan] | None = None, open_nulls: int = 0,
              open_kinds: Sequence[str] = OPEN_KINDS, open_large: int = 0) -> dict[str, Any]:
    """The blind proof: generate the cases of :func:`proof_tasks`, analyse each noisy recording with
    ``physics.discrepancy.analyze`` (default arguments unless ``analyze_kwargs``; never anything of the
    truth), score. Returns ``{"score", "cases", "config"}``, JSON-safe; an open-world case's record
    also has the scorer's ``judgement`` (proof.score.judge_open)."""
    tasks = proof_tasks(n, seed, plan, nulls, pairs, motion, analyze_kwargs, pair_nc, open_n, open_plan, open_nulls,
                        open_kinds, open_large)
    t0 = time.perf_counter()
    cases, outcomes = run_tasks(tasks, workers, progress)
    sc = score(cases, outcomes)
    per_case = []
    for c, o in zip(cases, outcomes):
        d = c.summary()
        r = o.result or {}
        d.update({"verdict": r.get("verdict"),
                  "findings": [{k: f.get(k) for k in FINDING_KEYS} for f in r.get("findings", [])],
                  "heldout_ratio": o.heldout_ratio, "heldout_before": o.heldout_before, "seconds": o.seconds,
                  "error": o.error, "heading_error_deg": r.get("heading_error_deg")})
        if c.kind in OPEN_KINDS:
            d["judgement"] = judge_open(c, o.result, o.heading_free)
        per_case.append(d)
    config = {"n": n, "seed": seed, "nulls": sum(c.kind == "null" for c in cases),
              "pairs": sum("+" in c.kind for c in cases), "pair_nc": list(pair_nc), "workers": workers, "plan_items": len(plan),
              "open_n": open_n, "open_nulls": open_nulls, "open_large": open_large,
              "open_kinds": list(open_kinds) if open_n or open_large else [],
              "open_plan_items": len(tasks[-1].plan) if open_n or open_nulls or open_large else 0,
              "analyze_kwargs": dict(analyze_kwargs or {}), "wall_s": time.perf_counter() - t0}
    return json_safe({"score": sc, "cases": per_case, "config": config})


# --------------------------------------------------------------------------------------------------
# The proof without table angles (hand-held recordings, the attitude-free model)
# --------------------------------------------------------------------------------------------------

def run_handheld_case(job: tuple[int, str | None, float]) -> dict[str, Any]:
    """Generate one hand-held case (:func:`proof.handheld.make_handheld_case`), hand its recording (only) to
    the analyser, judge it as the table proof's open-world cases are (:func:`proof.score.judge_model`; a
    hand-held recording has no heading reference, so that criterion drops out). Top level for spawn."""
    from physics.discrepancy import analyze  # the analyser is imported here only, never by the generator

    seed, kind, lam = job
    rec, truth = make_handheld_case(seed, kind, lam)
    t0 = time.perf_counter()
    out: dict[str, Any] = {"seed": seed, "kind": kind, "lambda": lam, "truth": truth}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = analyze(rec.select(slice(None)), seed=seed).result
    except Exception as e:  # noqa: BLE001 - a crash is a result of the proof, scored and reported
        out.update(seconds=time.perf_counter() - t0, error=f"{type(e).__name__}: {e}", alarm=None, success=False,
                   frame=False, windows=False, findings=[])
        return out
    out.update(seconds=time.perf_counter() - t0, error=None, alarm=r["verdict"] != "consistent",
               findings=[{k: f.get(k) for k in FINDING_KEYS} for f in r.get("findings", [])])
    if kind is not None:
        span = (float(rec.t[0]), float(rec.t[-1] + np.median(np.diff(rec.t))))
        j = judge_model(truth, span, None, r)
        out.update(success=j["success"], frame=j["frame_right"], windows=j["where_right"], failed=j["failed"],
                   residual_ratio=j["residual_ratio"])
    return out


def run_handheld_proof(n: int, nulls: int, seed: int, workers: int = 2,
                       progress: Callable[[int, int, str], None] | None = None) -> dict[str, Any]:
    """The blind proof without table angles: the cases of :func:`proof.handheld.handheld_jobs`, each
    analysed by ``physics.discrepancy.analyze`` (the attitude-free model: the recordings have no table
    angles), scored by :func:`proof.score.score_handheld`. Returns ``{"score", "cases", "config"}``, JSON-safe."""
    jobs = handheld_jobs(n, nulls, seed)
    t0 = time.perf_counter()
    cases = _map(run_handheld_case, jobs, workers, progress, lambda r: f"hand-held {r['kind'] or 'null'}")
    config = {"n": n, "nulls": nulls, "seed": seed, "workers": workers, "kinds": list(HANDHELD_KINDS),
              "wall_s": time.perf_counter() - t0}
    return json_safe({"score": score_handheld(cases), "cases": cases, "config": config})
