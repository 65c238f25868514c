"""The planner's tunables as MAVLink parameters (`companion.service.params`).

Two halves: a ground station (pymavlink's mavutil, as MAVProxy uses it) talking to the whole
service over UDP on 127.0.0.1 (list, read by id and by index, set accepted and refused); and
the control cycle on a manual clock with the real planner, where a PARAM_SET must reach the
planner at the next cycle (eq. (7)'s side threshold following H_d, v_d / D_min / phi_max in
the planner's params). No test waits on the wall clock for anything but a reply, with a
generous bound.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil

from companion.config import load_config
from companion.planner.types import PathMode, StepResult
from companion.service import Service
from companion.service.codec import mavlink2
from companion.service.flightlog import FlightLogWriter
from companion.service.host import default_planner_factory, height_only
from companion.service.link import UdpInLink
from companion.service.notify import SystemdNotifier
from companion.service.params import (
    MAV_PARAM_TYPE_REAL32,
    PARAM_ID_LEN,
    PARAM_PREFIX,
    PARAMS,
    ParamServer,
    from_real32,
    param_table_markdown,
    persist_to,
    write_planner_values,
)
from companion.tuning import PlannerConfig
from tests.service_fakes import SENSORS, FakePlanner, make_config
from tests.test_service_cycle import GUIDED, Rig, rig

pytestmark = pytest.mark.timeout(60)

REPLY_S = 10.0
"""Bound on one reply over loopback (a loaded machine is slow, never this slow)."""
OUR_SYSID, OUR_COMPID = 7, 191
INDEX = {p.param_id: i for i, p in enumerate(PARAMS)}


# --- the table -----------------------------------------------------------------------------


def test_the_table_names_planner_keys_with_short_prefixed_unique_ids() -> None:
    ids = [p.param_id for p in PARAMS]
    assert len(set(ids)) == len(ids)
    assert all(i.startswith(PARAM_PREFIX) and len(i) <= PARAM_ID_LEN for i in ids)
    assert {"h_d_m", "v_d_mps", "d_min_m", "phi_max_rad"} <= {p.key for p in PARAMS}
    fields = PlannerConfig.model_fields
    assert all(fields[p.key].annotation is float for p in PARAMS)  # REAL32 can carry them


def test_real32_values_read_as_the_decimal_the_station_meant() -> None:
    sent = float(np.float32(0.1))
    assert sent != 0.1 and from_real32(sent) == 0.1
    assert from_real32(float(np.float32(2.75))) == 2.75
    assert math.isnan(from_real32(math.nan))


# --- a ground station over UDP -------------------------------------------------------------


class Station:
    """A ground station on mavutil (system 255, component 190), blocking calls in a thread."""

    def __init__(self, port: int) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=255, source_component=190, dialect=None
        )

    async def send(self, msg: Any) -> None:
        await asyncio.to_thread(self.conn.mav.send, msg)

    async def values(self, n: int, timeout: float = REPLY_S) -> list[Any]:
        """The next n PARAM_VALUEs (TimeoutError when they do not all come)."""

        def collect() -> list[Any]:
            out: list[Any] = []
            while len(out) < n:
                m = self.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=timeout)
                if m is None:
                    raise TimeoutError(f"{len(out)} of {n} PARAM_VALUEs")
                out.append(m)
            return out

        return await asyncio.to_thread(collect)

    async def texts(self, timeout: float = REPLY_S) -> str:
        def one() -> str:
            m = self.conn.recv_match(type="STATUSTEXT", blocking=True, timeout=timeout)
            if m is None:
                raise TimeoutError("no STATUSTEXT")
            return str(m.text)

        return await asyncio.to_thread(one)

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
async def station() -> AsyncIterator[tuple[Service, Station]]:
    cfg = make_config(identity={"system_id": OUR_SYSID, "component_id": OUR_COMPID})
    link = UdpInLink("127.0.0.1", 0)
    svc = Service(cfg, link, planner_factory=default_planner_factory, notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    for _ in range(500):
        if link.is_open:
            break
        await asyncio.sleep(0.01)
    gcs = Station(link.local_address[1])
    try:
        yield svc, gcs
    finally:
        gcs.close()
        svc.stop()
        await asyncio.wait_for(task, 20)


def read(param_id: bytes, index: int = -1) -> Any:
    return mavlink2.MAVLink_param_request_read_message(OUR_SYSID, OUR_COMPID, param_id, index)


def _id(m: Any) -> str:
    return str(m.param_id)


async def test_list_answers_every_parameter_with_count_and_index(
    station: tuple[Service, Station],
) -> None:
    svc, gcs = station
    await gcs.send(mavlink2.MAVLink_param_request_list_message(OUR_SYSID, OUR_COMPID))
    got = await gcs.values(len(PARAMS))
    assert [_id(m) for m in got] == [p.param_id for p in PARAMS]
    assert [m.param_index for m in got] == list(range(len(PARAMS)))
    assert {m.param_count for m in got} == {len(PARAMS)}
    assert {m.param_type for m in got} == {MAV_PARAM_TYPE_REAL32}
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in got} == {(OUR_SYSID, OUR_COMPID)}
    planner = svc.cfg.planner
    for m, p in zip(got, PARAMS, strict=True):
        assert m.param_value == pytest.approx(getattr(planner, p.key), rel=1e-6)
    # the broadcast ids (QGroundControl asks MAV_COMP_ID_ALL) are answered too
    await gcs.send(mavlink2.MAVLink_param_request_list_message(0, 0))
    assert len(await gcs.values(len(PARAMS))) == len(PARAMS)


async def test_read_by_id_and_by_index(station: tuple[Service, Station]) -> None:
    _, gcs = station
    await gcs.send(
        mavlink2.MAVLink_param_request_read_message(OUR_SYSID, OUR_COMPID, b"TFC_D_MIN", -1)
    )
    (m,) = await gcs.values(1)
    assert _id(m) == "TFC_D_MIN" and m.param_index == INDEX["TFC_D_MIN"]
    assert m.param_value == pytest.approx(2.0)
    i = INDEX["TFC_PHI_MAX"]
    await gcs.send(mavlink2.MAVLink_param_request_read_message(OUR_SYSID, OUR_COMPID, b"", i))
    (m,) = await gcs.values(1)
    assert _id(m) == "TFC_PHI_MAX" and m.param_index == i
    assert m.param_value == pytest.approx(0.6, rel=1e-6)


async def test_set_accepted_answers_the_new_value_and_the_host_has_it(
    station: tuple[Service, Station],
) -> None:
    svc, gcs = station
    await gcs.send(
        mavlink2.MAVLink_param_set_message(
            OUR_SYSID, OUR_COMPID, b"TFC_H_D", 3.5, MAV_PARAM_TYPE_REAL32
        )
    )
    (m,) = await gcs.values(1)
    assert _id(m) == "TFC_H_D" and m.param_value == 3.5 and m.param_index == INDEX["TFC_H_D"]
    assert svc.host.h_d_m == 3.5 and svc.status().h_d_m == 3.5
    await gcs.send(
        mavlink2.MAVLink_param_set_message(
            OUR_SYSID, OUR_COMPID, b"TFC_V_D", float(np.float32(0.1)), MAV_PARAM_TYPE_REAL32
        )
    )
    (m,) = await gcs.values(1)
    assert svc.host.params.v_d_mps == 0.1  # the decimal meant, not float32's 0.10000000149
    assert m.param_value == pytest.approx(0.1, rel=1e-7)
    await gcs.send(
        mavlink2.MAVLink_param_request_read_message(OUR_SYSID, OUR_COMPID, b"TFC_H_D", -1)
    )
    (m,) = await gcs.values(1)
    assert m.param_value == 3.5


@pytest.mark.parametrize(
    ("param_id", "value", "why"),
    [
        (b"TFC_H_D", -1.0, "planner.h_d_m: expected a number greater than 0"),
        (b"TFC_H_D", math.nan, "planner.h_d_m: expected a finite number"),
        (b"TFC_V_D", 25.0, "planner.v_d_mps: expected a number less than or equal to 20"),
        (b"TFC_PHI_MAX", 1.6, "planner.phi_max_rad: expected a number less than 1.57"),
        (b"TFC_REACT_T", math.inf, "planner.reaction_time_s"),
    ],
)
async def test_set_refused_answers_the_old_value_and_says_why(
    station: tuple[Service, Station], param_id: bytes, value: float, why: str
) -> None:
    svc, gcs = station
    before = svc.host.tuning
    await gcs.send(
        mavlink2.MAVLink_param_set_message(
            OUR_SYSID, OUR_COMPID, param_id, value, MAV_PARAM_TYPE_REAL32
        )
    )
    (m,) = await gcs.values(1)
    key = PARAMS[INDEX[param_id.decode()]].key
    assert m.param_value == pytest.approx(getattr(before, key), rel=1e-6)
    assert svc.host.tuning == before
    text = await gcs.texts()
    assert text.startswith(param_id.decode()) and "refused" in text
    assert svc.params.counters["refused"] == 1


async def test_set_of_another_type_is_refused(station: tuple[Service, Station]) -> None:
    svc, gcs = station
    await gcs.send(
        mavlink2.MAVLink_param_set_message(
            OUR_SYSID, OUR_COMPID, b"TFC_H_D", 3.0, mavlink2.MAV_PARAM_TYPE_INT32
        )
    )
    (m,) = await gcs.values(1)
    assert m.param_value == 2.0 and svc.host.h_d_m == 2.0
    assert "not REAL32" in await gcs.texts()


async def test_unknown_ids_and_other_components_get_no_value(
    station: tuple[Service, Station],
) -> None:
    svc, gcs = station
    said: list[str] = []
    say = svc.params.say
    svc.params.say = lambda text, sev: (said.append(text), say(text, sev))[-1]
    await gcs.send(
        mavlink2.MAVLink_param_set_message(
            OUR_SYSID, OUR_COMPID, b"TFC_NOPE", 1.0, MAV_PARAM_TYPE_REAL32
        )
    )
    assert "no such parameter" in await gcs.texts()
    # requests for the autopilot (component 1) or another system are not ours to answer
    await gcs.send(mavlink2.MAVLink_param_request_list_message(OUR_SYSID, 1))
    await gcs.send(mavlink2.MAVLink_param_request_list_message(OUR_SYSID + 1, OUR_COMPID))
    await gcs.send(
        mavlink2.MAVLink_param_set_message(OUR_SYSID, 1, b"TFC_H_D", 4.0, MAV_PARAM_TYPE_REAL32)
    )
    # an id we do not have, asked of every component, is another's: no word about it
    await gcs.send(
        mavlink2.MAVLink_param_set_message(
            OUR_SYSID, 0, b"RNGFND1_TYPE", 10.0, MAV_PARAM_TYPE_REAL32
        )
    )
    await gcs.send(mavlink2.MAVLink_param_request_read_message(OUR_SYSID, 0, b"RNGFND1_TYPE", -1))
    # then one request that is ours: the first PARAM_VALUE must be its answer
    await gcs.send(mavlink2.MAVLink_param_request_read_message(OUR_SYSID, OUR_COMPID, b"", 0))
    (m,) = await gcs.values(1)
    assert m.param_index == 0 and svc.host.h_d_m == 2.0
    assert svc.params.counters == {"requests": 4, "set": 0, "refused": 0, "unknown": 1}
    assert said == ["cannot set 'TFC_NOPE': no such parameter"]  # nothing about RNGFND1_TYPE


# --- the planner sees it at the next cycle (manual clock, the real planner) -------------------

SIDE_SENSORS = [
    *SENSORS,
    {"id": 3, "name": "left", "role": "obstacle", "group": "L", "orientation": "YAW_270"},
    {"id": 4, "name": "right", "role": "obstacle", "group": "R", "orientation": "YAW_90"},
]


class Ids:
    system_id, component_id = OUR_SYSID, OUR_COMPID


@dataclass
class Desk:
    """A parameter server on the cycle rig's host; what it sends and says."""

    r: Rig
    server: ParamServer = field(init=False)
    sent: list[Any] = field(default_factory=list)
    said: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.server = ParamServer(
            self.r.host, Ids(), self.sent.append, lambda t, s: self.said.append(t)
        )

    def set(self, param_id: str, value: float) -> Any:
        """PARAM_SET; the one PARAM_VALUE it is answered with."""
        n = len(self.sent)
        self.server.handle(
            mavlink2.MAVLink_param_set_message(
                OUR_SYSID, OUR_COMPID, param_id.encode(), value, MAV_PARAM_TYPE_REAL32
            )
        )
        (reply,) = self.sent[n:]
        return reply


@pytest.fixture
def flying() -> Desk:
    r = rig(sensors=SIDE_SENSORS)
    r.ap.ranges_cm = {0: 0, 1: 700, 2: 700, 3: 0, 4: 0}
    r.ap.orientations = {**r.ap.orientations, 3: (6, [0, 0, 0, 0]), 4: (2, [0, 0, 0, 0])}
    r.host.planner_factory = default_planner_factory
    r.ap.custom_mode = GUIDED
    r.run(0.5)
    assert r.cycle.last_kind == "planner" and r.host.last_result is not None
    return Desk(r)


def _side_threshold(result: StepResult) -> float:
    th = result.diagnostics.threshold_rad  # table order of the obstacle sensors: F, L, R
    assert th[1] == th[2]
    return float(th[1])


def test_h_d_within_phi_max_goes_to_the_running_planner(
    flying: Desk,
) -> None:
    r, desk = flying.r, flying
    planner = r.host.planner
    assert _side_threshold(r.host.last_result) == pytest.approx(0.6)  # type: ignore[arg-type]
    reply = desk.set("TFC_H_D", 3.0)  # arctan(3 / 2) > phi_max: the threshold stays 0.6
    assert reply.param_value == 3.0
    r.run(0.05)
    assert r.host.planner is planner and planner.desired_height_m == 3.0  # type: ignore[union-attr]
    assert r.host.planner.params.h_d_m == 2.0  # type: ignore[union-attr]  # built with; ramps


def test_h_d_that_moves_the_side_threshold_rebuilds_the_planner_with_it(
    flying: Desk,
) -> None:
    """The bug of the issue: `set_desired_height` alone left eq. (7)'s side threshold at
    min(arctan(H_d / D_min), phi_max) of the old H_d."""
    r, desk = flying.r, flying
    old = r.host.planner
    starts = r.counters["planner_starts"]
    desk.set("TFC_H_D", 1.0)
    r.run(0.05)
    assert r.host.planner is not old and r.counters["planner_starts"] == starts + 1
    assert r.host.planner.params.h_d_m == 1.0  # type: ignore[union-attr]
    want = min(math.atan2(1.0, 2.0), 0.6)
    assert want < 0.6
    assert _side_threshold(r.host.last_result) == pytest.approx(want)  # type: ignore[arg-type]
    assert r.cycle.last_kind == "planner"  # flown in the same cycle (lockstep: built in place)


@pytest.mark.parametrize(
    ("param_id", "key", "value"),
    [
        ("TFC_V_D", "v_d_mps", 1.5),
        ("TFC_D_MIN", "d_min_m", 3.0),
        ("TFC_PHI_MAX", "phi_max_rad", 0.4),
    ],
)
def test_v_d_d_min_and_phi_max_reach_the_planners_params(
    flying: Desk, param_id: str, key: str, value: float
) -> None:
    r, desk = flying.r, flying
    assert desk.set(param_id, value).param_value == pytest.approx(value, rel=1e-7)
    r.run(0.05)
    params = r.host.planner.params  # type: ignore[union-attr]
    assert getattr(params, key) == value and params == r.host.params
    side = _side_threshold(r.host.last_result)  # type: ignore[arg-type]
    assert side == pytest.approx(min(math.atan2(params.h_d_m, params.d_min_m), params.phi_max_rad))


def test_a_change_while_off_the_route_is_refused_whole() -> None:
    class Around(FakePlanner):
        def step(self, *a: Any) -> StepResult:
            res = super().step(*a)
            return StepResult(res.setpoint, replace(res.diagnostics, mode=PathMode.AROUND))

    r = rig()
    r.host.planner_factory = lambda *a: Around(*a)
    r.ap.custom_mode = GUIDED
    r.run(0.2)
    desk = Desk(r)
    before = r.host.params
    assert desk.set("TFC_V_D", 2.0).param_value == 1.0
    assert r.host.params == before and "off the route (around)" in desk.said[-1]
    # H_d within phi_max needs no rebuild: taken at once
    assert desk.set("TFC_H_D", 3.0).param_value == 3.0
    assert r.host.planner.h_d == 3.0  # type: ignore[union-attr]


def test_height_only_is_exactly_a_change_the_running_planner_can_take() -> None:
    base = PlannerConfig().to_params()
    assert height_only(base, replace(base, h_d_m=5.0))  # arctan(5/2) > 0.6 either way
    assert not height_only(base, replace(base, h_d_m=1.0))  # the side threshold moves
    assert not height_only(base, replace(base, h_d_m=5.0, v_d_mps=2.0))


# --- writing accepted values back to the config file ---------------------------------------

CONFIG_TEXT = """\
# a service config, with comments a user wrote
link: {connection: "udpin:0.0.0.0:14540"}
route:
  source: config
  points: [[20.0, 0.0], [40.0, 0.0]]
planner:   # tuned on the field
  h_d_m: 2.0     # H_d, m
  # D_min stays at its default
  v_d_mps: 1.0
sensors:
  - {id: 0, name: front, role: obstacle, group: F, orientation: NONE}
  - {id: 1, name: h1, role: surface, group: forward, orientation: PITCH_315}
  - {id: 2, name: h2, role: surface, group: back, rpy_deg: [0, 315, 180]}
"""
PLANNER_BLOCK = CONFIG_TEXT[CONFIG_TEXT.index("planner:") : CONFIG_TEXT.index("sensors:")]


def test_write_keeps_comments_replaces_and_adds_keys(tmp_path: Path) -> None:
    path = tmp_path / "companion.yaml"
    path.write_text(CONFIG_TEXT)
    path.chmod(0o640)
    write_planner_values(path, {"h_d_m": 3.5, "d_min_m": 2.5})
    text = path.read_text()
    assert "  h_d_m: 3.5     # H_d, m\n" in text
    assert "planner:   # tuned on the field\n  d_min_m: 2.5\n" in text
    assert (
        text.replace("  h_d_m: 3.5     # H_d, m\n", "  h_d_m: 2.0     # H_d, m\n").replace(
            "  d_min_m: 2.5\n", ""
        )
        == CONFIG_TEXT
    )  # nothing else moved
    cfg = load_config(path)
    assert (cfg.planner.h_d_m, cfg.planner.d_min_m, cfg.planner.v_d_mps) == (3.5, 2.5, 1.0)
    assert path.stat().st_mode & 0o777 == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["companion.yaml"]  # no temporary


def test_write_adds_a_missing_section(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(CONFIG_TEXT.replace(PLANNER_BLOCK, ""))
    write_planner_values(path, {"v_d_mps": 1.5})
    assert load_config(path).planner.v_d_mps == 1.5


def test_write_refuses_flow_style_and_leaves_the_file_alone(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    original = CONFIG_TEXT.replace(
        PLANNER_BLOCK,
        "planner: {h_d_m: 2.0}\n",
    )
    path.write_text(original)
    with pytest.raises(ValueError, match="flow style"):
        write_planner_values(path, {"h_d_m": 3.0})
    assert path.read_text() == original
    # a value the config refuses is not written either
    path.write_text(CONFIG_TEXT)
    with pytest.raises(ValueError, match="would not load"):
        write_planner_values(path, {"h_d_m": -1.0})
    assert path.read_text() == CONFIG_TEXT
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml"]


def test_an_accepted_set_is_persisted_and_a_refused_one_is_not(tmp_path: Path) -> None:
    path = tmp_path / "companion.yaml"
    path.write_text(CONFIG_TEXT)
    desk = Desk(rig())
    desk.server.persist = persist_to(path)
    desk.set("TFC_H_D", 4.0)
    desk.set("TFC_V_D", 50.0)  # refused
    cfg = load_config(path)
    assert cfg.planner.h_d_m == 4.0 and cfg.planner.v_d_mps == 1.0
    path.write_text(CONFIG_TEXT.replace(PLANNER_BLOCK, "planner: {h_d_m: 4.0}\n"))
    # a file it cannot edit: the change stays in force, and the pilot is told
    assert desk.set("TFC_H_D", 5.0).param_value == 5.0
    assert "not saved to the config" in desk.said[-1] and "flow style" in desk.said[-1]
    assert desk.r.host.h_d_m == 5.0


def test_a_change_in_flight_is_a_planner_record_of_the_flight_log(tmp_path: Path) -> None:
    r = rig()
    r.host.flight_log = FlightLogWriter(tmp_path, 10_000_000, 3)
    r.host.flight_log.header({"planner": r.host.tuning.model_dump(mode="json")})
    Desk(r).set("TFC_D_MIN", 3.0)
    r.host.flight_log.close()
    (log_file,) = tmp_path.glob("flight-*.jsonl")
    records = [json.loads(line) for line in log_file.read_text().splitlines()]
    (rec,) = [x for x in records if x["type"] == "planner"]
    assert rec["planner"]["d_min_m"] == 3.0 and rec["planner"]["h_d_m"] == 2.0


def test_the_docs_table_is_the_codes() -> None:
    docs = (Path(__file__).resolve().parents[1] / "docs" / "service.md").read_text()
    assert param_table_markdown() in docs
