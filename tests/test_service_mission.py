"""Mission download and waypoint extraction (`companion.service.mission`) against a scripted
peer: the MAVLink mission protocol (REQUEST_LIST, COUNT, REQUEST_INT, ITEM_INT, ACK)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from companion.geo import GeoPoint, LocalFrame
from companion.service.codec import mavlink2
from companion.service.mission import (
    MAX_ITEMS,
    MissionError,
    MissionItem,
    download_mission,
    latlon_to_xy,
    mission_waypoints,
)
from companion.service.modes import AutopilotKind
from tests.service_peer import Peer, connected, settle

pytestmark = pytest.mark.timeout(30)

mav = mavlink2
WP = mav.MAV_CMD_NAV_WAYPOINT
REL = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
HOME = (47.397742, 8.545594)
SHORT_S = 0.05


def item_int(seq: int, lat: float, lon: float, command: int = WP, frame: int = REL) -> Any:
    return mav.MAVLink_mission_item_int_message(
        1, 191, seq, frame, command, 0, 1, 0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 10.0
    )


def serve(peer: Peer, points: list[tuple[float, float]], lose: set[int] | None = None) -> None:
    """Answer the mission protocol with `points` (lat, lon); items in `lose` go unanswered
    the first time they are asked for."""
    lost = set(lose or ())

    def reply(m: Any) -> list[Any]:
        t = m.get_type()
        if t == "MISSION_REQUEST_LIST":
            return [mav.MAVLink_mission_count_message(1, 191, len(points))]
        if t == "MISSION_REQUEST_INT":
            seq = int(m.seq)
            if seq in lost:
                lost.discard(seq)
                return []
            return [item_int(seq, *points[seq])]
        return []

    peer.reply = reply


async def test_download_reads_every_item_in_order_and_acks() -> None:
    conn, peer = await connected()
    pts = [HOME, (47.3980, 8.5456), (47.3985, 8.5460)]
    serve(peer, pts)
    items = await download_mission(conn, timeout_s=5.0, retries=0)
    assert [it.seq for it in items] == [0, 1, 2]
    np.testing.assert_allclose([(it.lat_deg, it.lon_deg) for it in items], pts, atol=1e-7)
    assert all(it.frame == REL and it.command == WP and it.z == 10.0 for it in items)
    await settle()
    (ack,) = peer.of_type("MISSION_ACK")
    assert int(ack.type) == mav.MAV_MISSION_ACCEPTED


async def test_a_lost_item_is_asked_for_again() -> None:
    conn, peer = await connected()
    serve(peer, [HOME, (47.3980, 8.5456)], lose={1})
    items = await download_mission(conn, timeout_s=SHORT_S, retries=2)
    assert len(items) == 2
    asked = [int(m.seq) for m in peer.of_type("MISSION_REQUEST_INT")]
    assert asked == [0, 1, 1]


async def test_no_answer_names_what_was_missing() -> None:
    conn, _peer = await connected()
    with pytest.raises(MissionError, match="no MISSION_COUNT after 2 attempt"):
        await download_mission(conn, timeout_s=SHORT_S, retries=1)


async def test_a_lost_item_after_every_retry_names_the_item() -> None:
    conn, peer = await connected()
    serve(peer, [HOME, (47.3980, 8.5456)])
    peer.reply = (lambda inner: lambda m: [] if getattr(m, "seq", -1) == 1 else inner(m))(
        peer.reply
    )
    with pytest.raises(MissionError) as info:
        await download_mission(conn, timeout_s=SHORT_S, retries=1)
    assert info.value.seq == 1 and str(info.value).startswith("item 1:")


async def test_a_mission_larger_than_the_limit_is_refused() -> None:
    conn, peer = await connected()
    peer.reply = lambda m: (
        [mav.MAVLink_mission_count_message(1, 191, MAX_ITEMS + 1)]
        if m.get_type() == "MISSION_REQUEST_LIST"
        else []
    )
    with pytest.raises(MissionError, match="larger than"):
        await download_mission(conn, timeout_s=5.0, retries=0)
    assert peer.of_type("MISSION_REQUEST_INT") == []


async def test_no_autopilot_yet() -> None:
    conn, _peer = await connected(lock=False)
    with pytest.raises(MissionError, match="no autopilot yet"):
        await download_mission(conn)


def item(seq: int, lat: float, lon: float, command: int = WP, frame: int = REL) -> MissionItem:
    return MissionItem(seq, frame, command, lat, lon, 10.0)


def test_waypoints_skip_home_other_commands_local_frames_and_repeats() -> None:
    items = [
        item(0, *HOME),  # ArduPilot's home
        item(1, 47.3980, 8.5456),
        item(2, 47.3980, 8.5456),  # repeated
        item(3, 0.0, 0.0, command=mav.MAV_CMD_DO_CHANGE_SPEED),
        item(4, 47.3981, 8.5457, frame=mav.MAV_FRAME_LOCAL_NED),
        item(5, 47.3985, 8.5460, command=mav.MAV_CMD_NAV_SPLINE_WAYPOINT),
        item(6, 95.0, 8.5460),  # not a latitude
    ]
    assert mission_waypoints(items, AutopilotKind.ARDUPILOT) == [
        (47.3980, 8.5456),
        (47.3985, 8.5460),
    ]
    # PX4 has no home item: the first one counts
    assert mission_waypoints(items, AutopilotKind.PX4)[0] == HOME


def test_latlon_to_xy_is_the_frames_enu() -> None:
    frame = LocalFrame(GeoPoint(HOME[0], HOME[1], 488.0))
    pts = [HOME, (47.3980, 8.5456)]
    xy = latlon_to_xy(pts, frame)
    assert xy.shape == (2, 2)
    np.testing.assert_allclose(xy[0], [0.0, 0.0], atol=1e-6)
    e, n, _ = frame.to_enu(GeoPoint(47.3980, 8.5456, 488.0))
    np.testing.assert_allclose(xy[1], [e, n])
    assert 20.0 < n < 40.0 and abs(e) < 1.0  # about 29 m north
    assert latlon_to_xy([], frame).shape == (0, 2)
