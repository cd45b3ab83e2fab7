"""Every procedure of the station, as pure generators of steps (see procedures/steps.py).

``calibrate`` is the full error-separation procedure of the paper (PHYSICS.md, "The error-separation
procedure"); the others are its building blocks and checks: ``level``, ``sweep``, ``rotate_z``,
``accel6`` and ``evaluate``; ``characterize`` is the run the discrepancy analysis (issue 6) needs. Each takes validated parameters with defaults chosen for accuracy per
second of table time, and none does I/O: the engine, or a fake one in a test, runs them.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Literal, Mapping, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationInfo, field_validator, model_validator

from physics import errorsep as es
from physics.calibration import Calibration
from physics.errorsep import InsufficientData
from physics.fit import METHODS, evaluate as evaluate_recording, fit
from physics.heading import circular_mean_deg, wrap180
from physics.methods import TWELVE_POSITIONS
from physics.precision import CONFIDENCE, TARGET_LEVEL_DEG, TARGET_TILTED_DEG, UnitPrecision, unit_precision
from physics.recording import Recording, RecordingError, concat
from physics.simulate import Pose, plan_cost, plan_timeline
from physics.table import DRIVE_SETTLE_S, PROCEDURE_SETTLE_S, Motion
from procedures.steps import (Acquire, Checkpoint, Compute, Move, Outcome, Park, Procedure, ProcedureGen, Prompt, Scan, Settle,
                              Where, request_number, step_seconds)

NAME = "calibrate"
VERSION = "2"


class _Params(BaseModel):
    # a misspelt parameter is an error, not silently the default; "nan" is no number (it was said to be
    # out of range)
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_numbers(cls, v: Any, info: ValidationInfo) -> Any:
        # a number field (not one that also takes a bool or text) takes a number only
        kinds = get_args(cls.model_fields[info.field_name].annotation) or (cls.model_fields[info.field_name].annotation,)
        if (int in kinds or float in kinds) and bool not in kinds and str not in kinds:
            if isinstance(v, list):  # a list of numbers (list[float]'s argument is float): each one a number
                return [request_number(x) for x in v]
            if int in kinds and float not in kinds and isinstance(v, float) and v.is_integer():
                # a whole number written as 1e30 is judged by the field's range ("less than or equal to 10000"),
                # not refused as "an input string ... exceeded maximum size"
                return int(v)
            return request_number(v)
        return v

    samples: int = Field(60, ge=1, le=10_000, description="samples averaged at each pose")
    # The drive reports IN_POSITION only once the axis has settled in its window; this is extra
    # margin for the unit's own output filter (none at AVG 1).
    settle_s: float = Field(PROCEDURE_SETTLE_S, ge=0, le=60, description="wait after each move is in position, table seconds")


def _step(default: float, what: str) -> Any:
    """A full turn's step (deg): at least three poses a turn, and none finer than 1 deg (a z step of
    0.001 asked 360,000 poses; one of 1e-300 failed on the table)."""
    return Field(default, ge=1.0, le=120.0, description=f"{what}, deg (1 to 120: at least three poses a turn)")


def _angle(default: float, what: str) -> Any:
    """An angle the table is sent to (deg): within a turn of its zero either way (a sweep azimuth of
    -720.5 drove the table round twice to get there)."""
    return Field(default, ge=-360.0, le=360.0, description=f"{what}, deg (-360 to 360)")


def _turn(step_deg: float) -> np.ndarray:
    return np.arange(0.0, 360.0 - 1e-9, step_deg)


#: The adaptive extension's table-time budget unless one is given (s): issue 14's three minutes.
DEFAULT_BUDGET_S = 180.0


class CalibrateParams(_Params):
    """Choices of the calibration, with defaults chosen for accuracy per second of table time.

    z_step_deg: azimuth step of the level rotation about z (a full turn).
    tilt_step_deg: step of the sweeps about y and x (full turns of the middle and inner axes).
    sweep_psi_deg: azimuth at which the y and x sweeps are made.
    method: the fit (physics.fit.METHODS); the joint least-squares fit by default. Two comparison
    methods bring their own plan: ``twelve-position`` visits its twelve positions (the steps and
    sweep_psi_deg are not used), ``maxmin`` makes its turns about y and x at the headings where x and
    y point along the field, found from the level turn (sweep_psi_deg is not used).
    """

    z_step_deg: float = _step(45.0, "azimuth step of the level turn")
    tilt_step_deg: float = _step(60.0, "step of the turns about y and x")
    sweep_psi_deg: float = _angle(315.0, "azimuth of the turns about y and x")
    method: str = "joint"
    adaptive: StrictBool = Field(False, description="after the plan, add the poses that lower the predicted heading error "
                           "fastest until every unit meets both targets together at 95 % confidence or budget_s ends (joint method)")
    target_level_deg: float = Field(TARGET_LEVEL_DEG, gt=0, le=10, description="adaptive: level heading error target, deg")
    target_tilted_deg: float = Field(TARGET_TILTED_DEG, gt=0, le=10, description="adaptive: heading error target at pitch and roll up to 60 deg")
    budget_s: float = Field(DEFAULT_BUDGET_S, gt=0, le=3600, description="adaptive: table seconds the whole calibration may take "
                            "(the plan's and the added poses' nominal seconds; a batch unit's move back to the load "
                            "pose included)")

    @field_validator("method")
    @classmethod
    def _known(cls, v: str) -> str:
        if v not in METHODS:
            raise ValueError(f"expected one of {', '.join(METHODS)}")
        return v

    @model_validator(mode="after")
    def _adaptive_needs_joint(self) -> "CalibrateParams":
        if self.adaptive and self.method != "joint":
            raise ValueError(f"adaptive: needs method 'joint' (the covariance it predicts from), got {self.method!r}")
        # (a run's stored parameters carry every field, the default budget too: that one is not a request)
        if "budget_s" in self.model_fields_set and not self.adaptive and self.budget_s != DEFAULT_BUDGET_S:
            raise ValueError("budget_s: only the adaptive extension has a table-time budget; set adaptive true, "
                             "or leave budget_s out")
        if self.adaptive:
            plan_s = self.plan_seconds()
            if self.budget_s < plan_s:
                raise ValueError(f"budget_s: {self.budget_s:g} s is shorter than the plan itself ({plan_s:.1f} s of "
                                 f"table time, nominal, at these samples and steps); give at least {math.ceil(plan_s)} "
                                 "s, more to leave room for added poses")
        return self

    #: Where the table goes once the poses are done (None: it stays at the last pose).
    END_POSE: ClassVar[tuple[float, float, float] | None] = None

    def plan_seconds(self) -> float:
        """Nominal table seconds of the plan without an adaptive extension (and the move to
        :attr:`END_POSE` after it), as the budget counts them."""
        poses = calibration_poses(self)
        last = (poses[-1].psi_t, poses[-1].theta_t, poses[-1].phi_t)
        return _plan_seconds(poses, self) + _return_seconds(last, self.END_POSE)


def calibration_poses(p: CalibrateParams = CalibrateParams()) -> list[Pose]:
    """Poses of the calibration: a level turn about z, then full turns about y and about x.

    The level turn (step ``rotate_z``) gives each horizontal axis its sinusoid and line and the
    accelerometer its reversal; the y and x sweeps let every axis see the field from -1 to +1 and
    the gravity vector turn through the body, which separates all of M, b, I, D and the base tilt.
    """
    poses = [Pose("rotate_z", float(psi), 0.0, 0.0, p.samples) for psi in _turn(p.z_step_deg)]
    poses += [Pose("sweep_y", p.sweep_psi_deg, float(th), 0.0, p.samples) for th in _turn(p.tilt_step_deg)[1:]]
    poses += [Pose("sweep_x", p.sweep_psi_deg, 0.0, float(ph), p.samples) for ph in _turn(p.tilt_step_deg)[1:]]
    return poses


class Collected:
    """Samples a run has acquired so far, per slot (what the engine sent back for each Acquire)."""

    def __init__(self) -> None:
        self.parts: dict[int, list[Recording]] = {}

    def add(self, reply: object) -> None:
        """Keep one Acquire's reply."""
        if isinstance(reply, dict):
            for slot, rec in reply.items():
                self.parts.setdefault(slot, []).append(rec)

    def recordings(self) -> dict[int, Recording]:
        """Everything so far, one recording per slot."""
        return {slot: concat(parts) for slot, parts in sorted(self.parts.items())}


def visit(plan: list[Pose | Scan], settle_s: float, data: Collected) -> ProcedureGen:
    """Run poses (an approach move first when they have one; move, settle, acquire) and scans in turn,
    with a checkpoint after each, keeping the samples in ``data``."""
    for item in plan:
        if isinstance(item, Scan):
            data.add((yield item))  # a plan's scan is the step itself
        else:
            if item.approach_deg:
                yield Move(item.psi_t - item.approach_deg, item.theta_t, item.phi_t)
            yield Move(item.psi_t, item.theta_t, item.phi_t)
            if settle_s > 0:
                yield Settle(settle_s)
            data.add((yield Acquire(item.samples, item.step)))
        yield Checkpoint(item.step)
    return Outcome()


def _per_slot(data: Collected, work: Any, done: dict[int, dict[str, Any]] | None = None) -> Outcome:
    """Run ``work(recording) -> dict`` for each slot (the slots in ``done`` have their result already); a
    unit whose data cannot be used gets its error."""
    out = Outcome()
    for slot, rec in data.recordings().items():
        try:
            out.results[slot] = done[slot] if done and slot in done else work(rec)
        except (RecordingError, InsufficientData, ValueError) as e:
            out.results[slot] = {"error": str(e)}
    return out


def twelve_position_poses(p: CalibrateParams = CalibrateParams()) -> list[Pose]:
    """The twelve positions of the seed-002 method (physics.methods.TWELVE_POSITIONS): each body axis
    down and up, each at two headings 180 deg apart."""
    return [Pose("twelve_position", psi, th, ph, p.samples) for psi, th, ph in TWELVE_POSITIONS]


def _peak_deg(angle: np.ndarray, mag: np.ndarray, axis: int) -> float:
    """Where sensor ``axis`` reads most over a turn (deg): the phase of its fitted sinusoid."""
    coef, _ = es.fit_sinusoid(angle, mag[:, axis])
    return float(np.degrees(np.arctan2(coef[2], coef[1])) % 360.0)


def _fixture_peak(data: Collected, step: str, column: str, axis: int) -> float:
    """The peak of ``axis`` over the turn labelled ``step`` (angle column ``column``), averaged over the
    fixture's units (mounted alike, they peak within their misalignments of each other)."""
    peaks = []
    for rec in data.recordings().values():
        keep = rec.step == step
        peaks.append(_peak_deg(getattr(rec, column)[keep], rec.mag[keep], axis))
    # no data: the plan's length is being estimated (Procedure.plan), any angle will do
    return round(circular_mean_deg(peaks), 2) if peaks else 0.0


def _short_tour(angles: set[float], start: float, lo: float, hi: float) -> list[float]:
    """``angles`` (deg, in (-180, 180]) in the order and at the turns (a or a + 360, within [lo, hi], the
    range the plan's turns already use) that keep the axis's travel from ``start`` short: nearest first.
    The axis drives to the angle it is given, not the short way round: sorted ascending after a sweep
    that ended at 300 deg, the extremes had cost a 445-deg drive where 100 would do."""
    left = sorted(angles)
    here, tour = start, []
    while left:
        a, at = min(((a, r) for a in left for r in (a, a + 360.0) if lo <= r <= hi), key=lambda ar: abs(ar[1] - here))
        left.remove(a)
        tour.append(at)
        here = at
    return tour


def maxmin_visit(p: CalibrateParams, data: Collected) -> ProcedureGen:
    """The plan of the maxmin method: every sensor axis pointed along and against the field.

    The level turn gives the heading at which x and at which y point along the field's horizontal
    part (psi near D and D - 90). A turn about y there swings x and z through the vertical plane that
    holds the field, a turn about x at the other swings y and z: each turn's sinusoids say at which
    angle each axis peaks, and the axis is then held there and opposite (so the extremes are
    measured, not missed by up to half a step)."""
    yield from visit([Pose("rotate_z", float(a), 0.0, 0.0, p.samples) for a in _turn(p.z_step_deg)], p.settle_s, data)
    psi_x = _fixture_peak(data, "rotate_z", "psi_t", 0)
    psi_y = _fixture_peak(data, "rotate_z", "psi_t", 1)
    for label, psi, column, axes in (("sweep_y", psi_x, "theta_t", (0, 2)), ("sweep_x", psi_y, "phi_t", (1, 2))):
        def pose(step: str, a: float, psi: float = psi, label: str = label) -> Pose:
            return Pose(step, psi, a if label == "sweep_y" else 0.0, a if label == "sweep_x" else 0.0, p.samples)
        yield from visit([pose(label, float(a)) for a in _turn(p.tilt_step_deg)], p.settle_s, data)
        peaks = [_fixture_peak(data, label, column, i) for i in axes]
        extremes = {round(float(wrap180(a + d)), 2) for a in peaks for d in (0.0, 180.0)}
        turn = _turn(p.tilt_step_deg)
        tour = _short_tour(extremes, float(turn[-1]), -180.0, float(turn[-1]))
        yield from visit([pose("maxmin_" + label[-1], a) for a in tour], p.settle_s, data)
    return Outcome()


def calibrate(p: CalibrateParams) -> ProcedureGen:
    """The calibration of every unit in the fixture, ending in the fit: the error-separation poses
    (:func:`calibration_poses`), or the plan of a comparison method that needs its own (the twelve
    positions; maxmin's field-aligned turns)."""
    data = Collected()
    precision: dict[int, dict[str, Any]] = {}
    fitted: dict[int, Calibration] = {}  # the adaptive extension's last fits, on all the data
    if p.method == "twelve-position":
        yield from visit(twelve_position_poses(p), p.settle_s, data)
    elif p.method == "maxmin":
        yield from maxmin_visit(p, data)
    else:
        poses = calibration_poses(p)
        # the budget counts the plan from where the table stands (a run after another starts where that one
        # ended: its first move back from psi 315 took 11 s that a plan counted from home left out, and a
        # 150-s budget ran to 168 s)
        start = (yield Where()) if p.adaptive else None
        yield from visit(poses, p.settle_s, data)
        if p.adaptive:
            spent = _plan_seconds(poses, p, tuple(start) if start else (0.0, 0.0, 0.0))
            here = (poses[-1].psi_t, poses[-1].theta_t, poses[-1].phi_t)
            precision, fitted = yield from extend_to_target(p, data, spent, here)
    if p.END_POSE is not None:  # a fault on the way there is a warning: the data are in
        yield Park(*p.END_POSE)

    def result(cal: Calibration) -> dict[str, Any]:
        return {"calibration": cal, "quality": cal.quality}
    yield Compute("calibration fit")
    out = _per_slot(data, lambda rec: result(fit(rec, p.method, bootstrap=0)), {s: result(c) for s, c in fitted.items()})
    for slot, pr in precision.items():
        if "calibration" in out.results.get(slot, {}):
            out.results[slot]["calibration"].quality["precision"] = pr
            out.results[slot]["calibration"].notes.append(pr["why"])
    return out


# --- adaptive extension (issue 14, part 3) ----------------------------------------------------------

#: Poses the adaptive extension chooses from: the level turn every 45 deg, and each quarter heading with the
#: platform pitched or rolled by +-60 and +-120 deg or upside down (where a weak axis sees the field).
ADAPTIVE_POSES = ([(float(a), 0.0, 0.0) for a in _turn(45.0)]
                  + [(float(a), th, ph) for a in _turn(90.0)
                     for th, ph in ((60.0, 0.0), (-60.0, 0.0), (0.0, 60.0), (0.0, -60.0), (120.0, 0.0), (-120.0, 0.0),
                                    (0.0, 120.0), (0.0, -120.0), (180.0, 0.0))])
#: Table seconds of poses chosen per round between refits (the choice is made on the information the
#: poses will add; the refit then checks the prediction on the data they gave).
ROUND_S = 20.0


def _plan_seconds(poses: list[Pose], p: CalibrateParams, start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> float:
    """Nominal table seconds of poses from ``start`` (moves, the drive's settling, the procedure's settle,
    samples), as the adaptive extension counts its budget: as the engine counts them on a station whose
    drives settle in :data:`DRIVE_SETTLE_S` (the default; the simulated servo's)."""
    return plan_cost(poses, Motion(settle_s=DRIVE_SETTLE_S + p.settle_s), start=start).total_s


def _return_seconds(here: tuple[float, float, float], end: tuple[float, float, float] | None) -> float:
    """Nominal table seconds of the move from ``here`` to ``end`` (0 without one), as the engine counts
    a move (:func:`~procedures.steps.step_seconds`): the drives' settling, no procedure settle."""
    if end is None:
        return 0.0
    return step_seconds([Move(*end)], Motion(settle_s=DRIVE_SETTLE_S), start=here)[0]


def adaptive_reserve(p: CalibrateParams) -> float:
    """Table seconds an adaptive extension may add after the plan (0 when not adaptive)."""
    return max(p.budget_s - _plan_seconds(calibration_poses(p), p), 0.0) if p.adaptive else 0.0


def _unit_precisions(data: Collected) -> dict[int, tuple[UnitPrecision, Calibration]]:
    """Each slot's joint fit of its data so far and the precision model from it (a slot whose fit fails
    is left out)."""
    out = {}
    for slot, rec in data.recordings().items():
        try:
            cal = fit(rec, "joint", bootstrap=0)
            out[slot] = (unit_precision(rec, cal), cal)
        except (RecordingError, InsufficientData, ValueError, np.linalg.LinAlgError):
            continue
    return out


#: Hold lengths the extension chooses from, in multiples of ``samples``: a long hold spreads a move's
#: seconds over more samples, a short one lets the next pose come sooner.
HOLDS = (1, 4)


def choose_poses(units: dict[int, UnitPrecision], targets: dict[str, float], p: CalibrateParams,
                 here: tuple[float, float, float], left_s: float,
                 added: dict[int, list] | None = None,
                 end: tuple[float, float, float] | None = None) -> tuple[list[Pose], float, dict[int, list]]:
    """Poses (up to :data:`ROUND_S` of table time, within ``left_s``) that lower the units' predicted heading
    errors fastest: each in turn the candidate (pose and hold length) with the largest fall per table second
    of the sum over units of their worst 1-sigma error over target, counting the poses already chosen (and
    ``added``, the information of poses chosen before but not yet in the fit). Returns them, their seconds
    and the information added with them (per slot: magnetometer, accelerometer). With ``end``, a pose is
    taken only if the move from it to ``end`` still fits in ``left_s`` (not counted in the seconds returned)."""
    cands = np.array(ADAPTIVE_POSES)
    back = np.array([_return_seconds(c, end) for c in ADAPTIVE_POSES])
    per = {s: (u.mag.per_sample(cands), u.acc.per_sample(cands) if u.acc else None) for s, u in units.items()}
    if added is None:
        added = {s: [np.zeros((14, 14)), np.zeros((14, 14)) if u.acc else None] for s, u in units.items()}
    # every candidate at once: pose c held n samples, for each (c, n) of the grid below
    grid_c = np.repeat(np.arange(len(ADAPTIVE_POSES)), len(HOLDS))
    grid_n = np.tile(np.array(HOLDS) * p.samples, len(ADAPTIVE_POSES)).astype(float)

    def objective(extra: dict[int, list]) -> np.ndarray:
        """Sum over units of their worst 1-sigma error over target (batched over the leading axis of extra)."""
        total = 0.0
        for s, u in units.items():
            sig = u.sigma_max(extra[s][0], extra[s][1])
            total = total + np.max([sig[k] / t for k, t in targets.items()], axis=0)
        return np.asarray(total)

    chosen: list[Pose] = []
    spent = 0.0
    now = float(objective(added))
    while spent < ROUND_S:
        cost = np.array([_plan_seconds([Pose("adaptive", *ADAPTIVE_POSES[c], samples=int(n))], p, here)
                         for c, n in zip(grid_c, grid_n)])
        trial = {s: [a[0] + grid_n[:, None, None] * per[s][0][grid_c],
                     None if a[1] is None else a[1] + grid_n[:, None, None] * per[s][1][grid_c]]
                 for s, a in added.items()}
        after = objective(trial)
        rate = np.where(spent + cost + back[grid_c] <= left_s, (now - after) / cost, -np.inf)
        i = int(np.argmax(rate))
        if not rate[i] > 0.0:
            break
        c, n = int(grid_c[i]), int(grid_n[i])
        # the chosen candidate's information and objective are the trial's (not computed again)
        added = {s: [t[0][i], None if t[1] is None else t[1][i]] for s, t in trial.items()}
        now = float(after[i])
        chosen.append(Pose("adaptive", *ADAPTIVE_POSES[c], samples=n))
        spent += float(cost[i])
        here = ADAPTIVE_POSES[c]
    return chosen, spent, added


#: How far beyond the budget :func:`time_to_target` looks.
LOOKAHEAD_S = 900.0


def time_to_target(u: UnitPrecision, targets: dict[str, float], p: CalibrateParams,
                   here: tuple[float, float, float], end: tuple[float, float, float] | None = None) -> float | None:
    """Table seconds of further poses, chosen round by round as the extension chooses them, after which
    ``u``'s predicted errors (bounds at 95 % confidence, on the information those poses would add to its fit) meet
    the targets; None when :data:`LOOKAHEAD_S` would not do. For a unit the budget left short: the
    budget it needed. With ``end``: the move there from the last pose counted, less the one from ``here``
    (which the table time so far already counts)."""
    spent, added, back = 0.0, None, _return_seconds(here, end)
    while spent < LOOKAHEAD_S:
        poses, seconds, added = choose_poses({0: u}, targets, p, here, LOOKAHEAD_S - spent, added, end)
        if not poses:
            return None
        spent += seconds
        here = (poses[-1].psi_t, poses[-1].theta_t, poses[-1].phi_t)
        q = u.quantile(extra_mag=added[0][0], extra_acc=added[0][1])
        if all(q[k] <= t for k, t in targets.items()):
            return spent + _return_seconds(here, end) - back
    return None


def extend_to_target(p: CalibrateParams, data: Collected, spent_s: float,
                     here: tuple[float, float, float]) -> ProcedureGen:
    """Add poses until every unit's predicted heading error (bounds on its largest error level and at +-60 deg
    that hold together at 95 % confidence, from its joint fit's covariance: physics.precision) meets the targets, or the table-time budget
    would be exceeded (with ``p.END_POSE``, the move there after the last pose included: it is counted in
    the budget and in ``table_s``). Returns per slot what was predicted, whether the targets were met and why it stopped;
    and the last round's joint fits, made on all the data (the calibration's own fit, not made again)."""
    targets = {"level": p.target_level_deg, "tilted": p.target_tilted_deg}
    added = 0
    rounds: dict[int, list[dict[str, float]]] = {}  # per slot: the prediction after each round, for the plot
    while True:
        yield Compute("fit and predicted heading error of each unit")
        fits = _unit_precisions(data)
        units = {s: u for s, (u, _) in fits.items()}
        predicted = {s: u.quantile() for s, u in units.items()}
        for s, q in predicted.items():
            rounds.setdefault(s, []).append({"table_s": spent_s, "level_deg": q["level"], "tilted_deg": q["tilted"]})
        pending = {s: units[s] for s in units if any(predicted[s][k] > t for k, t in targets.items())}
        if not pending:
            break
        poses, seconds, _ = choose_poses(pending, targets, p, here, p.budget_s - spent_s, end=p.END_POSE)
        if not poses:  # the budget cannot take another pose
            break
        yield from visit(poses, p.settle_s, data)
        spent_s += seconds
        added += len(poses)
        here = (poses[-1].psi_t, poses[-1].theta_t, poses[-1].phi_t)
    out = {}
    spent_s += _return_seconds(here, p.END_POSE)
    for s, q in predicted.items():
        met = all(q[k] <= t for k, t in targets.items())
        # for a unit short of the targets: the further table time it needs (None: beyond the look-ahead)
        more = None if met else time_to_target(units[s], targets, p, here, p.END_POSE)
        res = {"predicted_level_deg": q["level"], "predicted_tilted_deg": q["tilted"], "confidence": CONFIDENCE,
               "target_level_deg": targets["level"], "target_tilted_deg": targets["tilted"], "met": met,
               "stopped": "reached" if met else "budget", "added_poses": added,
               "table_s": spent_s, "more_table_s": more, "budget_s": p.budget_s, "rounds": rounds[s]}
        predicted_said = (f"predicted heading error (bounds holding together at 95 % confidence) {q['level']:.4f} deg level, "
                          f"{q['tilted']:.4f} deg at +-60 deg: ")
        if met:
            why = (predicted_said + f"within the targets {targets['level']:g} and {targets['tilted']:g} deg"
                   + (f" after {_poses(added)} added" if added else " with the plan alone"))
        else:
            need = (f"about {more:.0f} s more table time (a budget of {needed_budget_s(res):.0f} s) would reach them"
                    if more is not None else
                    f"even {LOOKAHEAD_S / 60:.0f} min more table time would not: a unit with less noise per field, "
                    f"or a compass that averages more per sample, would")
            why = (predicted_said + f"above the targets {targets['level']:g} / {targets['tilted']:g} deg when the {p.budget_s:g}-s "
                   f"table-time budget ended ({_poses(added)} added); {need}")
        out[s] = {**res, "why": why}
    return out, {s: cal for s, (_, cal) in fits.items()}


def needed_budget_s(precision: Mapping[str, Any]) -> float | None:
    """The budget a unit the extension left short would have needed (its table time plus the look-ahead's
    ``more_table_s``); None when it met the targets or when even the look-ahead would not do."""
    more = precision.get("more_table_s")
    return None if precision.get("met") or more is None else float(precision["table_s"] + more)


def _poses(n: int) -> str:
    """'1 pose', '3 poses'."""
    return f"{n} pose" + ("" if n == 1 else "s")


# --- building blocks and checks -----------------------------------------------------------------

class RotateParams(_Params):
    """A turn about z at fixed tilt."""

    step_deg: float = _step(45.0, "azimuth step")
    theta_deg: float = _angle(0.0, "tilt about y")
    phi_deg: float = _angle(0.0, "tilt about x")


def rotate_z(p: RotateParams) -> ProcedureGen:
    """Rotate about z from 0 through a full turn, holding at each step."""
    data = Collected()
    poses = [Pose("rotate_z", float(psi), p.theta_deg, p.phi_deg, p.samples) for psi in _turn(p.step_deg)]
    yield from visit(poses, p.settle_s, data)
    return _per_slot(data, lambda rec: {"samples": len(rec), "mag_mean": rec.mag.mean(axis=0).tolist()})


class SweepParams(_Params):
    """A full turn of one axis (the others held)."""

    axis: Literal["z", "y", "x"] = "y"
    step_deg: float = _step(30.0, "step of the turn")
    psi_deg: float = _angle(315.0, "azimuth of a turn about y or x")


def sweep(p: SweepParams) -> ProcedureGen:
    """Turn one axis through 360 deg and locate where each sensor axis peaks (sinusoid fit)."""
    data = Collected()
    angles = _turn(p.step_deg)
    poses = [Pose(f"sweep_{p.axis}", float(a) if p.axis == "z" else p.psi_deg, float(a) if p.axis == "y" else 0.0,
                  float(a) if p.axis == "x" else 0.0, p.samples) for a in angles]
    yield from visit(poses, p.settle_s, data)

    def work(rec: Recording) -> dict[str, Any]:
        a = {"z": rec.psi_t, "y": rec.theta_t, "x": rec.phi_t}[p.axis]
        coef, _ = es.fit_sinusoid(a, rec.mag)
        peak = np.degrees(np.arctan2(coef[2], coef[1])) % 360.0
        return {"peak_deg": peak.tolist(), "amplitude_lsb": np.hypot(coef[1], coef[2]).tolist(), "offset_lsb": coef[0].tolist()}
    return _per_slot(data, work)


class Accel6Params(_Params):
    """Six positions: each body axis up and down."""


ACCEL6_POSES = [(0.0, 0.0, 0.0), (0.0, 0.0, 180.0), (0.0, 90.0, 0.0), (0.0, -90.0, 0.0), (0.0, 0.0, 90.0), (0.0, 0.0, -90.0)]


def accel6(p: Accel6Params) -> ProcedureGen:
    """Six-position accelerometer calibration."""
    data = Collected()
    yield from visit([Pose("accel6", *a, samples=p.samples) for a in ACCEL6_POSES], p.settle_s, data)

    def work(rec: Recording) -> dict[str, Any]:
        if rec.acc is None:
            raise RecordingError("no accelerometer readings")
        sensor = es.six_position(es.table_angles(rec), rec.acc)
        if sensor is None:
            raise RecordingError("a six-position attitude is missing")
        return {"M_o": sensor.M_o.tolist(), "k": sensor.k.tolist(), "bias": sensor.bias.tolist()}
    return _per_slot(data, work)


class LevelParams(_Params):
    """Base tilt by reversal (a level turn), then optionally level the platform at psi = 0."""

    step_deg: float = _step(90.0, "azimuth step of the reversals")
    apply: StrictBool = True


def level(p: LevelParams) -> ProcedureGen:
    """Measure the base tilt by reversal and, with ``apply``, tilt the middle and inner axes to level
    the platform at psi = 0 (the tilt comes back as the outer axis turns: it is the base's)."""
    data = Collected()
    yield from visit([Pose("level", float(a), 0.0, 0.0, p.samples) for a in _turn(p.step_deg)], p.settle_s, data)
    out = Outcome()
    tilts = []
    for slot, rec in data.recordings().items():
        if rec.acc is None:
            out.results[slot] = {"error": "no accelerometer readings"}
            continue
        tilt = es.tilt_by_reversal(rec.psi_t, rec.acc)
        tilts.append(tilt)
        out.results[slot] = {"base_tilt_deg": [float(tilt[0]), float(tilt[1])]}
    if tilts and p.apply:
        tx, ty = np.mean(tilts, axis=0)
        # C_LP = Ry(ty) Rx(tx) Ry(theta) Rx(phi) at psi = 0 is level for theta = -ty, phi = -tx (small angles)
        yield Move(0.0, float(-ty), float(-tx))
        out.notes.append(f"platform levelled at psi=0: theta={-ty:.4f}, phi={-tx:.4f} deg")
    return out


class EvaluateParams(_Params):
    """Check given calibrations on the table: a level turn and every heading at pitch and roll up to the limit."""

    calibrations: dict[int, dict[str, Any]] = Field(description="slot -> calibration JSON (physics format)")
    heading_step_deg: float = _step(45.0, "azimuth step of the level turn")
    max_tilt_deg: float = Field(60.0, ge=0, le=80)
    tilt_step_deg: float = Field(60.0, ge=1.0, le=160.0, description="step of pitch and roll from -max_tilt_deg, deg (1 to 160)")
    tilted_heading_step_deg: float = _step(90.0, "azimuth step of the tilted poses")
    # The level turn is what the 0.02 deg target is about: enough samples that a pose's own noise is
    # well below it; the tilted poses check the 0.05 deg target with fewer.
    samples: int = Field(160, ge=1, le=10_000, description="samples per level pose")
    tilted_samples: int = Field(40, ge=1, le=10_000, description="samples per tilted pose")

    @field_validator("calibrations")
    @classmethod
    def _readable(cls, v: dict[int, dict[str, Any]]) -> dict[int, dict[str, Any]]:
        for slot, d in v.items():
            try:
                Calibration.from_json(d)
            except (KeyError, TypeError, ValueError) as e:
                raise ValueError(f"slot {slot}: not a calibration ({e})") from None
        return v


def evaluation_poses(p: EvaluateParams) -> list[Pose]:
    """Level turn, then each heading at each (pitch, roll) of the grid except level."""
    poses = [Pose("evaluate_level", float(a), 0.0, 0.0, p.samples) for a in _turn(p.heading_step_deg)]
    psi = _turn(p.tilted_heading_step_deg)
    tilts = np.arange(-p.max_tilt_deg, p.max_tilt_deg + 1e-9, p.tilt_step_deg) if p.max_tilt_deg > 0 else np.zeros(1)
    for th in tilts:
        for ph in tilts:
            if th == 0 and ph == 0:
                continue
            poses += [Pose("evaluate_tilted", float(a), float(th), float(ph), p.tilted_samples) for a in psi]
    return poses


def evaluate(p: EvaluateParams) -> ProcedureGen:
    """Heading error of each unit's calibration over a full turn and at pitch and roll up to the limit."""
    data = Collected()
    yield from visit(evaluation_poses(p), p.settle_s, data)

    out = Outcome()
    for slot, rec in data.recordings().items():
        if slot in p.calibrations:
            cal = Calibration.from_json(p.calibrations[slot])
            # whose calibration it was: the worker compares it with the unit the slot identified
            out.results[slot] = {**evaluate_recording(rec, cal, p.max_tilt_deg), "calibration_serial": cal.serial}
        else:
            out.results[slot] = {"error": f"no calibration given for slot {slot}"}
    return out


# --- characterize: a run designed to make the catalogue of physics/effects.py identifiable ---------

class CharacterizeParams(_Params):
    """Choices of the characterize run (defaults: 9.5 minutes of table time at the default Motion,
    see :func:`characterize_plan`).

    samples: samples of each hold (60 at 20 Hz = 3 s, long enough for a spectrum of the noise).
    long_samples: samples of the first hold and of the closing hold that repeats it (drift, warm-up,
    the mains alias line).
    azimuths: level holds per turn, each visited from both sides.
    tilt_deg, tilt_azimuths: pitch and roll holds of +-tilt_deg at this many azimuths (stage iron,
    table axis errors and gradients need tilts at several azimuths); ``diagonal`` adds the four
    combined pitch-and-roll holds at each of those azimuths.
    z_speeds_dps: turns about z, both ways at each of these speeds (a lag changes sign with the
    direction and grows with the speed; hysteresis does neither).
    tilt_scan_speed_dps: turns about y and about x, both ways at this speed (0: none).
    """

    samples: int = Field(60, ge=1, le=10_000, description="samples of each hold")
    # A sensor that lags the encoder still sees the last move for its lag after the table stops:
    # wait out the largest plausible lag (physics.effects) so that holds are truly at rest.
    settle_s: float = Field(0.5, ge=0, le=60, description="wait after each move is in position, table seconds")
    long_samples: int = Field(600, ge=1, le=100_000, description="samples of the first and the closing hold")
    azimuths: int = Field(8, ge=3, le=72, description="level holds per turn, each approached from both sides")
    tilt_deg: float = Field(60.0, gt=0, le=80, description="pitch and roll of the tilted holds, deg")
    tilt_azimuths: int = Field(4, ge=2, le=36, description="azimuths of the tilted holds")
    diagonal: StrictBool = Field(True, description="also hold pitched and rolled at once")
    z_speeds_dps: list[float] = Field([10.0, 30.0], min_length=1, max_length=4,
                                      description="speeds of the turns about z (each turned both ways), deg/s")
    tilt_scan_speed_dps: float = Field(30.0, ge=0, le=60, description="speed of the turns about y and x (0: none)")

    @field_validator("z_speeds_dps")
    @classmethod
    def _speeds(cls, v: list[float]) -> list[float]:
        bad = [x for x in v if not 0 < x <= 60]
        if bad:
            raise ValueError(f"each speed must be > 0 and <= 60 deg/s (the controller's MAX_VEL), got {bad}")
        return v


def characterize_plan(p: CharacterizeParams = CharacterizeParams()) -> list[Pose | Scan]:
    """The characterize run as poses and scans (physics.simulate types, so the offline simulator runs
    the same plan). With the defaults: 571 s (9.5 min) of table time at the default Motion
    (:func:`plan_seconds`; about 620 s on the simulated station, whose moves also wait for the
    servo to settle): 50 holds (4080 samples at rest) and 8 turns (about 2950 samples in motion at
    20 Hz).

    1. ``hold_first``: a long level hold at psi = 0 (noise floor, its colour and spectrum, warm-up).
    2. ``level_up``: a level turn of ``azimuths`` holds, each approached from below (going up).
    3. ``scan_z_down_<v>``, ``scan_z_up_<v>``: full turns about z (-180 to 180 deg) both ways at each
       speed: time lag (its sign follows the direction, its size the speed) against hysteresis.
    4. ``level_down``: the level holds again, each approached from above (coming down): hysteresis
       against the direction of approach, and the level harmonics (stage soft iron, nonlinearity,
       gradients).
    5. ``tilt_theta``, ``tilt_phi`` (and ``tilt_both``): pitch and roll holds at several azimuths:
       stage hard and soft iron, table axis errors, gradients.
    6. ``scan_y_down``/``scan_y_up``, ``scan_x_down``/``scan_x_up``: full turns about y and about x
       at the first tilt azimuth: first harmonics against theta and phi (iron on the outer or middle
       stage).
    7. ``hold_closing``: the first hold again, approached the same way: drift over the run.
    """
    # Both sides of approach come from the order of the holds (a pass going up, a pass coming down),
    # never from an unrecorded overshoot: the analysis follows the table between recorded samples and
    # could not see a detour.
    first = Pose("hold_first", 0.0, 0.0, 0.0, p.long_samples)
    plan: list[Pose | Scan] = [first]
    level = [float(a) for a in _turn(360.0 / p.azimuths)]
    plan += [Pose("level_up", a, 0.0, 0.0, p.samples) for a in level]
    # the turns about z come between the two level passes (the table is near +180 there)
    for v in p.z_speeds_dps:
        name = f"{v:g}".replace(".", "p")
        plan += [Scan(f"scan_z_down_{name}", "psi", 180.0, -180.0, v),
                 Scan(f"scan_z_up_{name}", "psi", -180.0, 180.0, v)]
    plan += [Pose("level_down", a, 0.0, 0.0, p.samples) for a in reversed(level)]
    T = p.tilt_deg
    azimuths = [round(float(x), 6) for x in _turn(360.0 / p.tilt_azimuths) + 180.0 / p.tilt_azimuths]
    for a in reversed(azimuths):  # ends at the first azimuth, where the turns about y and x are made
        plan += [Pose("tilt_theta", a, th, 0.0, p.samples) for th in (T, -T)]
        plan += [Pose("tilt_phi", a, 0.0, ph, p.samples) for ph in (T, -T)]
        if p.diagonal:
            plan += [Pose("tilt_both", a, th, ph, p.samples) for th, ph in ((T, T), (T, -T), (-T, -T), (-T, T))]
    if p.tilt_scan_speed_dps > 0:
        v, psi = p.tilt_scan_speed_dps, azimuths[0]  # neither horizontal body axis along a table axis
        for axis, label in (("theta", "y"), ("phi", "x")):
            plan += [Scan(f"scan_{label}_down", axis, 180.0, -180.0, v, psi_t=psi),
                     Scan(f"scan_{label}_up", axis, -180.0, 180.0, v, psi_t=psi)]
    plan.append(Pose("hold_closing", first.psi_t, first.theta_t, first.phi_t, first.samples))
    return plan


def plan_seconds(plan: list[Pose | Scan], motion: Motion = Motion(),
                 start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> float:
    """Table seconds of a plan under ``motion``, as the offline simulator lays it out
    (physics.simulate.plan_timeline: moves as trapezoids, a settle before each hold and scan, holds at
    the sample rate, scans at their own speed)."""
    return float(plan_timeline(plan, motion, start).duration_s)


def _holds(rec: Recording) -> Recording:
    """The samples taken at rest (every step but the scans)."""
    keep = np.array([not str(s).startswith("scan_") for s in rec.step])
    return Recording.from_arrays(rec.t[keep], rec.step[keep], rec.psi_t[keep], rec.theta_t[keep], rec.phi_t[keep],
                                 rec.mag[keep], None if rec.acc is None else rec.acc[keep],
                                 None if rec.temp_c is None else rec.temp_c[keep], dict(rec.meta))


def characterize(p: CharacterizeParams) -> ProcedureGen:
    """Run :func:`characterize_plan`, then for each unit: the nominal calibration (the joint fit of the
    holds; the scans are left to the analysis, since a lag or hysteresis would bias the fit) and the
    discrepancy analysis of the whole recording (physics.discrepancy)."""
    data = Collected()
    yield from visit(characterize_plan(p), p.settle_s, data)

    out = Outcome()
    for slot, rec in data.recordings().items():
        res: dict[str, Any] = {"samples": len(rec), "notes": []}
        yield Compute(f"calibration fit of slot {slot}")
        try:
            res["calibration"] = fit(_holds(rec), "joint", bootstrap=0).to_json()
        except (RecordingError, InsufficientData, ValueError) as e:
            res["calibration"] = None
            res["notes"].append(f"no calibration: {e}")
        progress = yield Compute(f"discrepancy analysis of slot {slot}")
        try:
            from physics.discrepancy import analyze  # written alongside; the plan runs without it
            res["analysis"] = analyze(rec, progress=progress).to_json()
        except ImportError as e:
            res["analysis"] = None
            res["notes"].append(f"no analysis: the discrepancy analyser is not available ({e})")
        except Exception as e:  # noqa: BLE001 - the run's data are kept; a failed analysis must not lose the fit
            res["analysis"] = None
            res["notes"].append(f"no analysis: {type(e).__name__}: {e}")
        out.results[slot] = res
    return out


#: Where the table waits while the operator swaps units (level, at home: the calibration's first pose).
LOAD_POSE = (0.0, 0.0, 0.0)
#: The id of a batch unit's mount prompt: its unit is on the fixture only after it is answered.
MOUNT_PROMPT = "mount"


#: The parameters a batch sets for each of its units (never a request's; no part of the calibration's plan).
BATCH_SETS = ("serial", "unmount")
#: The parameters only an adaptive calibration reads.
ADAPTIVE_ONLY = ("target_level_deg", "target_tilted_deg", "budget_s")


def parameters_said(parameters: dict[str, Any]) -> dict[str, Any]:
    """A run's parameters as its certificate states them: those of its plan, without what a batch set for
    the unit nor, unless adaptive, the targets and budget it never read (a plain run's certificate listed
    "budget_s = 180.0", which a run not adaptive refuses to be given)."""
    return {k: v for k, v in parameters.items()
            if k not in BATCH_SETS and (parameters.get("adaptive") or k not in ADAPTIVE_ONLY)}


class BatchCalibrateParams(CalibrateParams):
    """The calibration of one unit of a batch: the operator is asked to mount it first."""

    #: the unit is taken out on a level platform at home, where the next unit's plan starts: the move
    #: back is part of this unit's calibration (and of its budget), not of the next unit's
    END_POSE: ClassVar[tuple[float, float, float] | None] = LOAD_POSE

    serial: str = Field(min_length=1, description="the unit to mount in slot 0")
    unmount: str | None = Field(None, description="the previous unit (with its result), to take out first")


def batch_calibrate(p: BatchCalibrateParams) -> ProcedureGen:
    """Prompt the operator to swap units, then the full calibration.

    There is no unmount prompt at the end: the unit's verdict is only known once its calibration is
    judged after the run, so the next unit's mount prompt says which unit to take out and how it did
    (the operator sorts it into the right bin), and the batch's summary covers the last one."""
    text = f"mount unit {p.serial} in slot 0"
    if p.unmount:
        text = f"unmount unit {p.unmount}, then {text}"
    # the previous unit's run ended at the load pose (END_POSE); the first unit of a batch may find the
    # table wherever another run left it
    yield Move(*LOAD_POSE)
    yield Prompt(text, id=MOUNT_PROMPT)
    return (yield from calibrate(p))


#: The name of the batch's per-unit procedure (its unit is mounted only after its prompt).
BATCH = "batch_calibrate"

PROCEDURES: dict[str, Procedure] = {
    proc.name: proc for proc in (
        Procedure(NAME, VERSION, CalibrateParams, calibrate, "error-separation calibration, ending in the fit",
                  reserve=adaptive_reserve),
        Procedure("rotate_z", "1", RotateParams, rotate_z, "a turn about z at fixed tilt"),
        Procedure("sweep", "1", SweepParams, sweep, "a full turn of one axis, with each sensor axis's peak"),
        Procedure("accel6", "1", Accel6Params, accel6, "six-position accelerometer calibration"),
        Procedure("level", "1", LevelParams, level, "base tilt by reversal; level the platform"),
        Procedure("evaluate", "1", EvaluateParams, evaluate, "heading error of given calibrations, level and tilted"),
        Procedure("characterize", "1", CharacterizeParams, characterize,
                  "holds from both sides, tilts, turns both ways at two speeds: the discrepancy analysis's run"),
        Procedure(BATCH, "2", BatchCalibrateParams, batch_calibrate,
                  "one unit of a batch: mount prompt, then the error-separation calibration", reserve=adaptive_reserve),
    )
}
