"""Mission files for the simulator (`python -m companion.sim serve --mission FILE`): both formats,
the home item per personality, one-line errors, and the service flying a loaded mission with
`route.source: mission` against the simulator."""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.config import parse_config
from companion.harness.fly import service_config
from companion.service import Service
from companion.service.link import UdpOutLink
from companion.service.notify import SystemdNotifier
from companion.sim.mavlink import SimServer
from companion.sim.mavlink.missionfile import MissionFileError, load_mission
from companion.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
WP = mavlink.MAV_CMD_NAV_WAYPOINT
REL = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT


def _wpl(rows: list[tuple[float, float, float]], home: tuple[float, float, float]) -> str:
    lines = ["QGC WPL 110", f"0\t1\t0\t16\t0\t0\t0\t0\t{home[0]}\t{home[1]}\t{home[2]}\t1"]
    for k, (lat, lon, alt) in enumerate(rows, start=1):
        lines.append(f"{k}\t0\t{REL}\t{WP}\t0\t0\t0\t0\t{lat:.8f}\t{lon:.8f}\t{alt}\t1")
    return "\n".join(lines) + "\n"


def _plan(rows: list[tuple[float, float, float]], home: tuple[float, float, float]) -> str:
    items = [
        {
            "type": "SimpleItem",
            "command": WP,
            "frame": REL,
            "params": [0, 0, 0, None, lat, lon, alt],
            "autoContinue": True,
            "doJumpId": k + 1,
        }
        for k, (lat, lon, alt) in enumerate(rows)
    ]
    doc = {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "mission": {"version": 2, "items": items, "plannedHomePosition": list(home)},
    }
    return json.dumps(doc)


ROWS = [(-35.3630, 149.1650, 10.0), (-35.3625, 149.1655, 12.5)]
HOME = (-35.3632, 149.1652, 584.0)


@pytest.mark.parametrize("fmt", ["wpl", "plan"])
@pytest.mark.parametrize("has_home", [True, False])
def test_both_formats_give_the_same_items(tmp_path: Path, fmt: str, has_home: bool) -> None:
    path = tmp_path / ("m.waypoints" if fmt == "wpl" else "m.plan")
    path.write_text(_wpl(ROWS, HOME) if fmt == "wpl" else _plan(ROWS, HOME), encoding="utf-8")
    items = load_mission(path, has_home_item=has_home)
    assert [it.seq for it in items] == list(range(len(items)))
    waypoints = items[1:] if has_home else items
    assert len(waypoints) == len(ROWS)
    for it, (lat, lon, alt) in zip(waypoints, ROWS, strict=True):
        assert (it.command, it.frame) == (WP, REL)
        assert (it.x, it.y) == (round(lat * 1e7), round(lon * 1e7))
        assert it.z == pytest.approx(alt)
    if has_home:
        assert (items[0].x, items[0].y) == (round(HOME[0] * 1e7), round(HOME[1] * 1e7))


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("hello\n", "neither a QGroundControl plan"),
        ("{not json", "not JSON"),
        ('{"fileType": "Plan"}', "no mission.items"),
        ('{"fileType": "Plan", "mission": {"items": [{"type": "ComplexItem"}]}}', "expanded"),
        ("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t1\t2\n", "expected 12 columns"),
        ("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\tx\t2\t3\t1\n", "not a number"),
        ("QGC WPL 110\n1\t1\t0\t16\t0\t0\t0\t0\t1\t2\t3\t1\n", "item 1 where item 0"),
        ("QGC WPL 110\n0\t1\t3\t16\t0\t0\t0\t0\t91\t2\t3\t1\n", "out of range"),
        ("QGC WPL 110\n0\t1\t3\t16\t0\t0\t0\t0\tnan\t2\t3\t1\n", "not a finite"),
    ],
)
def test_bad_files_are_one_line_errors(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "bad.plan"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(MissionFileError) as err:
        load_mission(path, has_home_item=True)
    assert needle in str(err.value)
    assert "\n" not in str(err.value)


def test_serve_refuses_a_bad_mission_file_before_it_starts(tmp_path: Path) -> None:
    bad = tmp_path / "bad.waypoints"
    bad.write_text("QGC WPL 110\n0\t1\n", encoding="utf-8")
    scenario = ROOT / "config" / "scenarios" / "smooth-hill.yaml"
    cmd = [
        sys.executable,
        "-m",
        "companion.sim",
        "serve",
        str(scenario),
        "--port",
        "0",
        "--mission",
    ]
    proc = subprocess.run(
        [*cmd, str(bad)], capture_output=True, text=True, timeout=120, check=False, cwd=ROOT
    )
    assert proc.returncode == 2
    assert "expected 12 columns" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.sim
@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_service_flies_a_mission_loaded_from_a_file(tmp_path: Path, personality: str) -> None:
    """The simulator starts with a waypoint file's mission; the service (route.source:
    mission) downloads it and flies to its last waypoint. Lockstep, so load does not matter."""
    path = ROOT / "config" / "scenarios" / "smooth-hill.yaml"
    scenario = load_scenario(path)

    async def fly() -> tuple[np.ndarray, np.ndarray, bool]:
        server = SimServer.from_scenario(
            scenario,
            path.parent,
            port=0,
            personality=personality,
            speedup=math.inf,
            lockstep={"enabled": True, "period_s": scenario.dt_s},
            prearm_delay_s=0.5,
        )
        home = np.array(server.autopilot.home_enu, dtype=float)
        targets = [home[:2] + np.array([25.0, 0.0]), home[:2] + np.array([40.0, 8.0])]
        rows = []
        for e, n in targets:
            g = server.frame.to_geodetic(float(e), float(n), 0.0)
            rows.append((g.lat_deg, g.lon_deg, 10.0))
        h = server.frame.to_geodetic(*(float(v) for v in home))
        mission = tmp_path / f"{personality}.waypoints"
        mission.write_text(_wpl(rows, (h.lat_deg, h.lon_deg, h.alt_m)), encoding="utf-8")
        server.mission.load(load_mission(mission, server.personality.has_home_mission_item))
        await server.start()
        cfg = service_config(scenario, server.port, home[:2], tmp_path / personality)
        doc = cfg.model_dump(mode="json")
        doc["route"] = {"source": "mission"}
        link = UdpOutLink("127.0.0.1", server.port)
        svc = Service(parse_config(doc), link, notifier=SystemdNotifier({}))
        task = asyncio.create_task(svc.run())
        try:
            t = 0.0
            while t < 120.0 and not svc.route_finished.is_set() and not task.done():
                t += 5.0
                await server.run_until(t)
        finally:
            svc.stop()
            await asyncio.wait_for(task, 30.0)
            await server.close()
        last = np.array(server.truth[-1].position_enu[:2])
        return last, np.array(targets[-1]), svc.route_finished.is_set()

    last, goal, finished = asyncio.run(fly())
    assert finished
    assert float(np.hypot(*(last - goal))) < 1.0
