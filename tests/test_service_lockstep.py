"""Lockstep with the simulator: the same scenario flown twice through the service gives the
same trace, bit for bit. Auto start acts on the service clock, which the simulator's ticks
set, and each tick is answered only after what it woke has acted, so nothing depends on how
fast the machine runs the two processes' halves."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from companion.harness.fly import fly_async
from companion.sim.scenario import load_scenario

pytestmark = [pytest.mark.sim, pytest.mark.slow, pytest.mark.timeout(240)]

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"


def test_the_same_flight_twice_gives_the_same_trace(tmp_path: Path) -> None:
    # take-off, hand-over and the first seconds of the route: where auto start's commands
    # meet the ticks
    scenario = load_scenario(SCENARIOS / "paper.yaml").model_copy(update={"duration_s": 14.0})
    traces = []
    for run in ("a", "b"):
        flown = asyncio.run(fly_async(scenario, SCENARIOS, tmp_path / run))
        assert flown.lockstep_stalls == 0
        traces.append(flown.result.trace)
    a, b = traces
    assert len(a["t"]) > 50  # the planner flew
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
