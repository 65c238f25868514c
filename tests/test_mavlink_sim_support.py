"""Stand-ins and helpers shared by the tests of sim.mavlink (no tests in here).

`PlaneAndWall`: flat ground at z = floor_z and a wall filling x >= wall_x up to wall_h above
it, with exact ray casts (unit tests); `wall_world`: the same shape as a sim.world World
(the servers of the UDP tests). `Tracker`: a vehicle model exactly at its setpoint.
`Client`: a plain pymavlink (mavutil) client with small conveniences.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import GeoPoint, LocalFrame
from companion.planner.sensors import SensorSpec
from companion.planner.types import FloatArray, Setpoint, VehicleState
from companion.sim.mavlink import MavlinkSimConfig, SimServer
from companion.sim.vehicle import IdealTracker
from companion.sim.world import World, WorldConfig
from companion.tuning import SensorConfig


class PlaneAndWall:
    def __init__(self, wall_x: float = 10.0, wall_h: float = 8.0, floor_z: float = 0.0) -> None:
        self.wall_x = wall_x
        self.wall_h = wall_h
        self.floor_z = floor_z

    def height(self, x: Any, y: Any) -> Any:
        x = np.asarray(x, dtype=float)
        return self.floor_z + np.where(x >= self.wall_x, self.wall_h, 0.0)

    def raycast(self, origins: Any, directions: Any, max_range: Any) -> FloatArray:
        o = np.asarray(origins, float).reshape(-1, 3) - [0.0, 0.0, self.floor_z]
        d = np.asarray(directions, float).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=1)[:, None]
        r = np.broadcast_to(np.asarray(max_range, float), (len(o),))
        out = np.full(len(o), np.inf)
        for i in range(len(o)):
            hits = []
            if o[i, 2] < 0:
                hits.append(0.0)
            elif d[i, 2] < 0:
                hits.append(-o[i, 2] / d[i, 2])
            if d[i, 0] > 0:
                t = (self.wall_x - o[i, 0]) / d[i, 0]
                z = o[i, 2] + t * d[i, 2]
                if t >= 0 and 0 <= z <= self.wall_h:
                    hits.append(t)
            if hits and min(hits) <= r[i]:
                out[i] = min(hits)
        return out


class Tracker:
    """Exactly at the setpoint, level, with its yaw."""

    def __init__(self, initial: VehicleState) -> None:
        self.state = initial

    def step(self, setpoint: Setpoint, dt_s: float) -> VehicleState:
        self.state = VehicleState(np.array(setpoint.position_enu), 0.0, 0.0, setpoint.yaw_rad)
        return self.state


def sensors() -> list[SensorSpec]:
    cfgs = [
        SensorConfig(id=3, role="obstacle", group="F", orientation="NONE", max_range_m=12.0),
        SensorConfig(id=4, role="obstacle", group="F", rpy_deg=(0, 15, 0), max_range_m=12.0),
        SensorConfig(id=5, role="obstacle", group="L", orientation="YAW_180", max_range_m=12.0),
        SensorConfig(id=7, role="surface", group="forward", orientation="PITCH_315"),
        SensorConfig(id=8, role="surface", group="back", rpy_deg=(0, 315, 180)),
    ]
    return [c.to_spec() for c in cfgs]


def wall_world(wall_x: float = 10.0, wall_h: float = 8.0, floor_z: float = 0.0) -> World:
    """sim.world's World shaped like PlaneAndWall: a 2 m thick, 200 m wide box from wall_x."""
    box = {"type": "box", "center": [wall_x + 1.0, 0.0], "size_m": [2.0, 200.0, wall_h]}
    return World.from_config(WorldConfig.model_validate({"ground_z_m": floor_z, "features": [box]}))


def make_server(**overrides: Any) -> SimServer:
    """A server on 127.0.0.1, any port, fast: sim.world's World (a wall 10 m east of home),
    sim.vehicle's IdealTracker, the sensors above."""
    world = overrides.pop("world", None) or wall_world()
    fields: dict[str, Any] = {"port": 0, "speedup": 20.0, "prearm_delay_s": 0.2, **overrides}
    return SimServer(MavlinkSimConfig.model_validate(fields), world, sensors(), IdealTracker)


class Client:
    """A plain pymavlink client (what a ground station or a simple script does)."""

    def __init__(self, port: int, sysid: int = 42, compid: int = 191) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=sysid, source_component=compid
        )
        self.mav = self.conn.mav
        self._kept: list[Any] = []
        self.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0)

    KEPT = ("MESSAGE_INTERVAL",)
    """Replies that may arrive before a COMMAND_ACK: kept for a later recv()."""

    def recv(self, types: str | list[str], timeout: float = 5.0, cond: Any = None) -> Any:
        wanted = [types] if isinstance(types, str) else types
        for msg in self._kept:
            if msg.get_type() in wanted and (cond is None or cond(msg)):
                self._kept.remove(msg)
                return msg
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(blocking=True, timeout=left)
            if msg is None:
                continue
            if msg.get_type() in wanted and (cond is None or cond(msg)):
                return msg
            if msg.get_type() in self.KEPT:
                self._kept.append(msg)
        raise TimeoutError(f"no {types} within {timeout} s")

    def command(self, cmd: int, *params: float, timeout: float = 5.0) -> int:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.mav.command_long_send(1, 1, cmd, 0, *p)
        ack = self.recv("COMMAND_ACK", timeout, lambda m: m.command == cmd)
        return int(ack.result)

    def set_interval(self, msg_id: int, hz: float) -> int:
        return self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def frame_of(server: SimServer) -> LocalFrame:
    h = server.config.home_or_default
    return LocalFrame(GeoPoint(h.lat_deg, h.lon_deg, h.alt_m))


def latlon_int(frame: LocalFrame, east: float, north: float) -> tuple[int, int]:
    g = frame.to_geodetic(east, north, 0.0)
    return round(g.lat_deg * 1e7), round(g.lon_deg * 1e7)


def enu_of(frame: LocalFrame, msg: Any) -> FloatArray:
    """World ENU of a GLOBAL_POSITION_INT."""
    return np.array(frame.to_enu(GeoPoint(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)))


def yaw_ignore_pos_only() -> int:
    from companion.sim.mavlink.setpoints import ACC_IGNORE, VEL_IGNORE, YAW_IGNORE, YAW_RATE_IGNORE

    return VEL_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE


def close_to(a: float, b: float, tol: float) -> bool:
    return math.isclose(a, b, abs_tol=tol)
