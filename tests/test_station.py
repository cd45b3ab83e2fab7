"""The simulated station as a whole: its config, `compasscal sim`, the world behind the devices and
the fault side channel."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.compass import Compass, CompassTimeout, SerialFixture
from drivers.sim.config import ConfigError, load_config, parse_config, reference_config
from drivers.sim.station import SimStation
from drivers.sim.world import Effect
from drivers.turntable import AxisFault, Turntable
from physics.simulate import World, true_readings

STATION_TOML = """
[world]
inclination_deg = 55.0
declination_deg = 23.0
base_tilt_deg = [0.05, -0.03]
time_scale = 20.0
seed = 3

[table]
homed = true
enabled = true

[[unit]]
serial = "SN-0001"
mag_angles_deg = [[1.3020, 88.7122, 90.1977], [92.2085, 2.2337, 89.6656], [89.3381, 92.3069, 2.4001]]
mag_k = [3268.0, 3163.4, 3201.5]
mag_bias = [423.2, -480.5, 301.2]
mag_noise_lsb = 0.0
acc_k = [16384.0, 16384.0, 16384.0]

[[unit]]
serial = "SN-0002"
transport = "tcp"
mag_k = [2000.0, 2100.0, 1900.0]
"""


def test_config_errors_name_the_key_and_the_expected_form(tmp_path: Path):
    bad = tmp_path / "bad.toml"
    bad.write_text(STATION_TOML.replace("mag_k = [2000.0, 2100.0, 1900.0]", "mag_k = [2000.0]"))
    with pytest.raises(ConfigError, match=r"unit\[1\]\.mag_k: .*expected 3 sensitivities"):
        load_config(bad)
    with pytest.raises(ConfigError, match=r"world\.inclination: unknown key"):
        parse_config({"world": {"inclination": 50}, "unit": [{"serial": "A", "mag_k": [1, 1, 1]}]})
    with pytest.raises(ConfigError, match=r"unit\[0\]\.serial: missing"):
        parse_config({"unit": [{"mag_k": [1, 1, 1]}]})
    with pytest.raises(ConfigError, match="unit vector"):
        parse_config({"unit": [{"serial": "A", "mag_k": [1, 1, 1], "mag_M_o": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}]})
    with pytest.raises(ConfigError, match="not valid TOML"):
        bad.write_text("[world\n")
        load_config(bad)


def test_unset_imperfections_are_ideal():
    cfg = parse_config({"unit": [{"serial": "A", "mag_k": [1000, 1000, 1000]}]})
    u = cfg.unit[0].unit()
    assert cfg.world.world().geometry.is_ideal
    np.testing.assert_array_equal(u.mag.M_o, np.eye(3))
    assert u.mag.noise_lsb == 0 and not u.mag.bias.any() and u.acc.noise_lsb == 0


def test_devices_report_what_the_world_predicts(tmp_path: Path):
    """Over the real protocols: the table reaches the commanded angles and the compasses read exactly
    the physics forward model there (noise-free unit, quantised)."""
    path = tmp_path / "station.toml"
    path.write_text(STATION_TOML)
    cfg = load_config(path)

    async def main() -> None:
        async with SimStation(cfg) as st:
            d = st.describe()
            assert d["modbus"].startswith("tcp://127.0.0.1:") and d["units"] == [1, 2, 3]
            assert d["compasses"][0]["url"].startswith("/dev/pts/") and d["compasses"][1]["url"].startswith("socket://")
            async with Turntable(d["modbus"]) as table, SerialFixture({c["slot"]: c["url"] for c in d["compasses"]}) as fx:
                ids = await fx.identify_all()
                assert [ids[0][1], ids[1][1]] == ["SN-0001", "SN-0002"]
                await table.move_to(120.0, 30.0, -45.0)
                pos = await table.positions()
                np.testing.assert_allclose(pos, [120.0, 30.0, -45.0], atol=0.005)
                # settle as a procedure does (a line measured during the move can still be in flight on a
                # busy host: at time scale 20 its milliseconds are table seconds)
                await asyncio.sleep(0.05)
                got = await fx.read_all(5, timeout=2.0)
            world = World(55.0, 23.0, st.physics_world.geometry)
            mag, _ = true_readings(st.units[0], world, *(np.array([a]) for a in pos))
            np.testing.assert_allclose(np.array([s.mag for s in got[0]]), np.repeat(mag, 5, 0), atol=0.51)
            assert st.truth()[0]["serial"] == "SN-0001"
    asyncio.run(asyncio.wait_for(main(), 30))


def test_effect_hook_reaches_the_wire():
    class HardIron(Effect):
        def mag_raw(self, t, slot, raw, temp_c):
            return raw + np.array([500.0, 0.0, 0.0])
    cfg = reference_config(seed=1, time_scale=20)
    cfg.unit[0].mag_noise_lsb = 0.0

    async def read(effects: list[Effect]) -> np.ndarray:
        async with SimStation(cfg, effects=effects, control_port=None) as st:
            async with Compass(st.describe()["compasses"][0]["url"]) as c:
                return np.array([s.mag for s in await c.read(3, timeout=2.0)], dtype=float)
    plain, shifted = asyncio.run(read([])), asyncio.run(read([HardIron()]))
    np.testing.assert_allclose(shifted.mean(0) - plain.mean(0), [500.0, 0.0, 0.0], atol=1.0)


def test_faults_from_the_config_and_the_control_port():
    cfg = reference_config(seed=1, time_scale=20)
    cfg.table.homed = cfg.table.enabled = True
    cfg = parse_config({**cfg.model_dump(), "fault": [{"kind": "axis_alarm", "axis": "z", "code": 0x21, "at_angle_deg": 45.0}]})

    async def main() -> None:
        async with SimStation(cfg) as st:
            d = st.describe()
            async with Turntable(d["modbus"]) as table, Compass(d["compasses"][0]["url"]) as c:
                await c.set_rate(20)
                t0 = time.monotonic()
                with pytest.raises(AxisFault, match="0x21 drive overheat"):
                    await table.move_to(90.0, 0.0, 0.0)
                assert time.monotonic() - t0 < 3.0
                host, port = d["control"].removeprefix("tcp://").split(":")
                reader, writer = await asyncio.open_connection(host, int(port))
                writer.write(b'{"fault": {"kind": "compass_silent", "slot": 0}}\n{"fault": {"kind": "nonsense"}}\n')
                ok, bad = json.loads(await reader.readline()), json.loads(await reader.readline())
                writer.close()
                assert ok["ok"] and ok["sim_time"] > 0
                assert not bad["ok"] and "kind" in bad["error"]
                with pytest.raises(CompassTimeout):
                    await c.read(10, timeout=1.0)
    asyncio.run(asyncio.wait_for(main(), 30))


def test_sim_command_prints_one_json_line_then_serves_until_interrupted(tmp_path: Path):
    with socket.socket() as s:  # a free port for --compass-tcp-port
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "sim", "--seed", "4", "--time-scale", "10",
                             "--compass-tcp-port", str(free), "--truth", str(tmp_path / "truth.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parent.parent)
    try:
        line = proc.stdout.readline()
        d = json.loads(line)
        assert set(d) >= {"modbus", "units", "compasses"} and d["units"] == [1, 2, 3]
        assert d["compasses"] == [{"slot": 0, "url": f"socket://127.0.0.1:{free}", "serial": d["compasses"][0]["serial"]}]
        truth = json.loads((tmp_path / "truth.json").read_text())
        assert truth[0]["serial"] == d["compasses"][0]["serial"]

        async def talk() -> None:
            async with Turntable(d["modbus"]) as table, Compass(d["compasses"][0]["url"]) as c:
                assert (await c.identify())[1] == d["compasses"][0]["serial"]
                status = await table.status_all()
                assert not status["z"].homed  # a real table starts un-homed
        asyncio.run(asyncio.wait_for(talk(), 20))
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert out == ""  # nothing after the JSON line


def test_sim_command_refuses_a_bad_config_on_stderr(tmp_path: Path):
    bad = tmp_path / "s.toml"
    bad.write_text("[[unit]]\nserial = 'A'\n")
    r = subprocess.run([sys.executable, "-m", "service.cli", "sim", "--config", str(bad)], capture_output=True, text=True,
                       cwd=Path(__file__).parent.parent, timeout=60, env={**os.environ, "COLUMNS": "200"})
    assert r.returncode == 2 and r.stdout == ""
    assert "mag_k" in r.stderr and "missing" in r.stderr


def test_the_simulated_worlds_samples_are_the_sensor_model_plus_white_noise_at_every_attitude():
    """SimWorld.read computes the noise-free output once per attitude and adds the noise per sample: the
    samples' mean is the model's output at each attitude (held or moving) and their spread the unit's noise."""
    from physics.frames import SPECIFIC_FORCE_L
    from physics.table import platform_attitude
    from drivers.sim.world import SimWorld

    cfg = reference_config(seed=3)
    world = cfg.world.world()
    unit = cfg.unit[0].unit()
    angles = [(0.0, 0.0, 0.0), (123.0, -40.0, 75.0)]
    at = {"pose": angles[0]}
    sim = SimWorld(world, [unit], lambda t: at["pose"], rng=np.random.default_rng(5))
    for pose in angles:
        at["pose"] = pose
        C = platform_attitude(*pose, world.geometry)[0]
        want_mag = unit.mag.expected(C.T @ world.field_L)[0]
        want_acc = unit.acc.expected(C.T @ SPECIFIC_FORCE_L)[0]
        reads = [sim.read(0, 0.05 * i) for i in range(4000)]
        mag = np.array([r[0] for r in reads], float)
        acc = np.array([r[1] for r in reads], float)
        assert all(isinstance(v, int) for v in reads[0][0] + reads[0][1])
        assert np.allclose(mag.mean(axis=0), want_mag, atol=5 * unit.mag.noise_lsb / np.sqrt(4000) + 0.05)
        assert np.allclose(mag.std(axis=0), np.hypot(unit.mag.noise_lsb, 1 / np.sqrt(12)), rtol=0.08)
        assert np.allclose(acc.mean(axis=0), want_acc, atol=5 * unit.acc.noise_lsb / np.sqrt(4000) + 0.05)
        assert np.allclose(acc.std(axis=0), np.hypot(unit.acc.noise_lsb, 1 / np.sqrt(12)), rtol=0.08)
    # a table in motion: each sample at its own attitude
    sweep = iter(np.linspace(0.0, 90.0, 50))
    moving = SimWorld(world, [unit.with_noise(0.0, 0.0)], lambda t: (next(sweep), 0.0, 0.0))
    for psi in np.linspace(0.0, 90.0, 50):
        C = platform_attitude(psi, 0.0, 0.0, world.geometry)[0]
        assert moving.read(0, 0.0)[0] == [round(v) for v in unit.mag.expected(C.T @ world.field_L)[0]]


def test_a_station_fault_says_what_to_do_about_it():
    """Station faults said what went wrong only ("CommandRefused: axis z: RESET_FAULT refused: E-stop",
    "CompassTimeout: ..."): each now says what clears it, each remedy once, in the order named, and
    nothing is added to a fault that says it already or that no remedy fits."""
    from drivers import advised

    said = advised("could not reset station lab-1: CommandRefused: axis z: RESET_FAULT refused: E-stop")
    assert said.endswith("(to clear it: release the E-stop; then reset the station)"), said
    both = advised("FixtureError: port lost; stopping the axes failed: AxisUnreachable: axis x: no answer; "
                   "CompassTimeout: slot 1")
    assert both.count("compass's cable") == 1 and both.index("compass's cable") < both.index("axis controller's power"), both
    kept = "axis z: E-stop (release the E-stop, then reset)"
    assert advised(kept) == kept
    assert advised("ValueError: a bug") == "ValueError: a bug"
