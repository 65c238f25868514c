"""The service, the sensor bridge and the simulator's claims against the real ArduCopter SITL.

`make sitl-test` (pytest -m sitl). Every job gets its own SITL (own instance and ports),
started here and killed (process group) at teardown, and runs in its own worker process, all
side by side: the flights take their route length / v_d in wall time whatever SITL's
speed-up, since the service runs on the wall clock, so they are run at once rather than one
after the other. SITL runs at speed-up 1 (see docs/simulator.md, "Real SITL in the tests").
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.harness.sitl import (
    Px4Sitl,
    Sitl,
    SitlFlight,
    free_udp_port,
    sitl_params,
    start_heading_deg,
)
from tests.sitl_support import (
    COPTER_MODE,
    LAUNCHER,
    PX4_BUNDLE,
    PX4_FED,
    PX4_SKIP_REASON,
    SKIP_REASON,
    WIRED_PARAMS,
    PilotRun,
    SitlSpec,
    claims_job,
    flight_job,
    needs_sitl,
    next_instance,
    next_px4_instance,
    pilot_job,
    px4_claims_job,
    px4_flight_job,
    scenario_for,
)

pytestmark = [pytest.mark.sitl, needs_sitl, pytest.mark.timeout(900)]

# name -> (scenario, topology, wait until SITL can fly before starting the service)
FLIGHTS = {
    "paper": ("paper", "companion", True),
    "wall": ("wall", "companion", True),
    "pillars": ("pillars", "companion", True),
    "dead-end": ("dead-end", "companion", True),
    "wired-wall": ("wired-wall", "autopilot", True),
    "default-ekf": ("short", "companion", False),
}
SETTLED_HEIGHT_ERROR_M = 0.3
MAX_PARALLEL = 4
"""Jobs at once: each flight costs its worker ~15 % of a core and its SITL ~5 %."""


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """Every job's result (or the exception it raised). At most MAX_PARALLEL jobs at once,
    longest first; each job's SITL is started here when its turn comes and killed at the end."""
    if LAUNCHER is None:
        pytest.skip(SKIP_REASON)
    tmp = tmp_path_factory.mktemp("sitl")
    queue: list[tuple[str, Sitl | Px4Sitl, tuple[Any, ...]]] = []
    for name, (scenario, topology, ready) in FLIGHTS.items():
        sitl = Sitl(
            LAUNCHER,
            0,
            0,
            fast_ekf=name != "default-ekf",
            params=sitl_params(scenario_for(scenario), topology),  # type: ignore[arg-type]
            workdir=tmp / name / "sitl",
            heading_deg=start_heading_deg(scenario_for(scenario)),
        )
        queue.append((name, sitl, (flight_job, scenario, topology, str(tmp / name), ready)))
    queue.insert(
        4, ("pilot", Sitl(LAUNCHER, 0, 0, workdir=tmp / "pilot"), (pilot_job, str(tmp / "pilot")))
    )
    queue.insert(
        5,
        (
            "claims",
            Sitl(LAUNCHER, 0, 0, params=WIRED_PARAMS, workdir=tmp / "claims"),
            (claims_job,),
        ),
    )
    if PX4_BUNDLE is not None:  # PX4 with SIH physics: the paper's flight, second in line
        px4 = Px4Sitl(PX4_BUNDLE, workdir=tmp / "px4-paper")
        queue.insert(1, ("px4-paper", px4, (px4_flight_job, "paper", str(tmp / "px4-paper"))))
        claims = Px4Sitl(PX4_BUNDLE, workdir=tmp / "px4-claims")
        queue.append(("px4-claims", claims, (px4_claims_job,)))
    results: dict[str, Any] = {}
    started: list[Sitl | Px4Sitl] = []
    pool = multiprocessing.get_context("spawn").Pool(MAX_PARALLEL, maxtasksperchild=1)
    try:
        running: dict[str, Any] = {}
        while queue or running:
            while queue and len(running) < MAX_PARALLEL:
                name, sitl, (fn, *args) = queue.pop(0)
                if isinstance(sitl, Px4Sitl):
                    sitl.instance = next_px4_instance(
                        {s.instance for _, s in running.values() if isinstance(s, Px4Sitl)}
                    )
                else:
                    sitl.instance = next_instance()
                    sitl.port = free_udp_port()
                started.append(sitl)
                sitl.start()
                sitl.wait_heartbeat(60.0)
                spec: Any = (
                    sitl.detached()
                    if isinstance(sitl, Px4Sitl)
                    else SitlSpec(str(sitl.launcher), sitl.instance, sitl.port, 1.0, sitl.fast_ekf)
                )
                running[name] = (pool.apply_async(fn, (spec, *args)), sitl)
            time.sleep(0.5)
            for name, (res, sitl) in list(running.items()):
                if res.ready():
                    try:
                        results[name] = res.get()
                    except Exception as exc:  # reported by the test that reads it
                        results[name] = exc
                    sitl.stop()
                    del running[name]
        yield results
    finally:
        pool.terminate()
        pool.join()
        for sitl in started:
            with contextlib.suppress(Exception):
                sitl.stop()


def _get(runs: dict[str, Any], name: str) -> Any:
    value = runs[name]
    if isinstance(value, BaseException):
        raise AssertionError(f"{name}: the job failed: {value!r}") from value
    return value


def _figures(flight: SitlFlight) -> str:
    m = flight.metrics
    keys = (
        "goal_distance_m",
        "min_clearance_m",
        "max_height_error_m",
        "max_abs_phi_d_rad",
        "max_abs_pitch_rad",
        "duration_s",
    )
    return ", ".join(f"{k} {m.get(k, float('nan')):.3f}" for k in keys)


def assert_flight(flight: SitlFlight, height: bool = True, clearance: bool = True) -> None:
    """Goal reached, no collision, clearance >= D_min (with `clearance`), |H - H_d| <= 0.3 m
    once settled (with `height`), |phi_d| <= phi_max, all from the pose SITL reported,
    placed in the scenario's world."""
    m = flight.metrics
    assert m, "the service never took over"
    why = f"{flight.scenario.name}: {_figures(flight)}; events {flight.events}"
    assert flight.finished and m["reached_goal"], why
    assert m["collisions"] == 0, why
    assert not clearance or m["min_clearance_m"] >= flight.scenario.planner.d_min_m, why
    assert not height or m["max_height_error_m"] <= SETTLED_HEIGHT_ERROR_M, why
    assert m["max_abs_phi_d_rad"] <= flight.scenario.planner.phi_max_rad + 1e-9, why
    assert len(flight.track) > 100, "too few SITL positions to judge the flight"


WIRED_STOP = (
    "the planner's stop keeps a margin now (X_d rests v t short of the trigger: 2.49 m in a "
    "run with four flights side by side), but on a loaded machine the service can starve: "
    "position went stale for 1.1 s, the failsafe's STOP sent nothing then, and ArduCopter flew "
    "on its last position+velocity target 1.3 m past X_d (1.686 m; a STOP brakes since); "
    "another loaded run 0.925 m, cause not found"
)


@pytest.mark.parametrize("name", ["paper", "wall", "pillars", "dead-end"])
def test_flight_with_sensors_on_the_companion(runs: dict[str, Any], name: str) -> None:
    flight: SitlFlight = _get(runs, name)
    assert flight.topology == "companion"
    assert_flight(flight)


PX4_HEIGHT = (
    "PX4 with SIH physics moves 0.3-0.7 m vertically (its reported altitude) where the vehicle "
    "accelerates horizontally, with the setpoint's altitude constant: +0.36 m while reversing "
    "after a back-out over flat ground, -0.47 m at the stop at the goal (recovering at about "
    "0.1 m/s), in one flight; ArduCopter SITL flies the paper's route within 0.3 m"
)


@pytest.mark.skipif(PX4_BUNDLE is None, reason=PX4_SKIP_REASON)
def test_flight_on_px4(runs: dict[str, Any]) -> None:
    """The paper's scenario on PX4 with SIH physics: auto start (arm, AUTO.TAKEOFF, setpoints
    streamed, OFFBOARD), a turn to face the route (PX4 boots facing north, the route goes
    west), the route flown to the goal with D_min kept."""
    flight: SitlFlight = _get(runs, "px4-paper")
    m = flight.metrics
    print(f"px4-paper: {_figures(flight)}, on route {m.get('max_height_error_route_m')}")
    assert any("to face the route" in t for t in flight.statustexts), flight.statustexts
    assert_flight(flight, height=False, clearance=False)
    # D_min on PX4 is test_clearance_on_px4's (an expected failure at times, PX4_STOP).


PX4_STOP = (
    "PX4 with SIH physics runs past a stop before it comes back (0.6 m; 0.38 m with the "
    "acceleration fed forward), and the planner stops X_d D_min + margin/2 (0.3 m more) from "
    "the memory: a stop next to an obstacle can end inside D_min. Single flights kept "
    "3.04-3.40 m (sharp hill passed on the left); in a "
    "clean-clone run beside four ArduCopter flights the sharp hill was passed on the right "
    "after two stops and back-outs, at 1.96 m"
)


@pytest.mark.skipif(PX4_BUNDLE is None, reason=PX4_SKIP_REASON)
@pytest.mark.xfail(strict=False, reason=PX4_STOP)
def test_clearance_on_px4(runs: dict[str, Any]) -> None:
    flight: SitlFlight = _get(runs, "px4-paper")
    assert flight.metrics["min_clearance_m"] >= flight.scenario.planner.d_min_m, _figures(flight)


@pytest.mark.skipif(PX4_BUNDLE is None, reason=PX4_SKIP_REASON)
@pytest.mark.xfail(strict=False, reason=PX4_HEIGHT)
def test_height_on_px4(runs: dict[str, Any]) -> None:
    flight: SitlFlight = _get(runs, "px4-paper")
    assert flight.metrics["max_height_error_route_m"] <= SETTLED_HEIGHT_ERROR_M, _figures(flight)


@pytest.mark.skipif(PX4_BUNDLE is None, reason=PX4_SKIP_REASON)
def test_px4_keeps_one_mavlink_rangefinder_per_link(runs: dict[str, Any]) -> None:
    """Three rangefinders fed to PX4 over one MAVLink link come back on its onboard link as
    one sensor: one id (PX4's index after SIH's own downward sensor, id 0), carrying
    whichever reading came last, at about 10 Hz in all. Sensors for the companion must reach
    it directly on PX4 (docs/autopilots.md)."""
    got = _get(runs, "px4-claims")
    seen: dict[tuple[int, int], list[int]] = got["seen"]
    own = {k for k in seen if k[1] == 25}  # SIH's downward rangefinder
    assert {i for i, _ in own} == {0}, seen.keys()
    fed = {k: v for k, v in seen.items() if k[1] in PX4_FED}
    assert fed, f"no fed sensor came back: {seen.keys()}"
    assert len({i for i, _ in fed}) == 1 and 0 not in {i for i, _ in fed}, fed.keys()
    rate = sum(len(v) for v in fed.values()) / got["seconds"]
    assert 5.0 <= rate <= 15.0, rate  # three sensors fed at 10 Hz each: 10 Hz in all


def test_sensors_wired_to_the_autopilot_reach_the_planner(runs: dict[str, Any]) -> None:
    """Rangefinders and proximity fed to SITL; the companion reads SITL's re-reports only."""
    flight: SitlFlight = _get(runs, "wired-wall")
    assert flight.topology == "autopilot"
    c = flight.counters
    # every reading the planner got came from SITL (ids 0, 1 and 10+sector), none refused
    assert c.get("input.rejected_sensor_unknown_id", 0) == 0
    assert c.get("input.rejected_sensor_orientation_mismatch", 0) == 0
    assert c.get("input.rejected_sensor_orientation_unknown", 0) == 0
    assert flight.result is not None
    ranges = flight.result.trace["min_range"]
    assert np.any(ranges > 0.0), "no obstacle reading reached the planner"
    assert flight.metrics["collisions"] == 0


@pytest.mark.xfail(strict=False, reason=WIRED_STOP)
def test_flight_with_sensors_wired_to_the_autopilot(runs: dict[str, Any]) -> None:
    flight: SitlFlight = _get(runs, "wired-wall")
    print(f"wired-wall: {_figures(flight)}")  # pytest -rP shows it
    assert_flight(flight)


def test_default_ekf_boot_then_fly(runs: dict[str, Any]) -> None:
    """Default EKF3, service started as soon as SITL's heartbeat is seen: auto start must ride
    out the boot-time refusals of GUIDED and arming, then fly."""
    flight: SitlFlight = _get(runs, "default-ekf")
    assert_flight(flight)


def _setpoint_times(flight: SitlFlight) -> np.ndarray:
    return np.array([t for t, kind, _ in flight.sent if kind == "SET_POSITION_TARGET_GLOBAL_INT"])


def _first_heartbeat(flight: SitlFlight, after: float, mode: str) -> float:
    for t, custom_mode, _ in flight.heartbeats:
        if t >= after and custom_mode == COPTER_MODE[mode]:
            return t
    raise AssertionError(f"no {mode} heartbeat after the ground station's command")


def test_pilot_takes_over_and_gives_back(runs: dict[str, Any]) -> None:
    run: PilotRun = _get(runs, "pilot")
    flight = run.flight
    acts = {what: (t, result) for t, what, result in run.actions}
    assert acts["LOITER"][1] == mavlink.MAV_RESULT_ACCEPTED
    assert acts["GUIDED"][1] == mavlink.MAV_RESULT_ACCEPTED
    assert acts["RTL"][1] == mavlink.MAV_RESULT_ACCEPTED
    sp = _setpoint_times(flight)
    engaged = flight.engaged_at
    assert engaged is not None
    # the service never asks for a mode itself once it has taken over
    own_modes = [
        (t, kind, d)
        for t, kind, d in flight.sent
        if t > engaged
        and (kind == "SET_MODE" or (kind == "COMMAND_LONG" and d == mavlink.MAV_CMD_DO_SET_MODE))
    ]
    assert own_modes == []
    # LOITER: not one setpoint after the heartbeat that says so, until GUIDED again
    t_loiter = _first_heartbeat(flight, acts["LOITER"][0], "LOITER")
    t_guided = _first_heartbeat(flight, acts["GUIDED"][0], "GUIDED")
    assert not np.any((sp > t_loiter) & (sp < t_guided))
    assert np.any((sp > acts["LOITER"][0] - 2.0) & (sp < t_loiter)), "was not commanding"
    # back in GUIDED: it flies on (control.reengage, the default)
    assert run.engaged_again_at is not None
    assert np.any(sp > t_guided)
    # disarm in the air without force: refused, still armed, still commanding
    t_disarm, disarm_result = acts["disarm"]
    assert disarm_result == mavlink.MAV_RESULT_FAILED
    assert all(armed for t, _, armed in flight.heartbeats if t_disarm < t < acts["RTL"][0])
    assert np.any((sp > t_disarm) & (sp < acts["RTL"][0]))
    # RTL: stops at once and stays out
    t_rtl = _first_heartbeat(flight, acts["RTL"][0], "RTL")
    assert not np.any(sp > t_rtl)
    assert all(m != COPTER_MODE["GUIDED"] for t, m, _ in flight.heartbeats if t > t_rtl)


@pytest.fixture(scope="module")
def claims(runs: dict[str, Any]) -> dict[str, Any]:
    seen: dict[str, Any] = _get(runs, "claims")
    print("SITL claims:", seen)
    return seen


def test_heartbeat_and_unasked_streams(claims: dict[str, Any]) -> None:
    assert claims["heartbeat"] == (
        1,
        1,
        mavlink.MAV_TYPE_QUADROTOR,
        mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    )
    # nothing streamed before it is asked for (event messages may come: home, texts, and
    # ArduPilot's own TIMESYNC requests, seen every few seconds)
    assert set(claims["unasked_types"]) <= {
        "HEARTBEAT",
        "STATUSTEXT",
        "HOME_POSITION",
        "GPS_GLOBAL_ORIGIN",
        "TIMESYNC",
    }


def test_parameter_names(claims: dict[str, Any]) -> None:
    p = claims["params"]
    assert p["RNGFND1_MAX"] == pytest.approx(10.0)  # metres, set by us
    assert p["RNGFND1_MAX_CM"] is None  # the old name is gone
    assert p["PRX1_TYPE"] == pytest.approx(2.0)
    assert p["PRX_TYPE"] is None
    assert p["GUID_TIMEOUT"] == pytest.approx(3.0)  # sim's guided_timeout_s
    assert p["DISARM_DELAY"] == pytest.approx(10.0)
    assert p["RTL_ALT"] == pytest.approx(1500.0)  # cm: sim's rtl_altitude_m 15


def test_message_interval_answers(claims: dict[str, Any]) -> None:
    acks = claims["set_interval_acks"]
    for name in ("DISTANCE_SENSOR", "HOME_POSITION", "GLOBAL_POSITION_INT"):
        assert acks[name] == mavlink.MAV_RESULT_ACCEPTED
    assert acks["unknown id 60000"] == mavlink.MAV_RESULT_DENIED
    # GET_MESSAGE_INTERVAL: MESSAGE_INTERVAL first, then the ACK
    kinds = [k for k, _ in claims["get_interval"]]
    assert kinds[:2] == ["MESSAGE_INTERVAL", "COMMAND_ACK"]
    assert claims["get_interval"][0][1] == 50_000
    # REQUEST_MESSAGE: the ACK, then the message
    assert claims["request_home"] == ["COMMAND_ACK", "HOME_POSITION"]


def test_distance_sensor_re_reports(claims: dict[str, Any]) -> None:
    s = claims["sensors"]
    # rangefinders: id = instance - 1, orientation = RNGFNDn_ORIENT, limits from parameters
    assert s[0]["orientation"] == {39} and s[1]["orientation"] == {25}
    assert s[0]["min"] == {20} and s[0]["max"] == {1000}
    assert set(s[0]["current"]) == {500}
    # "nothing in range" from a MAVLink rangefinder is passed on as sent (max + 1 m)
    assert set(s[1]["current"]) == {1100}
    # proximity: id 10 + sector, the message's max, min 0.2 m as 19 cm
    assert s[10]["orientation"] == {0} and s[16]["orientation"] == {6}
    assert s[10]["max"] == {1200} and s[10]["min"] == {19}
    assert set(s[10]["current"]) == {800} and set(s[16]["current"]) == {400}
    # a sector that has never seen anything in range is not reported at all
    assert 12 not in s
    for row in s.values():
        assert row["quaternion"] == [0.0, 0.0, 0.0, 0.0]
        assert row["covariance"] == 0 and row["signal_quality"] == 0
        assert row["rate_hz"] > 5.0  # 20 Hz asked; generous for a loaded machine
    after = claims["sensors_after"]
    # a sector that lost its object reports its max; a silent rangefinder stops being sent
    assert set(after[16]["current"]) == {1200}
    assert 0 not in after
    assert set(after[1]["current"]) == {1100}


def test_guided_targets(claims: dict[str, Any]) -> None:
    assert claims["guided"] == mavlink.MAV_RESULT_ACCEPTED
    assert claims["arm"] == mavlink.MAV_RESULT_ACCEPTED
    assert claims["takeoff"] == mavlink.MAV_RESULT_ACCEPTED
    f6 = claims["frame6"]  # frame 6: altitude above home
    assert f6["relative_alt_m"] == pytest.approx(12.0, abs=0.5)
    assert f6["alt_above_home_m"] == pytest.approx(12.0, abs=0.5)
    assert f6["north_m"] == pytest.approx(10.0, abs=1.0)
    # LOITER while flying to a target 40 m north, then GUIDED again: the old target is gone,
    # the vehicle holds where it is (as companion/sim/ does: GUIDED starts at the stopping point)
    re = claims["reenter"]
    assert claims["loiter"] == claims["guided_again"] == mavlink.MAV_RESULT_ACCEPTED
    assert abs(re["north_after_8s_m"] - re["north_at_loiter_m"]) < 3.0
    # a target in a frame it does not take (LOCAL_NED here) stops the vehicle short of the
    # 45 m target it was flying to (GUIDED re-initialised at its stopping point)
    bad = claims["bad_frame"]
    assert bad["north_after_8s_m"] < 40.0
    # disarming in the air without the force value is refused
    assert claims["disarm_in_air"] == mavlink.MAV_RESULT_FAILED


def test_sitl_fixture_kills_sitl(tmp_path: Path) -> None:
    """The SITL fixture's process group is gone after stop()."""
    from tests.sitl_support import running_sitl

    with running_sitl(tmp_path) as sitl:
        assert sitl.proc is not None and sitl.proc.poll() is None
        pid = sitl.proc.pid
    assert sitl.proc.poll() is not None
    with pytest.raises(ProcessLookupError):
        os.killpg(pid, 0)
