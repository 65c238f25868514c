"""Sensor bridge: virtual range sensors for a real ArduPilot or PX4 SITL.

The simulator flies nothing here. It reads the autopilot's MAVLink stream (HOME_POSITION for
the origin, GLOBAL_POSITION_INT and ATTITUDE for the pose), ray-casts the scenario's world at
that pose and sends a DISTANCE_SENSOR per configured sensor, at `rate_hz` wall-clock:
- `send_to: autopilot`: back over the same connection, from (system_id, component_id), for
  the autopilot to use (RNGFNDn_TYPE = MAVLink, PRX1_TYPE = MAVLink on ArduPilot) and
  re-publish. Filled as a MAVLink rangefinder would be: id = configured sensor id, "nothing
  in range" as max + 1 m.
- `send_to: companion`: straight to `companion_address` over UDP, filled the way the
  autopilot (from its HEARTBEAT: ArduPilot or PX4) re-reports them, as if it had sent them.

Placement: the autopilot's home sits at world (anchor_xy, anchor_z: by default the terrain
height there); world ENU = anchor + ENU offset of the reported position from home. The
SITL's own ground stays flat at home altitude; the virtual terrain is only seen through the
sensors.

The bridge asks for the messages it needs (MAV_CMD_SET_MESSAGE_INTERVAL, REQUEST_MESSAGE for
HOME_POSITION), since ArduPilot sends nothing but HEARTBEAT to a client that has not asked.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import GeoPoint, LocalFrame
from companion.planner.frames import attitude_ned_to_enu
from companion.planner.sensors import SensorSpec
from companion.planner.types import VehicleState
from companion.sim.mavlink.codec import Codec
from companion.sim.mavlink.config import BridgeConfig, parse_host_port
from companion.sim.mavlink.models import RangeWorld
from companion.sim.mavlink.rangefinder import Rangefinders

log = logging.getLogger(__name__)

REQUEST_EVERY_S = 1.0
PERIPHERAL_COMPONENT = mavlink.MAV_COMP_ID_PERIPHERAL


class BridgeCore:
    """Pose tracking and DISTANCE_SENSOR generation, without I/O (fed decoded messages)."""

    def __init__(
        self, config: BridgeConfig, world: RangeWorld, sensors: Sequence[SensorSpec]
    ) -> None:
        self.config = config
        self.world = world
        self.sensors = tuple(sensors)
        ax, ay = config.anchor_xy
        az = config.anchor_z
        if az is None:
            az = float(np.asarray(world.height(ax, ay)))
        self.anchor = np.array([ax, ay, az])
        self.autopilot_family: Literal["ardupilot", "px4"] = "ardupilot"
        self.autopilot_sysid: int | None = None
        self.home: LocalFrame | None = None
        self.time_boot_ms = 0
        self._boot_ms_rx: float | None = None
        self._geo: GeoPoint | None = None
        self._attitude_ned: tuple[float, float, float] | None = None
        self._rangefinders: dict[str, Rangefinders] = {}
        self.track: list[tuple[float, ...]] | None = None
        """Set to a list to record (t_rx, x, y, z, roll, pitch, yaw) of the world-frame pose
        at each GLOBAL_POSITION_INT (t_rx as given to handle(), e.g. monotonic seconds)."""

    def handle(self, msg: Any, t_rx: float | None = None) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
            self.autopilot_sysid = msg.get_srcSystem()
            self.autopilot_family = (
                "px4" if msg.autopilot == mavlink.MAV_AUTOPILOT_PX4 else "ardupilot"
            )
        elif kind == "HOME_POSITION":
            self.home = LocalFrame(
                GeoPoint(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            )
        elif kind == "GLOBAL_POSITION_INT":
            self._geo = GeoPoint(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
            self._stamp(msg, t_rx)
            if self.track is not None and t_rx is not None:
                state = self.pose()
                if state is not None:
                    self.track.append(
                        (t_rx, *state.position_enu, state.roll_rad, state.pitch_rad, state.yaw_rad)
                    )
        elif kind == "ATTITUDE":
            self._attitude_ned = (float(msg.roll), float(msg.pitch), float(msg.yaw))
            self._stamp(msg, t_rx)

    def _stamp(self, msg: Any, t_rx: float | None) -> None:
        self.time_boot_ms = int(msg.time_boot_ms)
        self._boot_ms_rx = t_rx

    def boot_ms_at(self, now: float | None) -> int:
        """The autopilot's time_boot_ms now, extrapolated in wall time from the last stamped
        message (as the autopilot stamps its re-reports with the send time); without `now`,
        the last one received."""
        if now is None or self._boot_ms_rx is None:
            return self.time_boot_ms
        return self.time_boot_ms + max(int((now - self._boot_ms_rx) * 1000.0), 0)

    def pose(self) -> VehicleState | None:
        """The vehicle in the world frame, once home, position and attitude are known."""
        if self.home is None or self._geo is None or self._attitude_ned is None:
            return None
        offset = np.array(self.home.to_enu(self._geo))
        roll, pitch, yaw = attitude_ned_to_enu(*self._attitude_ned)
        return VehicleState(self.anchor + offset, roll, pitch, yaw)

    def rangefinders(self) -> Rangefinders:
        family = "ardupilot" if self.config.send_to == "autopilot" else self.autopilot_family
        if family not in self._rangefinders:
            self._rangefinders[family] = Rangefinders(self.sensors, self.world, family)
        return self._rangefinders[family]

    def distance_messages(self, mav: Any, now: float | None = None) -> list[Any]:
        """One DISTANCE_SENSOR per sensor at the current pose (none before it is known);
        `now` (the clock handle() was given) stamps them at the autopilot's current time."""
        state = self.pose()
        if state is None:
            return []
        if self.config.send_to == "companion" and self.autopilot_sysid is None:
            return []  # which autopilot's conventions to imitate is not known yet
        rf = self.rangefinders()
        ranges = rf.measure(state)
        stamp = self.boot_ms_at(now)
        return rf.messages(mav, ranges, stamp)


class _Link(asyncio.DatagramProtocol):
    def __init__(self, on_data: Callable[[bytes, Any], None]) -> None:
        self.on_data = on_data

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.on_data(data, addr)

    def error_received(self, exc: Exception) -> None:
        log.debug("bridge UDP error: %s", exc)


class SensorBridge:
    """BridgeCore on a live connection (udpin:, udpout:/udp:, tcp: connection strings)."""

    def __init__(
        self, config: BridgeConfig, world: RangeWorld, sensors: Sequence[SensorSpec]
    ) -> None:
        self.config = config
        self.core = BridgeCore(config, world, sensors)
        self.codec = Codec(config.system_id, config.component_id)
        # What goes to the autopilot must not claim to come from the autopilot itself
        # (ArduPilot ignores its own system/component): component 1 is replaced by 158.
        link_component = PERIPHERAL_COMPONENT if config.component_id == 1 else config.component_id
        self.link_codec = Codec(config.system_id, link_component)
        self.sent = 0
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_peer: Any = None
        self._tcp: asyncio.StreamWriter | None = None
        self._tcp_reader_task: asyncio.Task[None] | None = None
        self._companion: asyncio.DatagramTransport | None = None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        kind, _, rest = self.config.connect.partition(":")
        host, port = parse_host_port(rest)
        if kind in ("udpin", "udp"):
            self._udp, _ = await loop.create_datagram_endpoint(
                lambda: _Link(self._on_udp), local_addr=(host, port)
            )
        elif kind == "udpout":
            self._udp_peer = (host, port)
            self._udp, _ = await loop.create_datagram_endpoint(
                lambda: _Link(self._on_udp), remote_addr=(host, port)
            )
        elif kind == "tcp":
            reader, self._tcp = await asyncio.open_connection(host, port)
            self._tcp_reader_task = loop.create_task(self._read_tcp(reader))
        else:
            raise ValueError(f"unsupported connection string {self.config.connect!r}")
        if self.config.send_to == "companion":
            assert self.config.companion_address is not None
            self._companion, _ = await loop.create_datagram_endpoint(
                lambda: _Link(lambda data, addr: None),
                remote_addr=parse_host_port(self.config.companion_address),
            )

    async def run(self, duration_s: float | None = None) -> None:
        """Send at rate_hz until duration_s (wall clock) or cancellation."""
        period = 1.0 / self.config.rate_hz
        start = time.monotonic()
        next_request = start
        next_send = start
        while duration_s is None or time.monotonic() - start < duration_s:
            now = time.monotonic()
            if now >= next_request:
                next_request = now + REQUEST_EVERY_S
                self._request_streams()
            to_companion = self.config.send_to == "companion"
            codec = self.codec if to_companion else self.link_codec
            msgs = self.core.distance_messages(codec.mav, time.monotonic())
            if to_companion and msgs:
                # one datagram per round, as an autopilot packs its UDP stream: a busy
                # companion's socket buffer then holds many more rounds
                self._send_companion(b"".join(codec.encode(m) for m in msgs), len(msgs))
            else:
                for msg in msgs:
                    self._send(msg)
            next_send += period
            await asyncio.sleep(max(next_send - time.monotonic(), 0.0))

    async def close(self) -> None:
        if self._tcp_reader_task is not None:
            self._tcp_reader_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._tcp_reader_task
        for transport in (self._udp, self._companion):
            if transport is not None:
                transport.close()
        if self._tcp is not None:
            self._tcp.close()

    def _request_streams(self) -> None:
        """Heartbeat, and ask for what the pose needs (cheap to repeat, as GCSs do)."""
        mav = self.link_codec.mav
        self._send(
            mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
            )
        )
        target = self.core.autopilot_sysid or 0
        interval_us = 1e6 / max(self.config.rate_hz, 1.0)
        for msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT):
            self._send(
                mav.command_long_encode(
                    target,
                    0,
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    0,
                    msg_id,
                    interval_us,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            )
        if self.core.home is None:
            self._send(
                mav.command_long_encode(
                    target,
                    0,
                    mavlink.MAV_CMD_REQUEST_MESSAGE,
                    0,
                    mavlink.MAVLINK_MSG_ID_HOME_POSITION,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            )

    def _send_companion(self, data: bytes, count: int) -> None:
        if self._companion is not None:
            self._companion.sendto(data)
            self.sent += count

    def _send(self, msg: Any, to_companion: bool = False) -> None:
        data = (self.codec if to_companion else self.link_codec).encode(msg)
        if to_companion:
            if self._companion is not None:
                self._companion.sendto(data)
                self.sent += 1
            return
        if self._tcp is not None:
            self._tcp.write(data)
        elif self._udp is not None and self._udp_peer is not None:
            if self._udp.get_extra_info("peername") is not None:
                self._udp.sendto(data)
            else:
                self._udp.sendto(data, self._udp_peer)
        else:
            return
        self.sent += 1

    def _on_udp(self, data: bytes, addr: Any) -> None:
        if self._udp_peer is None or self.config.connect.startswith(("udpin", "udp:")):
            self._udp_peer = addr
        self._feed(data)

    async def _read_tcp(self, reader: asyncio.StreamReader) -> None:
        while data := await reader.read(4096):
            self._feed(data)

    def _feed(self, data: bytes) -> None:
        now = time.monotonic()
        for msg in self.link_codec.decode(data):
            self.core.handle(msg, now)
