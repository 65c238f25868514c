"""The shipped service configs fly against the bundled simulator as their headers say:

    python -m companion.sim serve config/scenarios/smooth-hill.yaml [--personality px4] \
        --target 127.0.0.1:14540
    companion run --config config/sitl-copter.yaml   (or config/px4-sitl.yaml)

with two changes that keep the test independent of the machine's load: the port is a free one
passed as `--connection` would (nothing collides with 14540), and the service runs on the
simulator's lockstep clock (`control.time_source: sim`) instead of the monotonic one, so a
loaded machine slows the flight down instead of starving it (a real-time flight of both
configs needs about a third of a core; on a loaded 2-core CI machine it timed out).
"""

from __future__ import annotations

import asyncio
import math
import re
import socket
from pathlib import Path

import numpy as np
import pytest

from companion.config import check_config, load_config
from companion.service import Service, open_link
from companion.service.notify import SystemdNotifier
from companion.sim.mavlink import SimServer
from companion.sim.scenario import load_scenario

pytestmark = [pytest.mark.sim, pytest.mark.slow, pytest.mark.timeout(240)]

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {"sitl-copter.yaml": "ardupilot", "px4-sitl.yaml": "px4"}
SIM_BUDGET_S = 150.0
"""Simulated seconds a flight may take (at idle both finish in about 45)."""


def _header_pairing(text: str) -> tuple[str, str]:
    """The scenario and personality the config's header pairs it with."""
    m = re.search(
        r"python -m companion.sim serve (\S+)((?: --personality \w+)?) --target 127.0.0.1:14540",
        text,
    )
    assert m is not None, "the config's header documents the simulator pairing"
    return m.group(1), (m.group(2).split()[-1] if m.group(2) else "ardupilot")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _fly(config: Path) -> tuple[Service, SimServer, list[float]]:
    scenario_path, personality = _header_pairing(config.read_text(encoding="utf-8"))
    assert personality == CONFIGS[config.name]
    scenario = load_scenario(ROOT / scenario_path)
    port = _free_udp_port()
    cfg = load_config(config, connection=f"udpin:127.0.0.1:{port}")
    cfg = cfg.model_copy(
        update={
            "logging": cfg.logging.model_copy(update={"flight_log_dir": None}),
            "control": cfg.control.model_copy(update={"time_source": "sim"}),
        }
    )
    server = SimServer.from_scenario(
        scenario,
        (ROOT / scenario_path).parent,
        port=0,
        personality=personality,
        target=f"127.0.0.1:{port}",
        speedup=math.inf,
        lockstep={"enabled": True, "period_s": 1.0 / cfg.control.rate_hz},
    )
    service = Service(cfg, open_link(cfg.link.spec), notifier=SystemdNotifier({}))
    await server.start()
    task = asyncio.create_task(service.run())
    try:
        t = 0.0
        while t < SIM_BUDGET_S and not service.route_finished.is_set() and not task.done():
            t += 5.0
            await server.run_until(t)
    finally:
        service.stop()
        await asyncio.wait_for(task, 30.0)
        await server.close()
    home = np.array(server.autopilot.home_enu[:2])
    goal = home + np.array(cfg.route.points[-1] if cfg.route.points else [0.0, 0.0])
    last = np.array(server.truth[-1].position_enu[:2])
    return service, server, [float(np.hypot(*(last - goal)))]


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_shipped_config_is_valid(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert check_config(ROOT / "config" / name) == 0
    assert "link udpin:127.0.0.1:14540" in capsys.readouterr().out


def test_shipped_configs_fly_against_the_bundled_simulator() -> None:
    """Both configs at once (each against its own simulator), to the end of their route."""

    async def both() -> list[tuple[Service, SimServer, list[float]]]:
        return await asyncio.gather(*(_fly(ROOT / "config" / n) for n in sorted(CONFIGS)))

    for service, server, (to_goal,) in asyncio.run(both()):
        assert service.route_finished.is_set()
        assert service.counters["planner_starts"] >= 1
        assert to_goal < 2.0, to_goal
        assert server.stats.received > 0


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "config").glob("*.yaml")))
def test_flight_logs_of_shipped_configs_are_not_tracked(name: str) -> None:
    """Running a shipped config leaves the working tree clean: its flight-log directory is
    ignored by git."""
    import shutil
    import subprocess

    git = shutil.which("git")
    if git is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    log_dir = load_config(ROOT / "config" / name).logging.flight_log_dir
    if log_dir is None:
        return
    probe = Path(log_dir) / "flight-probe.jsonl"
    proc = subprocess.run(
        [git, "-C", str(ROOT), "check-ignore", "-q", str(probe)], check=False, timeout=60
    )
    assert proc.returncode == 0, f"{probe} would be an untracked file"
