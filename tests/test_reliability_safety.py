"""Safety defects found by attacking the running service (issue "safety"), one test each.

Each test drives the service over UDP on 127.0.0.1 against the scripted fake autopilot of
`tests/service_fakes.py` (or checks the config path), and fails on the behaviour found by
the attack: a crash at take-over, a fight with the pilot's mode change, an obstacle below the
minimum range taken for free space, a stranger followed, a forged timestamp stopping the
vehicle, an unlimited position jump re-basing the plan, a take-off with no sensor or no route.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from companion.config import ConfigError, ServiceConfig, check_config, parse_config
from companion.service import Service
from companion.service.codec import MavCodec, mavlink2
from companion.service.identity import Health
from companion.service.link import UdpInLink, UdpOutLink
from companion.service.notify import SystemdNotifier
from tests.service_fakes import HOME, SENSORS, FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(40)

M = mavlink2
GUIDED = 4
LOITER = 5
RTL = 6


async def until(pred: Any, timeout: float = 8.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pred():
        if loop.time() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def over_udp(
    cfg: ServiceConfig | None = None, factory: Any = None, **ap_kwargs: Any
) -> AsyncIterator[tuple[Service, FakeAutopilot, asyncio.Task[int]]]:
    """The service on a UDP port and the fake autopilot sending to it; yields the run task."""
    link = UdpInLink("127.0.0.1", 0)
    svc = Service(
        cfg or make_config(),
        link,
        planner_factory=factory or PlannerBox(),
        notifier=SystemdNotifier({}),
    )
    task = asyncio.create_task(svc.run())
    await until(lambda: link._transport is not None)
    host, port = link.local_address
    ap = FakeAutopilot(UdpOutLink(host, port), **ap_kwargs)
    await ap.start()
    try:
        yield svc, ap, task
    finally:
        svc.stop()
        rc = await asyncio.wait_for(task, 10)
        await ap.stop()
        assert rc == 0, "the service ended with an error"


def pilot_texts(ap: FakeAutopilot) -> list[str]:
    return [r.msg.text for r in ap.of_type("STATUSTEXT")]


# === 1. nothing that can fail at take-over ends the process =================================


def test_check_config_refuses_equal_consecutive_points(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    data = {"route": {"source": "config", "points": [[30, 0], [30, 0], [30, 30]]}}
    path.write_text(yaml.safe_dump({**data, "sensors": SENSORS}))
    out = io.StringIO()
    assert check_config(path, out) == 2
    assert "base points 0 and 1 are 0.00 m apart" in out.getvalue()


def test_check_config_builds_the_planner_it_will_fly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """check-config builds the route and planner a take-over builds: what they refuse, it
    refuses (here a planner that cannot be built from the tuning)."""
    import companion.planner as planner_pkg

    class Refusing:
        def __init__(self, *a: Any) -> None:
            raise ValueError("v_d_mps too high for this sensor table")

    monkeypatch.setattr(planner_pkg, "Planner", Refusing)
    path = tmp_path / "c.yaml"
    path.write_text(
        yaml.safe_dump({"route": {"source": "config", "points": [[30, 0]]}, "sensors": SENSORS})
    )
    out = io.StringIO()
    assert check_config(path, out) == 2
    assert "cannot be built at take-over: v_d_mps too high" in out.getvalue()


async def test_take_over_failure_holds_and_says_why(caplog: pytest.LogCaptureFixture) -> None:
    """A route the planner refuses at take-over (as `Route` refused equal points): the service
    keeps running, holds where the vehicle is (hold setpoints, CRITICAL) and says why."""

    def refusing(*a: Any) -> Any:
        raise ValueError("consecutive base points must differ")

    async with over_udp(factory=refusing) as (svc, ap, task):
        await until(lambda: svc.configured)
        ap.set_mode(GUIDED)
        await until(lambda: svc.counters["route_build_failed"] >= 1)
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= n + 10)
        assert not task.done()
        assert svc.health is Health.CRITICAL
        east = [r.msg.lon_int for r in ap.setpoints()[n:]]
        assert max(east) - min(east) <= 1  # a hold: the same point every time
        assert any("cannot fly route" in t for t in pilot_texts(ap))
        assert "consecutive base points must differ" in caplog.text


# === 5. routes bounded; planner construction off the event loop =============================


@pytest.mark.parametrize(
    ("route", "expected"),
    [
        ({"points": [[1e9, 0.0]]}, "km from home"),
        ({"points": [[float(i), 0.0] for i in range(1, 1502)]}, "longer than 1000"),
        ({"points": [[10.0, 0.0], [10.2, 0.0]]}, "0.20 m apart"),
        ({"points_latlon": [[47.0, 8.0], [48.0, 8.0]]}, "km from the first point"),
    ],
    ids=["far", "too_many", "too_close", "latlon_far"],
)
def test_route_bounds(route: dict[str, Any], expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({"route": {"source": "config", **route}, "sensors": SENSORS})
    assert expected in str(err.value)


async def test_planner_built_off_the_event_loop() -> None:
    """A slow planner construction (a long route) does not stop heartbeats or setpoints."""
    import threading
    import time

    made = threading.Event()

    def slow(*a: Any) -> Any:
        time.sleep(1.5)
        made.set()
        return PlannerBox()(*a)

    async with over_udp(factory=slow) as (svc, ap, _):
        await until(lambda: svc.configured)
        ap.set_mode(GUIDED)
        await until(lambda: svc.ownership.engaged)
        t0 = asyncio.get_running_loop().time()
        n_hb = len(ap.of_type("HEARTBEAT"))
        n_sp = len(ap.setpoints())
        await until(made.is_set)
        waited = asyncio.get_running_loop().time() - t0
        assert waited > 1.0
        # heartbeats (1 Hz) and hold setpoints went on while the planner was being built
        assert len(ap.of_type("HEARTBEAT")) >= n_hb + 1
        assert len(ap.setpoints()) >= n_sp + 5


# === 3. an obstacle closer than the minimum range is not free space ========================


@pytest.mark.parametrize(
    ("cm", "limits", "expect"),
    [
        (250, (300, 1000), "refused"),  # (a) the message claims a 3 m minimum
        (5, (10, 1000), "at_min"),  # (b) closer than the configured 0.1 m minimum
        (150, (1, 2), "refused"),  # (c) message limits 1-2 cm
    ],
    ids=["msg_min_300cm", "below_configured_min", "msg_limits_1_2cm"],
)
async def test_close_obstacle_never_free_space(cm: int, limits: tuple[int, int], expect: str) -> None:
    box = PlannerBox()
    async with over_udp(factory=box, ranges_cm={0: 800, 1: 700, 2: 700}) as (svc, ap, task):
        await until(lambda: svc.configured)
        ap.set_mode(GUIDED)
        await until(lambda: bool(box.made) and len(box.made[-1].inputs) >= 5)
        ap.ranges_cm[0] = cm
        ap.limits_cm[0] = limits
        await asyncio.sleep(1.5)
        planner = box.made[-1]
        n_before = len(planner.inputs)
        await asyncio.sleep(1.0)
        front = [float(r[0]) for _, r, _ in planner.inputs[-10:]]
        assert 0.0 not in front, front  # never "nothing detected"
        if expect == "at_min":
            assert front[-1] == pytest.approx(0.1)  # an obstacle at the minimum range
        else:
            # refused: the sensor is stale, the planner is not stepped, the vehicle holds
            assert len(planner.inputs) == n_before
            assert svc.last_verdict.verdict.value == "hold"
            assert any(t.startswith("sensor 0 refused") for t in pilot_texts(ap))
            assert svc.counter_values()["input.rejected_sensor_limits"] > 0
