"""The engine end to end against the simulated station, over the real protocols: a full calibration
of several units, pause and resume, abort, prompts, and faults mid-run."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers import Station
from drivers.sim.config import StationConfig, parse_config, reference_config
from drivers.sim.station import SimStation
from drivers.station import open_station
from physics.calibration import truth_summary
from physics.precision import unit_precision
from physics.recording import parse_recording
from physics.sensor import random_unit
from physics.simulate import truth_from_json
from physics.table import Motion, move_seconds
from procedures.calibrate import PROCEDURES
from procedures.engine import PAUSED_WATCH_S, Engine, RecordingSink, Replay, RunState, run_procedure
from procedures.events import (COMPUTING_EVERY_S, Computing, Event, Progress, PromptAnswered, PromptAsked, Result, SamplesStored, StateChanged, StepRetried,
                               StepStarted, StepWarning)
from procedures.steps import Acquire, Checkpoint, Compute, Move, Outcome, Park, Procedure, Prompt


@asynccontextmanager
async def on_sim(cfg: StationConfig) -> AsyncIterator[tuple[SimStation, Station]]:
    """A fresh simulated station, and the drivers' station connected to it."""
    async with SimStation(cfg, control_port=None) as st:
        d = st.describe()
        async with open_station(d["modbus"], [c["url"] for c in d["compasses"]], time_scale=cfg.world.time_scale) as station:
            yield st, station


def two_units(time_scale: float = 20.0) -> StationConfig:
    cfg = reference_config(seed=2, time_scale=time_scale)
    u = random_unit(np.random.default_rng(11), mag_noise_lsb=3.0)
    second = {"serial": "SN-RANDOM", "mag_M_o": u.mag.M_o.tolist(), "mag_k": (u.mag.k * 1.5).tolist(),
              "mag_bias": u.mag.bias.tolist(), "mag_noise_lsb": 3.0, "acc_noise_lsb": 4.0, "transport": "tcp"}
    d = cfg.model_dump()
    d["unit"].append(second)
    return parse_config(d)


def run(cfg: StationConfig, name: str, params: dict | None = None, out: Path | None = None, control=None):
    """Run one procedure on a fresh simulated station; returns (result, serials, sink, station, events, wall)."""
    events: list[Event] = []

    async def main():
        async with on_sim(cfg) as (st, station):
            t0 = time.monotonic()
            result, serials, sink = await run_procedure(
                station, name, params, out_dir=out, on_event=events.append,
                engine_hook=(lambda e: control(e, st)) if control else (lambda e: None))
            wall = time.monotonic() - t0
            status = await station.table.status_all()
            return result, serials, sink, st, events, wall, status
    return asyncio.run(asyncio.wait_for(main(), 120))


def test_calibrate_two_units_at_time_scale_20(tmp_path: Path):
    cfg = two_units()
    result, serials, sink, st, events, wall, _ = run(cfg, "calibrate", {}, out=tmp_path)
    assert result.state is RunState.completed, result.reason
    assert wall < 60.0, wall  # about 8 s idle; in real time the plan takes minutes, so time scale 20 is in force
    # every pose's samples with the encoder angles read back, per unit, in a RECORDING.md file
    for slot, serial in serials.items():
        rec = parse_recording(sink.path(slot).read_text())
        assert rec.serial == serial and rec.meta["procedure"] == "calibrate"
        assert len(rec) == 18 * 60 and set(rec.step) == {"rotate_z", "sweep_y", "sweep_x"}
        # the table's working seconds: at least the holds' sampling (the steps between samples of one pose),
        # at most the recording's span (plus the end of the last hold after its last sample); the host's gaps
        # between steps are not table time, and under load they may be many seconds at time scale 20
        dt = np.diff(rec.t)
        held = dt[dt < 5 * np.median(dt)].sum()
        assert np.all(dt >= 0) and 0.95 * 18 * 59 * np.median(dt) < held <= result.table_seconds <= rec.t[-1] + 1.0, (held, rec.t[-1], result.table_seconds)
        unit, world = truth_from_json(st.truth()[slot])
        assert "calibration" in result.outcome.results[slot], result.outcome.results[slot]
        cal = result.outcome.results[slot]["calibration"]
        s = truth_summary(cal, unit, world)
        # as good as the unit's noise allows: within 1.5 times the bound its own data put on the error
        # 99 % of the time (the samples' timing, hence their noise, differs from run to run: the random
        # unit's level error ranged 0.020-0.031 deg unloaded, its 99 % bound 0.031)
        bound = unit_precision(rec, cal).quantile(0.99)
        assert s["level_max"] < 1.5 * bound["level"] and s["tilted_max"] < 1.5 * bound["tilted"], (serial, s, bound)
        # and those bounds are tight: the random unit's level bound was 0.030-0.033 in 12 idle runs and 0.030-0.034
        # in 18 runs beside 1-3 busy processes (2026-12-03: the residuals equal the holds' scatter either way, so
        # load does not widen it; it once came to 0.0350 under CI). The check is against a vacuous bound, not that.
        # (Idle runs repeat much of the simulator's seeded noise draws, so their errors are not independent: the
        # random unit's level error was 0.009-0.036 idle, 0.010-0.018 beside three busy processes.)
        assert bound["level"] < 0.04 and bound["tilted"] < 0.065, (serial, bound)
    progress = [e.percent for e in events if isinstance(e, Progress)]
    assert progress == sorted(progress) and progress[-1] == 100.0
    assert [e.state for e in events if isinstance(e, StateChanged)] == [RunState.running, RunState.completed]
    assert [e.units for e in events if isinstance(e, Result)] == [tuple(sorted(serials))]
    json.dumps([(e.kind, e.data()) for e in events])  # what the service stores and streams


def test_an_axis_alarm_mid_run_fails_the_run_stops_the_table_and_keeps_the_samples(tmp_path: Path):
    cfg = reference_config(seed=3, time_scale=20)
    d = cfg.model_dump()
    d["fault"] = [{"kind": "axis_alarm", "axis": "y", "code": 0x30, "at_angle_deg": 100.0}]
    result, serials, sink, st, events, wall, status = run(parse_config(d), "calibrate", {}, out=tmp_path)
    assert result.state is RunState.failed
    assert "0x30 overload" in result.reason and "axis y" in result.reason
    assert not any(s.moving for s in status.values())
    rec = parse_recording(sink.path(0).read_text())
    assert len(rec) == (8 + 1) * 60  # the level turn and the first sweep pose, all kept
    assert rec.step[-1] == "sweep_y"


def test_a_fault_on_the_way_to_the_rest_pose_is_a_warning_and_the_run_keeps_its_result(tmp_path: Path):
    """The move that parks the table once the data are in (a batch unit's load pose) faults: the axes
    stop and the run says so, but it completes with its result (a unit's whole calibration is not lost
    to the move back); a fault on an ordinary move still fails the run."""
    def parked(params) -> object:
        yield Move(30.0)
        data = yield Acquire(5, "check")
        yield Park(200.0)  # through the alarm at 100 deg
        return Outcome({0: {"n": len(data[0]) if data else 0}})
    cfg = reference_config(seed=3, time_scale=20)
    d = cfg.model_dump()
    d["fault"] = [{"kind": "axis_alarm", "axis": "z", "code": 0x30, "at_angle_deg": 100.0}]
    proc = Procedure("parked", "1", PROCEDURES["rotate_z"].params, parked)

    async def main():
        async with on_sim(parse_config(d)) as (st, station):
            events: list[Event] = []
            result = await Engine(station, proc, proc.validate({}), RecordingSink(None, {}), on_event=events.append).run()
            return result, events, await station.table.status_all()
    result, events, status = asyncio.run(asyncio.wait_for(main(), 30))
    assert result.state is RunState.completed and result.outcome.results[0] == {"n": 5}, result
    said = [e.warning for e in events if isinstance(e, StepWarning)]
    assert any("did not reach its rest pose" in m and "0x30 overload" in m for m in said), said
    assert not any(s.moving for s in status.values())
    plain = Procedure("plain", "1", proc.params, lambda params: (yield Move(200.0)))
    result, *_ = asyncio.run(asyncio.wait_for(_run_on(parse_config(d), plain), 30))
    assert result.state is RunState.failed and "0x30 overload" in result.reason


def test_a_table_that_cannot_be_stopped_is_said_in_the_runs_reason():
    """Every axis controller gone silent mid-move (the table's bus cut): the run fails for the move and
    its reason says the axes could not be stopped either (said only as an event before, while the run's
    reason named the move alone: a table that may still be turning)."""
    proc = Procedure("far", "1", PROCEDURES["rotate_z"].params, lambda params: (yield Move(170.0)))
    cfg = reference_config(seed=3, time_scale=5)

    async def main():
        async with on_sim(cfg) as (st, station):
            events: list[Event] = []
            engine = Engine(station, proc, proc.validate({}), RecordingSink(None, {}), on_event=events.append)
            loop = asyncio.get_running_loop()
            loop.call_later(0.3, lambda: [st.table.silence(a, True) for a in "zyx"])
            result = await engine.run()
            for a in "zyx":
                st.table.silence(a, False)
            return result, events
    result, events = asyncio.run(asyncio.wait_for(main(), 30))
    assert result.state is RunState.failed
    assert "stopping the axes failed" in result.reason and not result.reason.startswith("stopping"), result.reason
    assert any(isinstance(e, StepWarning) and e.warning.startswith("stopping the axes failed") for e in events)


async def _run_on(cfg: StationConfig, proc: Procedure):  # noqa: ANN202
    async with on_sim(cfg) as (st, station):
        return await Engine(station, proc, proc.validate({}), RecordingSink(None, {})).run(), None


def test_an_axis_alarm_raised_while_the_table_holds_fails_the_run_naming_it(tmp_path: Path):
    """The fault probe's case: an encoder error raised while the last pose acquired (the table holding,
    no move to refuse) went unnoticed: the run completed, the unit was certified, the station read idle.
    Each pose's samples are now followed by a status poll of every axis (in place of the positions read,
    the same round trips): the run fails naming the fault, every sample kept."""
    cfg = reference_config(seed=5, time_scale=20)
    fired = {}
    poses = 18

    def control(engine: Engine, st: SimStation) -> None:
        def on_event(e: Event, inner=engine.on_event) -> None:
            inner(e)
            if isinstance(e, StepStarted) and isinstance(e.step, Acquire) and engine._samples >= (poses - 1) * 60 and not fired:
                fired["t"] = time.monotonic()  # while the last pose acquires
                asyncio.get_running_loop().call_later(0.05, st.table.alarm, "z", 0x28)
        engine.on_event = on_event
    result, serials, sink, st, events, wall, status = run(cfg, "calibrate", {}, out=tmp_path, control=control)
    assert fired and result.state is RunState.failed, result.reason
    assert "axis z: fault 0x28 encoder error at the end of" in result.reason and "cannot be trusted" in result.reason
    assert result.outcome is None or not result.outcome.results  # nothing certified from it
    assert len(parse_recording(sink.path(0).read_text())) == poses * 60  # every sample kept
    assert not any(s.moving for s in status.values())


def test_a_compass_hiccup_is_retried_and_every_pose_keeps_exactly_its_planned_count(tmp_path: Path):
    """A compass silent for 1.5 s mid-pose (a USB hub reset): the acquisition times out, keeps what
    arrived and the retry reads only the rest, so the run completes with 60 samples in every pose."""
    cfg = reference_config(seed=5, time_scale=20)
    fired = {}

    def control(engine: Engine, st: SimStation) -> None:
        def on_event(e: Event, inner=engine.on_event) -> None:
            inner(e)
            if isinstance(e, StepStarted) and isinstance(e.step, Acquire) and engine._samples >= 2 * 60 and not fired:
                fired["t"] = time.monotonic()  # a few samples into the third pose (0.15 s of wall time)
                loop = asyncio.get_running_loop()
                loop.call_later(0.05, st.compasses[0].go_silent, True)
                loop.call_later(1.55, st.compasses[0].go_silent, False)
        engine.on_event = on_event
    result, serials, sink, st, events, wall, status = run(cfg, "calibrate", {}, out=tmp_path, control=control)
    assert result.state is RunState.completed, result.reason
    assert any(isinstance(e, StepRetried) and e.attempt == 1 for e in events)
    rec = parse_recording(sink.path(0).read_text())
    steps, counts = np.unique([f"{s}@{p:.1f},{t:.1f},{f:.1f}" for s, p, t, f in zip(rec.step, rec.psi_t, rec.theta_t, rec.phi_t)],
                              return_counts=True)
    assert len(steps) == 18 and set(counts) == {60}, dict(zip(steps, counts))


def test_an_axis_that_goes_silent_mid_acquisition_keeps_every_sample_received(tmp_path: Path):
    """The fault probe's case: an axis controller stops answering while a pose is acquiring. The
    table's position cannot be read back after the samples, so the run fails, but every sample that
    pose received is kept (they go to the sink before the table is asked again)."""
    cfg = reference_config(seed=6, time_scale=20)
    fired = {}

    def control(engine: Engine, st: SimStation) -> None:
        def on_event(e: Event, inner=engine.on_event) -> None:
            inner(e)
            if isinstance(e, StepStarted) and isinstance(e.step, Acquire) and engine._samples >= 2 * 60 and not fired:
                fired["t"] = time.monotonic()  # while the third pose acquires (0.15 s of wall time)
                asyncio.get_running_loop().call_later(0.03, st.table.silence, "z", True)
            if isinstance(e, StateChanged) and e.state is RunState.failed:
                st.table.silence("z", False)  # answers again for the final status read
        engine.on_event = on_event
    result, serials, sink, st, events, wall, status = run(cfg, "calibrate", {}, out=tmp_path, control=control)
    assert fired and result.state is RunState.failed, result.reason
    rec = parse_recording(sink.path(0).read_text())
    poses, counts = np.unique([f"{p:.1f},{t:.1f},{f:.1f}" for p, t, f in zip(rec.psi_t, rec.theta_t, rec.phi_t)],
                              return_counts=True)
    assert len(rec) == 3 * 60 and set(counts) == {60}, (result.reason, dict(zip(poses, counts)))
    last = [e for e in events if isinstance(e, StepStarted)][-1]
    assert isinstance(last.step, Acquire) and "axis z" in result.reason  # it failed in that acquisition


def test_a_compass_that_goes_silent_fails_the_run_within_seconds_with_the_samples_kept(tmp_path: Path):
    cfg = reference_config(seed=4, time_scale=20)
    fired = {}

    def control(engine: Engine, st: SimStation) -> None:
        def on_event(e: Event, inner=engine.on_event) -> None:
            inner(e)
            if isinstance(e, SamplesStored) and e.count >= 3 * 60 and not fired:
                fired["t"] = time.monotonic()
                st.compasses[0].go_silent(True)
        engine.on_event = on_event
    result, serials, sink, st, events, wall, status = run(cfg, "calibrate", {}, out=tmp_path, control=control)
    assert result.state is RunState.failed and "CompassTimeout" in result.reason
    assert time.monotonic() - fired["t"] < 8.0
    assert len(parse_recording(sink.path(0).read_text())) >= 3 * 60
    assert not any(s.moving for s in status.values())


def test_pause_resume_and_abort_at_checkpoints():
    cfg = reference_config(seed=5, time_scale=20)
    seen: list[str] = []

    def control(engine: Engine, st: SimStation) -> None:
        inner = engine.on_event

        def on_event(e: Event) -> None:
            inner(e)
            if isinstance(e, StateChanged):
                seen.append(e.state.value)
                if e.state is RunState.paused:
                    asyncio.get_running_loop().call_later(0.3, engine.resume)
            if isinstance(e, SamplesStored) and e.count == 60:
                engine.pause()
            if isinstance(e, SamplesStored) and e.count == 3 * 60:
                engine.abort("operator pressed abort")
                engine.abort("pressed again")  # the first abort is what stopped the run (the second overwrote it)
        engine.on_event = on_event
    result, *_ = run(cfg, "rotate_z", {"samples": 60}, control=control)
    assert seen == ["running", "paused", "running", "aborted"]
    assert result.state is RunState.aborted and result.reason == "operator pressed abort"
    assert result.samples == 3 * 60


@pytest.mark.parametrize("fault, said, within_s", [
    # an axis alarm: found by the next status poll
    (lambda st: st.table.alarm("y", 0x28), ["axis y: fault 0x28 encoder error while the run was paused"], 1.0),
    # a compass gone silent: the next read's stale second and its retry's
    (lambda st: st.compasses[0].go_silent(True), ["CompassTimeout", "no sample", "while the run was paused"], 2 * 1.3 + 1.0),
], ids=["axis alarm", "compass silent"])
def test_a_fault_while_paused_fails_the_run_at_once(fault: Any, said: list[str], within_s: float):
    """An axis alarm, or a compass that stopped talking, while the run stood paused was said only when the
    operator resumed; the run and the station looked healthy meanwhile. The paused engine polls the
    table's status and reads a sample of each streaming compass once a second."""
    cfg = reference_config(seed=5, time_scale=20)
    seen: dict[str, float] = {}

    def control(engine: Engine, st: SimStation) -> None:
        inner = engine.on_event

        def on_event(e: Event) -> None:
            inner(e)
            if isinstance(e, StateChanged) and e.state is RunState.paused:
                seen["paused"] = time.monotonic()
                asyncio.get_running_loop().call_later(0.2, fault, st)
            if isinstance(e, StateChanged) and e.state is RunState.failed:
                seen["failed"] = time.monotonic()
            if isinstance(e, SamplesStored) and e.count == 60:
                engine.pause()
        engine.on_event = on_event
    result, *_, status = run(cfg, "rotate_z", {"samples": 60}, control=control)
    assert result.state is RunState.failed and all(w in result.reason for w in said), result.reason
    assert seen["failed"] - seen["paused"] < 0.2 + 2 * PAUSED_WATCH_S + within_s  # not left for the operator to find
    assert result.samples == 60
    assert not any(s.moving for s in status.values())


def test_a_resumed_run_counts_no_more_table_time_than_its_samples_span():
    """A run resuming an interrupted one replays its samples up to a checkpoint from where the
    interrupted run left the table (here the far end of a whole calibration): the replayed steps count
    their nominal seconds, but never more than the replayed samples span (CI once saw the first move
    back, long from there, push the table time 4 s beyond the recording's last sample)."""
    cfg = reference_config(seed=4, time_scale=20)

    async def main():
        async with on_sim(cfg) as (st, station):
            first, _, sink1 = await run_procedure(station, "calibrate", {"samples": 20})
            assert first.state is RunState.completed, first.reason
            old = sink1.recording(0)
            samples = {str(label): {0: old.select(old.step == label)} for label in dict.fromkeys(old.step.tolist())}
            replay = Replay(1, 6, samples)
            second, _, sink2 = await run_procedure(station, "calibrate", {"samples": 20},
                                                   engine_hook=lambda e: setattr(e, "replay", replay))
            return second, old, sink2.recording(0)
    result, old, new = asyncio.run(asyncio.wait_for(main(), 120))
    assert result.state is RunState.completed, result.reason
    n = 6 * 20  # the replayed poses, as they were
    assert np.array_equal(new.mag[:n], old.mag[:n]) and new.t[n] > new.t[n - 1]
    assert 0.9 * (new.t[-1] - new.t[n]) < result.table_seconds <= new.t[-1] + 1.0, (result.table_seconds, new.t[n - 1], new.t[-1])


def test_prompts_wait_for_the_operator():
    def mount(params) -> object:
        answer = yield Prompt("mount unit SN-7 in slot 0", id="mount")
        yield Move(30.0)
        data = yield Acquire(5, "check")
        yield Checkpoint("done")
        return Outcome({0: {"answer": answer, "n": len(data[0])}})
    proc = Procedure("mount", "1", PROCEDURES["rotate_z"].params, mount)
    cfg = reference_config(seed=6, time_scale=20)

    async def main():
        async with on_sim(cfg) as (st, station):
            events: list[Event] = []
            eng = Engine(station, proc, proc.validate({}), RecordingSink(None, {}), on_event=events.append)
            task = asyncio.create_task(eng.run())
            while not any(isinstance(e, PromptAsked) for e in events):
                await asyncio.sleep(0.01)
            assert not eng.answer("other", "x")
            assert eng.answer("mount", "mounted")
            return await task
    result = asyncio.run(asyncio.wait_for(main(), 30))
    assert result.state is RunState.completed and result.outcome.results[0] == {"answer": "mounted", "n": 5}


def test_the_procedures_own_work_does_not_stall_the_engines_loop():
    """A procedure that computes between steps (its fits; a characterize run's analysis takes seconds)
    does so off the engine's loop: the loop that polls the table, takes the operator's commands and
    beats the worker's heartbeat keeps its pace meanwhile, and the outcome still comes back."""
    busy_s = 1.5

    def busy(params) -> object:
        yield Move(10.0)
        data = yield Acquire(5, "check")
        report = yield Compute("busy work")
        if data:  # not while the plan is laid out on empty replies
            t = time.monotonic()
            while time.monotonic() - t < busy_s:  # CPU-bound, holding the interpreter as a fit does
                sum(range(1000))
                report("spinning", (time.monotonic() - t) / busy_s)
        yield Move(20.0)
        return Outcome({0: {"n": len(data[0])}})
    proc = Procedure("busy", "1", PROCEDURES["rotate_z"].params, busy)
    cfg = reference_config(seed=6, time_scale=20)

    async def main():
        gaps: list[float] = []

        async def tick() -> None:
            last = time.monotonic()
            while True:
                await asyncio.sleep(0.01)
                now = time.monotonic()
                gaps.append(now - last)
                last = now
        async with on_sim(cfg) as (st, station):
            ticker = asyncio.create_task(tick())
            t0 = time.monotonic()
            result = await Engine(station, proc, proc.validate({}), RecordingSink(None, {}), on_event=events.append).run()
            wall = time.monotonic() - t0
            ticker.cancel()
            return result, gaps, wall
    events: list[Event] = []
    result, gaps, wall = asyncio.run(asyncio.wait_for(main(), 30))
    assert result.state is RunState.completed and result.outcome.results[0] == {"n": 5}, result.reason
    assert wall >= busy_s  # the work was done during the run
    assert max(gaps) < busy_s / 3, max(gaps)  # on the loop it would stall it for busy_s at once
    # the operator sees what is computed and how far it has got, twice a second (not once per report)
    assert [e.step for e in events if isinstance(e, StepStarted) and isinstance(e.step, Compute)] == [Compute("busy work")]
    told = [e.data()["step"] for e in events if isinstance(e, Computing)]
    assert told and all(d["kind"] == "compute" and d["label"] == "busy work" and d["stage"] == "spinning" for d in told)
    assert [d["percent"] for d in told] == sorted(d["percent"] for d in told) and len(told) <= busy_s / COMPUTING_EVERY_S + 1
    # the computation is not table time: at time scale 20 its 1.5 s would have counted 30 s (two short
    # moves and a 5-sample hold take a few seconds)
    assert result.table_seconds < 10.0, result.table_seconds


def test_host_work_after_a_holds_last_line_is_not_table_time(monkeypatch):
    """A hold ends with its last line. What the host does with the lines after it (placing them on
    the sample clock, sending them to the sink, the check that the table held) is host work: at time
    scale 20 its 100 ms per hold would count two seconds each. Here it takes 100 ms per hold, and the table
    time stays the moves' and holds' own."""
    def plan(params) -> object:
        for k in range(4):
            yield Move(10.0 * (k + 1))
            yield Acquire(20, f"hold {k}")
        return Outcome({})
    proc = Procedure("holds", "1", PROCEDURES["rotate_z"].params, plan)
    keep = Engine._keep

    def slow_keep(self, *args, **kwargs):
        time.sleep(0.1)  # the host busy with the lines it got (holding the loop, as a CPU-bound step does)
        return keep(self, *args, **kwargs)

    async def main(slow: bool) -> float:
        if slow:
            monkeypatch.setattr(Engine, "_keep", slow_keep)
        async with on_sim(reference_config(seed=3, time_scale=20)) as (st, station):
            result = await Engine(station, proc, proc.validate({}), RecordingSink(None, {})).run()
        monkeypatch.setattr(Engine, "_keep", keep)
        assert result.state is RunState.completed, result.reason
        return result.table_seconds
    # the best of two each: a loaded machine (CI's three test processes on two cores) only adds
    quick = min(asyncio.run(asyncio.wait_for(main(False), 60)) for _ in range(2))
    slow = min(asyncio.run(asyncio.wait_for(main(True), 60)) for _ in range(2))
    # four 1-s holds of 20 lines and four 10-deg moves (0.9 s each): ~8 s; 100 ms x 20 per hold would add 8 s
    assert slow < quick + 3.0, (quick, slow)


def test_a_runs_plan_seconds_start_where_the_table_stands():
    """A run after another starts where that one left the table: its first move back is table time
    the plan's nominal seconds count too (laid out from home they would not), so the table time, the
    progress and the time left agree with the plan from there."""
    def plan(params) -> object:
        yield Move(0.0)
        yield Acquire(20, "home")
        yield Move(240.0)
        yield Acquire(20, "away")
        return Outcome({})
    proc = Procedure("there and back", "1", PROCEDURES["rotate_z"].params, plan)

    async def main():
        async with on_sim(reference_config(seed=4, time_scale=20)) as (st, station):
            out = []
            for _ in range(2):
                events: list[Event] = []
                result = await Engine(station, proc, proc.validate({}), RecordingSink(None, {}), on_event=events.append).run()
                assert result.state is RunState.completed, result.reason
                out.append((result, [e for e in events if isinstance(e, Progress)]))
            return out, Motion(station.speed_dps, station.accel_dps2, station.settle_s)
    ((first, p1), (second, p2)), motion = asyncio.run(asyncio.wait_for(main(), 60))
    back = move_seconds([240.0], motion)  # the second run's first move: 8.5 s at 30 deg/s (and the settling)
    assert abs(second.plan_seconds - first.plan_seconds - back) < 1e-6, (first.plan_seconds, second.plan_seconds)
    for result in (first, second):
        # one-sided: the table cannot beat the plan, but at time scale 20 each move's few ms of host latency
        # count 20 times over, a large share of an 11-s plan on a busy machine (13 % once in CI; a plan
        # without its first move back would be half the table time); benchmarks/procedure.py holds the target
        ratio = result.table_seconds / result.plan_seconds
        assert 0.97 < ratio < 1.25, (result.table_seconds, result.plan_seconds)
    # the first move is nearly half of the second run's plan (none of the first's), and its progress says so
    settle = 100.0 * motion.settle_s
    assert abs(p1[0].percent - settle / first.plan_seconds) < 0.1, p1[0]
    assert abs(p2[0].percent - (100.0 * back + settle) / second.plan_seconds) < 0.1, p2[0]


def test_an_abort_while_the_procedure_computes_ends_the_run_at_once():
    """The operator's abort does not wait for a fit or an analysis to finish: the run is aborted, its
    samples kept, while the computation ends on its own in its thread."""
    computing, stop = threading.Event(), threading.Event()

    def slow(params) -> object:
        yield Move(10.0)
        data = yield Acquire(5, "check")
        if data:  # not while the plan is laid out
            computing.set()
            stop.wait(10.0)  # a long analysis
        yield Move(20.0)
        return Outcome({0: {"n": len(data[0])}})
    proc = Procedure("slow", "1", PROCEDURES["rotate_z"].params, slow)
    cfg = reference_config(seed=6, time_scale=20)

    async def main():
        async with on_sim(cfg) as (st, station):
            eng = Engine(station, proc, proc.validate({}), RecordingSink(None, {}))
            task = asyncio.create_task(eng.run())
            while not computing.is_set():
                await asyncio.sleep(0.01)
            eng.abort()
            t = time.monotonic()
            result = await task
            return result, time.monotonic() - t, st.table.true_angles()[0]
    try:
        result, took, z = asyncio.run(asyncio.wait_for(main(), 30))
    finally:
        stop.set()
    assert result.state is RunState.aborted and result.samples == 5, (result.state, result.reason)
    assert took < 2.0, took  # not the 10 s the computation would take
    assert abs(z - 10.0) < 0.01  # the move after the computation never started


def test_a_run_on_a_table_already_in_fault_fails_before_moving():
    cfg = reference_config(seed=7, time_scale=20)
    cfg.table.homed = cfg.table.enabled = True

    async def main():
        async with SimStation(cfg, control_port=None) as st:
            st.table.alarm("x", 0x28)
            await asyncio.sleep(0.05)
            d = st.describe()
            async with open_station(d["modbus"], [c["url"] for c in d["compasses"]], time_scale=20) as station:
                result, _, sink = await run_procedure(station, "rotate_z", {})
                return result, sink
    result, sink = asyncio.run(asyncio.wait_for(main(), 30))
    assert result.state is RunState.failed and "0x28 encoder error" in result.reason and "reset it first" in result.reason
    assert sink.parts == {}


def test_events_keep_their_wire_format():
    """The service stores ``(kind, data())`` in run_events and streams it as server-sent events:
    each event class makes exactly the JSON its clients read."""
    cases: list[tuple[Event, str, dict]] = [
        (StateChanged(RunState.failed, "AxisFault: boom", 12.5), "state",
         {"state": "failed", "reason": "AxisFault: boom", "t": 12.5}),
        (StateChanged(RunState.running, None, 0.0), "state", {"state": "running", "reason": None, "t": 0.0}),
        (StepStarted(Move(30.0, 5.0), 1.5), "step", {"step": {"kind": "move", "psi": 30.0, "theta": 5.0, "phi": 0.0}, "t": 1.5}),
        (StepStarted(Acquire(60, "rotate_z"), 2.0), "step",
         {"step": {"kind": "acquire", "samples": 60, "step": "rotate_z"}, "t": 2.0}),
        (StepRetried(1, "MoveTimeout: late"), "step", {"retry": 1, "reason": "MoveTimeout: late"}),
        (StepWarning("stopping the axes failed: x"), "step", {"warning": "stopping the axes failed: x"}),
        (Progress(42.5, 10.0, 13.5, 600), "progress", {"percent": 42.5, "table_s": 10.0, "left_s": 13.5, "samples": 600}),
        (SamplesStored("sweep_y", 660), "samples", {"step": "sweep_y", "count": 660}),
        (PromptAsked("mount", "mount unit SN-7 in slot 0"), "prompt", {"id": "mount", "text": "mount unit SN-7 in slot 0"}),
        (PromptAnswered("mount", "done"), "prompt", {"id": "mount", "answered": True, "answer": "done"}),
        (Result((0, 1)), "result", {"units": [0, 1]}),
        (Result(()), "result", {"units": []}),
    ]
    for event, kind, data in cases:
        assert event.kind == kind and event.data() == data, event
        assert json.loads(json.dumps(event.data())) == data


def test_lines_measured_while_the_table_moved_but_delivered_late_are_not_a_poses_samples(tmp_path: Path):
    """A busy host (or a USB adapter's latency timer) holds a compass's lines back and delivers them in
    one burst after the pose's acquisition has begun. Lines measured while the table was still moving
    must not count as the pose's samples: each pose keeps exactly its 60 samples, all at its angles."""
    cfg = reference_config(seed=7, time_scale=20)
    delayed: list[int] = []

    def control(engine: Engine, st: SimStation) -> None:
        def on_event(e: Event, inner=engine.on_event) -> None:
            inner(e)
            # from the second pose on, when the compass's history is still short
            if isinstance(e, StepStarted) and isinstance(e.step, Move) and engine._samples >= 60 and len(delayed) < 4:
                delayed.append(engine._samples)  # hold everything from the move's start until well after it
                st.compasses[0].delay_output(0.35)
        engine.on_event = on_event
    result, serials, sink, st, events, wall, status = run(cfg, "calibrate", {}, out=tmp_path, control=control)
    assert result.state is RunState.completed, result.reason
    assert len(delayed) == 4
    rec = parse_recording(sink.path(0).read_text())
    poses = [f"{s}@{p:.1f},{t:.1f},{f:.1f}" for s, p, t, f in zip(rec.step, rec.psi_t, rec.theta_t, rec.phi_t)]
    names, counts = np.unique(poses, return_counts=True)
    assert len(names) == 18 and set(counts) == {60}, dict(zip(names, counts))
    # every sample reads the field at its pose's angles: within noise of the pose's median (3 LSB
    # noise; a line from a move 45 deg away is thousands of LSB off)
    for name in names:
        m = rec.mag[np.array(poses) == name]
        worst = float(np.max(np.abs(m - np.median(m, axis=0))))
        assert worst < 25.0, (name, worst)


def test_the_recording_sink_appends_each_acquisition_and_the_file_reads_back_as_everything_kept(tmp_path: Path):
    from physics.recording import Recording

    def part(i: int, n: int, extra: dict | None = None) -> Recording:
        t = 10.0 * i + 0.05 * np.arange(n)
        return Recording.from_arrays(t=t, step=[f"pose{i}"] * n, psi_t=np.full(n, 45.0 * i), theta_t=np.zeros(n),
                                     phi_t=np.zeros(n), mag=np.arange(3 * n).reshape(n, 3) + 1000.0 * i,
                                     acc=np.ones((n, 3)) * 16384.0, temp_c=np.full(n, 23.5),
                                     meta={"serial": "SN-1", "slot": "0"}, extra=extra)

    sink = RecordingSink(tmp_path, {0: "SN-1"}, {"procedure": "calibrate"})
    for i, n in enumerate([60, 1, 60]):
        sink.add(0, part(i, n))
        back = parse_recording(sink.path(0).read_text())
        whole = sink.recording(0)
        assert len(back) == len(whole) == sum([60, 1, 60][:i + 1])
        assert np.array_equal(back.t, whole.t) and np.array_equal(back.mag, whole.mag) and list(back.step) == list(whole.step)
        assert back.meta["procedure"] == "calibrate" and back.serial == "SN-1"
    # a part with other columns cannot be appended under the file's header: the file is written anew
    sink.add(0, part(3, 2, extra={"note": ["a", "b"]}))
    back = parse_recording(sink.path(0).read_text())
    assert len(back) == 123 and list(back.extra["note"][-2:]) == ["a", "b"]
    # and a part without it, under the file's header that now has it: written anew again
    sink.add(0, part(4, 3))
    back = parse_recording(sink.path(0).read_text())
    assert len(back) == 126 and np.array_equal(back.mag, sink.recording(0).mag) and list(back.step[-3:]) == ["pose4"] * 3


def test_the_table_time_note_says_a_mismatch_the_host_s_latency_or_nothing() -> None:
    """A table time far from the plan's is a simulator at another time scale (mismatch: the caller says how
    to give it); stretched by a quarter or more at a high time scale, the host's latency (an outside prober:
    181 s for a 108-s plan at time scale 200, no word); a run that never moved the table (every unit
    refused) said it was "0 times the plan's nominal", which it is not to be told."""
    from procedures.engine import RunResult, table_time_note
    from procedures.states import RunState

    def run(table_s: float, samples: int = 1000) -> RunResult:
        return RunResult(RunState.completed, None, None, samples, table_s, 108.0)

    assert table_time_note(run(4.2), False, 20.0)[1] is True
    assert table_time_note(run(600.0), False, 1.0)[1] is True
    text, mismatch = table_time_note(run(181.0), False, 200.0)
    assert not mismatch and "at time scale 200" in text and "time scale 20 or less" in text
    assert table_time_note(run(181.0), False, 1.0) is None  # at time scale 1 the host adds nothing like it
    assert table_time_note(run(181.0), True, 200.0) is None  # an adaptive run's extension adds time
    assert table_time_note(run(112.0), False, 200.0) is None
    assert table_time_note(run(0.0, samples=0), False, 20.0) is None
