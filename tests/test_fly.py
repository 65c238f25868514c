"""`companion fly`: the paper scenario through the service and the MAVLink simulator over UDP
loopback (lockstep) meets the same outcome as in process."""

import asyncio
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from companion.harness.fly import fly_async
from companion.sim.scenario import load_scenario

pytestmark = [pytest.mark.sim, pytest.mark.slow, pytest.mark.timeout(180)]

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_paper_through_the_service(autopilot: str, tmp_path: Path) -> None:
    scenario = load_scenario(SCENARIOS / "paper.yaml")
    flown = asyncio.run(fly_async(scenario, SCENARIOS, tmp_path, autopilot))
    m, e = flown.metrics, scenario.expect
    assert flown.lockstep_stalls == 0
    assert m["reached_goal"]
    assert m["collisions"] == 0
    assert m["min_clearance_m"] >= scenario.planner.d_min_m
    assert m["max_abs_phi_d_rad"] <= scenario.planner.phi_max_rad + 1e-9
    assert m["max_height_error_m"] <= 0.15
    assert m["max_speed_error_mps"] <= 0.02
    assert m["final_heading_error_rad"] <= math.radians(1.0)
    assert m["passed_side"]["sharp hill"] == "left"
    assert m["max_lateral_deviation_m"]["smooth hill"] < e.max_lateral_deviation_over_m
    assert flown.log_path is not None and flown.log_path.stat().st_size > 0


def test_report_turns_the_flight_log_into_the_same_plots(tmp_path: Path) -> None:
    from companion.harness.fly import report

    scenario = load_scenario(SCENARIOS / "smooth-hill.yaml")
    flown = asyncio.run(fly_async(scenario, SCENARIOS, tmp_path / "fly", "ardupilot"))
    assert flown.log_path is not None
    out = io.StringIO()
    code = report(flown.log_path, tmp_path / "rep", SCENARIOS / "smooth-hill.yaml", stream=out)
    assert code == 0
    for name in ("fig6.png", "fig7.png"):
        assert (tmp_path / "rep" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "reached goal" in out.getvalue() and "planner cycles" in out.getvalue()
    # Without the scenario (a real flight): plots, no metrics that need the true surface.
    out = io.StringIO()
    assert report(flown.log_path, tmp_path / "rep2", stream=out) == 0
    assert "reached goal" not in out.getvalue()
    assert (tmp_path / "rep2" / "fig7.png").exists()
    # The planner parameters come from the log's header, not from defaults.
    lines = flown.log_path.read_text(encoding="utf-8").splitlines()
    header = json.loads(lines[0])
    assert header["type"] == "header"
    header["planner"] = {**header["planner"], "h_d_m": 3.5, "d_min_m": 2.75}
    edited = tmp_path / "edited.jsonl"
    edited.write_text("\n".join([json.dumps(header), *lines[1:]]) + "\n", encoding="utf-8")
    out = io.StringIO()
    assert report(edited, tmp_path / "rep3", plots=False, stream=out) == 0
    assert "H_d 3.5 m, D_min 2.75 m" in out.getvalue() and "(from the log)" in out.getvalue()
    assert not (tmp_path / "rep3" / "fig6.png").exists()


def test_seabed_through_the_service_with_ardusub(tmp_path: Path) -> None:
    """Underwater: the ArduSub personality (no take-off, the pilot arms and hands over in
    GUIDED at depth), the ROV follows the seabed at H_d and goes round the wreck."""
    scenario = load_scenario(SCENARIOS / "seabed.yaml")
    assert (scenario.mavlink or {}).get("personality") == "ardusub"
    flown = asyncio.run(fly_async(scenario, SCENARIOS, tmp_path, None))
    m = flown.metrics
    assert flown.lockstep_stalls == 0
    assert m["reached_goal"] and m["collisions"] == 0
    assert m["min_clearance_m"] >= scenario.planner.d_min_m
    assert m["max_height_error_m"] <= 0.15
    assert m["passed_side"]["wreck"] == "right"
    assert flown.counters.get("service.auto_start_failed", 0) == 0
    z = flown.result.trace["z"]
    assert np.all(z < -20.0)  # submerged all the way: never surfaced, never "took off"
    assert any(text == "flying route" for _, text in flown.result.events)
