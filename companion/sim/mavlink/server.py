"""The MAVLink vehicle simulator: an asyncio UDP endpoint in front of world + vehicle model.

    server = SimServer(config, world, sensors, vehicle_factory, bind=("127.0.0.1", 0))
    await server.start()              # binds; server.port is the UDP port
    await server.run_until(60.0)      # simulated seconds (or server.start_background())
    server.truth                      # per-tick true state, for metrics
    await server.close()

Addressing: the simulator listens on a UDP port and sends to whichever address last sent it
a datagram (like SITL's UDP ports), or always to `config.target` when set. Until someone has
sent something, outgoing messages are built (and fault draws made) but go nowhere.

Time: physics ticks of `physics_dt_s` simulated seconds. In each tick the simulator
1. applies scheduled faults (reboot, pilot mode change) due in [t, t + dt),
2. handles everything received since the previous tick, in arrival order,
3. runs the autopilot (sim.mavlink.autopilot) and steps the vehicle model to t + dt,
4. sends status texts and the telemetry due at t + dt, records the truth.
Then it paces: `speedup` times real time (inf: as fast as possible), and in lockstep:

Lockstep protocol (the companion side implements the other half):
- Every `lockstep.period_s` of simulated time (a whole number of ticks), after that tick's
  telemetry, the simulator sends TIMESYNC(tc1=0, ts1=simulated time since start in ns) and
  stops. The period's messages go out together, the TIMESYNC request last, packed into
  datagrams of at most `lockstep.datagram_bytes` (one per period as a rule): the companion
  wakes once per period, not once per message, and receives the same messages in the same
  order.
- The companion runs its cycle on what it has received, sends its setpoint/commands, and
  then answers TIMESYNC(tc1=its clock in ns, non-zero, ts1=the same ts1) -- what it would
  answer to any TIMESYNC request, only delayed until its cycle is done.
- On that answer the simulator handles everything received (in order) at the next tick and
  advances. Without an answer within `lockstep.timeout_s` of wall-clock time (also when no
  client has connected yet) it carries on and counts a stall in `stats.lockstep_stalls`.
- Lockstep TIMESYNCs are simulation control: link faults and reboots do not affect them,
  and the regular TIMESYNC stream is off in lockstep.
The same scenario with a companion that only acts between a TIMESYNC request and its answer
gives the same trace, whatever the machine load.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import GeoPoint, LocalFrame
from companion.planner.frames import wrap_pi
from companion.planner.sensors import SensorSpec
from companion.planner.types import FloatArray, VehicleState
from companion.sim.mavlink import telemetry as tm
from companion.sim.mavlink.autopilot import ACCEPTED, FAILED, FORCE_MAGIC, UNSUPPORTED, Autopilot
from companion.sim.mavlink.clock import Pacer
from companion.sim.mavlink.codec import Codec
from companion.sim.mavlink.config import MavlinkSimConfig, parse_host_port
from companion.sim.mavlink.faults import FaultSchedule, LinkFaults, SensorFaults, fault_rngs
from companion.sim.mavlink.mission import MissionItem, MissionServer
from companion.sim.mavlink.models import RangeWorld, VehicleFactory, VehicleModel
from companion.sim.mavlink.personality import personality
from companion.sim.mavlink.rangefinder import Rangefinders
from companion.sim.mavlink.setpoints import FRAMES_AMSL, Decision
from companion.sim.mavlink.streams import NAME_OF_ID, STREAMED_MESSAGES

log = logging.getLogger(__name__)

COMMAND_REBOOT_S = 1.0
"""Silence after MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN."""

Address = tuple[str, int]
_CommandHandler = Callable[[list[float], int | None, float], int]
"""A command's handler: (param1..param7, COMMAND_INT frame or None, now_s) -> MAV_RESULT."""

# MAV_DATA_STREAM groups of REQUEST_DATA_STREAM (ArduPilot's legacy stream rates).
_DATA_STREAMS: dict[int, tuple[str, ...]] = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "EXTENDED_SYS_STATE"),
    mavlink.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("DISTANCE_SENSOR", "SYSTEM_TIME"),
}
_DATA_STREAMS[mavlink.MAV_DATA_STREAM_ALL] = tuple(
    name for names in _DATA_STREAMS.values() for name in names
)


@dataclass(frozen=True, slots=True)
class TruthSample:
    """The true vehicle state after a tick. World ENU / FLU, metres, radians."""

    t_s: float
    position_enu: FloatArray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    mode: str
    armed: bool
    landed: bool


@dataclass
class SimStats:
    ticks: int = 0
    lockstep_waits: int = 0
    lockstep_stalls: int = 0
    received: int = 0
    received_by_type: Counter[str] = field(default_factory=Counter)
    sent: int = 0
    """Messages sent (lockstep packs a period's messages into few datagrams)."""
    datagrams: int = 0
    """Datagrams sent."""
    dropped_link_down: int = 0
    reboots: int = 0
    decisions: deque[Decision] = field(default_factory=lambda: deque(maxlen=32))
    """The last SET_POSITION_TARGET_GLOBAL_INT decisions (newest last)."""


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, server: SimServer) -> None:
        self.server = server

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.server._datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable on loopback when the peer has gone: keep serving.
        log.debug("UDP error: %s", exc)


class SimServer:
    """A simulated ArduPilot/PX4 vehicle on a UDP port (see module docstring).

    config: the `mavlink:` section. world: terrain height and ray casting. sensors: the range
    sensor table (body FLU boresights). vehicle_factory: makes the vehicle model at lift-off.
    start_position_enu: where the vehicle starts (x, y; z is put on the terrain for air
    vehicles; submarines start at the given z, default 0). bind: (host, port) overriding the
    config.
    """

    def __init__(
        self,
        config: MavlinkSimConfig,
        world: RangeWorld,
        sensors: Sequence[SensorSpec],
        vehicle_factory: VehicleFactory,
        *,
        start_position_enu: Sequence[float] | None = None,
        start_yaw_rad: float = 0.0,
        bind: Address | None = None,
    ) -> None:
        self.config = config
        self.personality = personality(config.personality)
        home = config.home_or_default
        self.frame = LocalFrame(GeoPoint(home.lat_deg, home.lon_deg, home.alt_m))
        self.world = world
        self._vehicle_factory = vehicle_factory
        self._bind: Address = bind if bind is not None else (config.bind_host, config.port)
        self._target: Address | None = (
            parse_host_port(config.target) if config.target is not None else None
        )
        self.dt_s = config.physics_dt_s
        self._lockstep_ticks = (
            max(1, round(config.lockstep.period_s / self.dt_s)) if config.lockstep.enabled else 0
        )
        # lockstep: the period's outgoing frames, sent together before its TIMESYNC request
        self._batch_bytes = config.lockstep.datagram_bytes if config.lockstep.enabled else 0
        self._batch: list[bytes] = []
        self._batch_len = 0

        x, y, z = (list(start_position_enu) + [0.0] * 3)[:3] if start_position_enu else (0, 0, 0)
        if not self.personality.is_submarine or start_position_enu is None:
            ground = self._height(float(x), float(y))
            z = ground if not self.personality.is_submarine else 0.0
        self.state = VehicleState(np.array([x, y, z], dtype=float), 0.0, 0.0, start_yaw_rad)
        self.velocity_enu = np.zeros(3)
        self._rates = (0.0, 0.0, 0.0)
        self.t_s = 0.0
        self._tick_index = 0
        self._vehicle: VehicleModel | None = None

        self.autopilot = Autopilot(
            self.personality, config, self.frame, self._height, self.state, 0.0
        )
        self.rangefinders = Rangefinders(
            sensors, world, self.personality.family, config.distance_sensor_quaternion
        )
        rng_sensors, rng_out, rng_in = fault_rngs(config.faults.seed)
        self.sensor_faults = SensorFaults(
            config.faults.sensors,
            [s.sensor_id for s in self.rangefinders.specs],
            self.rangefinders.min_m,
            self.rangefinders.max_m,
            rng_sensors,
        )
        self.outgoing_faults: LinkFaults[bytes] = LinkFaults(config.faults.outgoing, rng_out)
        self.incoming_faults: LinkFaults[Any] = LinkFaults(config.faults.incoming, rng_in)
        self.schedule = FaultSchedule(config.faults)

        rates = {**self.personality.default_rates_hz, **config.rates_hz}
        if config.lockstep.enabled:
            rates["TIMESYNC"] = 0.0
        # ArduPilot sends the streams of one interval together (its message buckets); PX4
        # runs one stream per message, each with its own phase.
        phases: tm.StreamPhases = (
            "buckets" if self.personality.family == "ardupilot" else "per_stream"
        )
        self.scheduler = tm.MessageScheduler(rates, phases)
        self.codec = Codec(config.system_id, config.component_id)
        self.mission = MissionServer(
            self.codec.mav,
            self._send,
            self._home_item if self.personality.has_home_mission_item else None,
        )

        self.truth: list[TruthSample] = []
        self.stats = SimStats()
        self.pacer = Pacer(config.speedup)
        self.peer: Address | None = None
        self._inbox: deque[Any] = deque()
        self._transport: asyncio.DatagramTransport | None = None
        self._peer_event = asyncio.Event()
        self._reply_event = asyncio.Event()
        self._lockstep_ts1: int | None = None
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        self._reboot_requested = False
        self._silent_until = -math.inf
        self._link_key: tuple[float, float] | None = None
        self._link_state = True
        self._after_ack: list[Any] = []
        self._home_amsl_key: tuple[float, ...] | None = None
        self._home_amsl_m = math.nan
        self._commands = self._command_table()
        self._record_truth()

    @classmethod
    def from_scenario(cls, scenario: Any, base_dir: Any = ".", **overrides: Any) -> SimServer:
        """Build from a `sim.scenario.Scenario`: its world, sensors, vehicle and `mavlink:`.

        overrides: fields of MavlinkSimConfig to replace (e.g. port=0, speedup=math.inf), or
        `bind=(host, port)`.
        """
        from companion.sim.vehicle import make_vehicle
        from companion.sim.world import World

        raw = getattr(scenario, "mavlink", None)
        if raw is None:
            config = MavlinkSimConfig()
        elif isinstance(raw, MavlinkSimConfig):
            config = raw
        else:
            config = MavlinkSimConfig.model_validate(raw)
        bind = overrides.pop("bind", None)
        if overrides:
            config = MavlinkSimConfig.model_validate({**config.model_dump(), **overrides})
        world = World.from_config(scenario.world, base_dir)
        specs = [s.to_spec() for s in scenario.sensors]
        vehicle_cfg = scenario.vehicle

        def factory(initial: VehicleState) -> VehicleModel:
            return make_vehicle(vehicle_cfg, initial)

        # Start at the route's first base point (air vehicles on the ground, submarines at
        # the given depth or the surface) unless the scenario gives a start position.
        start = scenario.start_position
        if start is None:
            x, y = scenario.route.points[0]
            start = (x, y, 0.0)
        # Facing along the route's start heading, as the in-process closed loop starts.
        yaw = scenario.route_obj().start_heading_rad
        return cls(
            config, world, specs, factory, start_position_enu=start, start_yaw_rad=yaw, bind=bind
        )

    # ------------------------------------------------------------------- life cycle
    async def start(self) -> None:
        """Bind the UDP socket (does not advance time)."""
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _Protocol(self), local_addr=self._bind
        )
        self._transport = transport

    @property
    def port(self) -> int:
        """The UDP port listened on (after start())."""
        if self._transport is None:
            raise RuntimeError("SimServer.start() has not been awaited")
        return int(self._transport.get_extra_info("sockname")[1])

    async def run_until(self, t_end_s: float) -> None:
        """Advance simulated time to t_end_s (paced, lockstep as configured)."""
        if self._transport is None:
            await self.start()
        end_tick = round(t_end_s / self.dt_s) if math.isfinite(t_end_s) else math.inf
        self.pacer.restart(self.t_s)
        while self._tick_index < end_tick and not self._closed:
            self._tick()
            if self._lockstep_ticks and self._tick_index % self._lockstep_ticks == 0:
                await self._lockstep_wait()
            await self.pacer.pace(self.t_s)
        self._flush_batch()

    async def run_forever(self) -> None:
        await self.run_until(math.inf)

    def start_background(self, until_s: float = math.inf) -> asyncio.Task[None]:
        """Run in a task until until_s (or close()); returns the task."""
        self._task = asyncio.get_running_loop().create_task(self.run_until(until_s))
        return self._task

    async def close(self) -> None:
        self._closed = True
        self._reply_event.set()
        self._peer_event.set()
        if self._task is not None and not self._task.done():
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self._transport is not None:
            self._flush_batch()
            self._transport.close()
            self._transport = None

    async def __aenter__(self) -> SimServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def mission_items(self, mission_type: int = 0) -> list[MissionItem]:
        return self.mission.items(mission_type)

    # ------------------------------------------------------------------------ ticks
    def _tick(self) -> None:
        now = self.t_s
        self._scheduled_events(now)
        self._drain_inbox(now)
        if self._reboot_requested:
            self._reboot_requested = False
            self._silent_until = now + COMMAND_REBOOT_S
            self._reboot(now)
        setpoint = self.autopilot.update(now, self.dt_s, self.state)
        previous = self.state
        if setpoint is None:
            self._vehicle = None
            new_state = self._resting(previous)
        else:
            if self._vehicle is None:
                self._vehicle = self._vehicle_factory(previous)
            new_state = self._vehicle.step(setpoint, self.dt_s)
        self._tick_index += 1
        self.stats.ticks = self._tick_index
        self.t_s = self._tick_index * self.dt_s
        self.velocity_enu = (new_state.position_enu - previous.position_enu) / self.dt_s
        # Euler-angle rates as body rates; yaw clockwise positive as MAVLink has it.
        self._rates = (
            wrap_pi(new_state.roll_rad - previous.roll_rad) / self.dt_s,
            wrap_pi(new_state.pitch_rad - previous.pitch_rad) / self.dt_s,
            -wrap_pi(new_state.yaw_rad - previous.yaw_rad) / self.dt_s,
        )
        self.state = new_state
        self._flush_texts()
        self._telemetry(self.t_s)
        self.mission.tick(self.t_s)
        if self._tick_index % self.config.truth_every_n_ticks == 0:
            self._record_truth()

    def _resting(self, state: VehicleState) -> VehicleState:
        """A vehicle that is not flown: level, on the terrain if it is an air vehicle."""
        pos = np.array(state.position_enu, dtype=np.float64)
        if not self.personality.is_submarine:
            pos[2] = self._height(float(pos[0]), float(pos[1]))
            return VehicleState(pos, 0.0, 0.0, state.yaw_rad)
        return state

    def _record_truth(self) -> None:
        s = self.state
        self.truth.append(
            TruthSample(
                self.t_s,
                np.array(s.position_enu),
                s.roll_rad,
                s.pitch_rad,
                s.yaw_rad,
                self.autopilot.mode.name,
                self.autopilot.armed,
                self.autopilot.landed,
            )
        )

    def _height(self, x: float, y: float) -> float:
        return float(np.asarray(self.world.height(x, y)))

    def _scheduled_events(self, now: float) -> None:
        self.autopilot.estimate_offset_enu = self.schedule.position_offset(now)
        # [now, now + dt) shifted down by a hair: tick times are k * dt in floating point
        # (13.700000000000001), so an event at 13.7 must not fall between two ticks.
        t0, t1 = now - 1e-6, now + self.dt_s - 1e-6
        for _ in self.schedule.reboots_in(t0, t1):
            self._reboot(now)
        for spec in self.schedule.mode_changes_in(t0, t1):
            mode = self.personality.mode_from_spec(spec)
            self.autopilot.set_mode(mode, now, self.state, forced=True)

    def _reboot(self, now: float) -> None:
        self.stats.reboots += 1
        self.autopilot.reboot(now, self.state)
        self.scheduler.reset(now)
        self.codec.restart()
        self.mission.cancel_transfers()
        self._inbox.clear()
        self.outgoing_faults.flush()
        self.incoming_faults.flush()

    # ------------------------------------------------------------------- telemetry
    def snapshot(self) -> tm.Snapshot:
        """The state as the autopilot estimates it (the truth, shifted by a position jump)."""
        ap = self.autopilot
        return tm.Snapshot(
            time_boot_ms=ap.time_boot_ms(self.t_s),
            time_ns=round((self.t_s - ap.boot_s) * 1e9),
            position_enu=np.asarray(self.state.position_enu) + ap.estimate_offset_enu,
            velocity_enu=self.velocity_enu,
            roll_rad=self.state.roll_rad,
            pitch_rad=self.state.pitch_rad,
            yaw_rad=self.state.yaw_rad,
            rates_radps=self._rates,
        )

    def _telemetry(self, now: float) -> None:
        due = self.scheduler.due(now)
        if not due:
            return
        snap = self.snapshot()
        for msg_id in due:
            self._send_telemetry(msg_id, snap)

    def _send_telemetry(
        self, msg_id: int, snap: tm.Snapshot, send: Callable[[Any], None] | None = None
    ) -> None:
        mav = self.codec.mav
        out = self._send if send is None else send
        ap = self.autopilot
        name = NAME_OF_ID[msg_id]
        if name == "HEARTBEAT":
            out(tm.heartbeat_message(mav, self.personality, ap.mode, ap.armed, ap.failsafe))
        elif name == "SYS_STATUS":
            out(tm.sys_status_message(mav, ap.ready(self.t_s), 0.0))
        elif name == "SYSTEM_TIME":
            out(mav.system_time_encode(int(time.time() * 1e6), snap.time_boot_ms))
        elif name == "ATTITUDE":
            out(tm.attitude_message(mav, snap))
        elif name == "GLOBAL_POSITION_INT":
            out(tm.global_position_int_message(mav, snap, self.frame, self._home_amsl()))
        elif name == "LOCAL_POSITION_NED":
            out(tm.local_position_ned_message(mav, snap, ap.origin_enu))
        elif name == "HOME_POSITION":
            out(
                tm.home_position_message(
                    mav, self.frame, ap.home_enu, ap.origin_enu, snap.time_boot_ms * 1000
                )
            )
        elif name == "EXTENDED_SYS_STATE":
            climbing = ap.takeoff_z is not None
            out(tm.extended_sys_state_message(mav, ap.landed, ap.armed, climbing))
        elif name == "TIMESYNC":
            out(mav.timesync_encode(0, snap.time_ns))
        elif name == "DISTANCE_SENSOR":
            self._send_distance_sensors(snap, out)

    def _home_amsl(self) -> float:
        """Home's altitude above mean sea level (m), converted again only when home moves."""
        key = tuple(float(v) for v in self.autopilot.home_enu)
        if key != self._home_amsl_key:
            self._home_amsl_key = key
            self._home_amsl_m = self.autopilot.frame_context.amsl(self.autopilot.home_enu)
        return self._home_amsl_m

    def _send_distance_sensors(self, snap: tm.Snapshot, out: Callable[[Any], None]) -> None:
        rf = self.rangefinders
        if not len(rf):
            return
        ranges, send = self.sensor_faults.apply(self.t_s, rf.measure(self.state))
        if out == self._send:  # streamed: packed straight to bytes, as _send would
            for data in rf.frames(self.codec, ranges, snap.time_boot_ms, send):
                self._send_frame(data)
            return
        for msg in rf.messages(self.codec.mav, ranges, snap.time_boot_ms, send):
            out(msg)

    def _flush_texts(self) -> None:
        texts, self.autopilot.texts = self.autopilot.texts, []
        for t in texts:
            self._send(self.codec.mav.statustext_encode(t.severity, t.text.encode()))

    def _home_item(self) -> MissionItem:
        geo = self.frame.to_geodetic(*(float(v) for v in self.autopilot.home_enu))
        return MissionItem(
            0,
            mavlink.MAV_FRAME_GLOBAL,
            mavlink.MAV_CMD_NAV_WAYPOINT,
            0,
            1,
            0.0,
            0.0,
            0.0,
            0.0,
            round(geo.lat_deg * 1e7),
            round(geo.lon_deg * 1e7),
            geo.alt_m,
        )

    # --------------------------------------------------------------------- sending
    def _destination(self) -> Address | None:
        return self._target if self._target is not None else self.peer

    def _send(self, msg: Any) -> None:
        """Encode and send through the outgoing faults (dropped while the link is down)."""
        self._send_frame(self.codec.encode(msg))

    def _send_frame(self, data: bytes) -> None:
        """Send one packed message as `_send` does."""
        if not self._link_up():
            self.stats.dropped_link_down += 1
            return
        for packet in self.outgoing_faults.filter(data, self.t_s):
            self._sendto(packet)

    def _link_up(self) -> bool:
        key = (self.t_s, self._silent_until)  # a tick's messages ask the same question
        if key != self._link_key:
            self._link_key = key
            self._link_state = self.t_s >= self._silent_until and self.schedule.link_up(self.t_s)
        return self._link_state

    def _sendto(self, data: bytes) -> None:
        dest = self._destination()
        if dest is None or self._transport is None:
            return
        self.stats.sent += 1
        if not self._batch_bytes:
            self.stats.datagrams += 1
            self._transport.sendto(data, dest)
            return
        if self._batch and self._batch_len + len(data) > self._batch_bytes:
            self._flush_batch()
        self._batch.append(data)
        self._batch_len += len(data)

    def _flush_batch(self) -> None:
        """Send the frames held for the lockstep period, whole, in one datagram."""
        if not self._batch:
            return
        data = b"".join(self._batch)
        self._batch.clear()
        self._batch_len = 0
        dest = self._destination()
        if dest is None or self._transport is None:
            return
        self.stats.datagrams += 1
        self._transport.sendto(data, dest)

    # ------------------------------------------------------------------- receiving
    def _datagram(self, data: bytes, addr: Address) -> None:
        messages = self.codec.decode(data)
        if not messages:
            return
        self.peer = addr
        self._peer_event.set()
        link_up = self._link_up()
        for msg in messages:
            self.stats.received += 1
            self.stats.received_by_type[msg.get_type()] += 1
            if msg.get_type() == "TIMESYNC" and msg.tc1 != 0:
                if self._lockstep_ts1 is not None and msg.ts1 == self._lockstep_ts1:
                    self._lockstep_ts1 = None
                    self._reply_event.set()
                continue
            if not link_up:
                self.stats.dropped_link_down += 1
                continue
            self._inbox.extend(self.incoming_faults.filter(msg, self.t_s))

    def _drain_inbox(self, now: float) -> None:
        while self._inbox:
            msg = self._inbox.popleft()
            try:
                self._handle(msg, now)
            except (ValueError, TypeError, AttributeError) as exc:
                log.warning("could not handle %s: %s", msg.get_type(), exc)

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.config.system_id) and tc in (0, self.config.component_id)

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "TIMESYNC":
            if msg.tc1 == 0:
                ns = round((now - self.autopilot.boot_s) * 1e9)
                self._send(self.codec.mav.timesync_encode(max(ns, 1), msg.ts1))
            return
        if not self._for_us(msg):
            return
        if kind == "SET_POSITION_TARGET_GLOBAL_INT":
            self.stats.decisions.append(self.autopilot.position_target(msg, now))
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(msg, now)
        elif kind == "SET_MODE":
            mode = self.personality.mode_for_custom(int(msg.custom_mode))
            if mode is None or not int(msg.base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                result = self.personality.result_refused
            else:
                result = self.autopilot.set_mode(mode, now, self.state)
            self._ack(msg, self.personality.set_mode_ack_command, result)
        elif kind.startswith("MISSION_") and kind != "MISSION_ACK":
            self.mission.handle(msg, now)
        elif kind == "REQUEST_DATA_STREAM" and self.personality.family == "ardupilot":
            hz = float(msg.req_message_rate) if msg.start_stop else 0.0
            for name in _DATA_STREAMS.get(int(msg.req_stream_id), ()):
                interval_us = 1e6 / hz if hz > 0 else -1
                self.scheduler.set_interval_us(STREAMED_MESSAGES[name], interval_us, now)

    def _ack(self, msg: Any, command: int, result: int) -> None:
        self._send(
            self.codec.mav.command_ack_encode(
                command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )
        )

    def _command(self, msg: Any, now: float) -> None:
        cmd = int(msg.command)
        p = [float(getattr(msg, f"param{i}")) for i in range(1, 5)]
        if msg.get_type() == "COMMAND_INT":
            p += [msg.x * 1e-7, msg.y * 1e-7, float(msg.z)]
            frame = int(msg.frame)
        else:
            p += [float(msg.param5), float(msg.param6), float(msg.param7)]
            frame = None
        self._ack(msg, cmd, self._command_result(cmd, p, frame, now))
        # Requested messages follow the ACK, as ArduPilot and PX4 send them.
        for reply in self._after_ack:
            self._send(reply)
        self._after_ack.clear()

    def _command_result(self, cmd: int, p: list[float], frame: int | None, now: float) -> int:
        """The COMMAND_ACK result of one command; p: param1..param7 (COMMAND_INT's x, y as
        degrees); frame: COMMAND_INT's frame, None for COMMAND_LONG."""
        handler = self._commands.get(cmd)
        if handler is None:
            return UNSUPPORTED
        return handler(p, frame, now)

    def _command_table(self) -> dict[int, _CommandHandler]:
        return {
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mavlink.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            mavlink.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mavlink.MAV_CMD_NAV_LAND: self._cmd_land,
            mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: self._cmd_return_to_launch,
            mavlink.MAV_CMD_DO_SET_HOME: self._cmd_set_home,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._cmd_request_capabilities,
            mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: self._cmd_reboot,
        }

    def _cmd_arm_disarm(self, p: list[float], frame: int | None, now: float) -> int:
        force = abs(p[1] - FORCE_MAGIC) < 0.5
        if p[0] > 0.5:
            return self.autopilot.arm(now, self.state, force)
        return self.autopilot.disarm(now, force)

    def _cmd_set_mode(self, p: list[float], frame: int | None, now: float) -> int:
        mode = self.personality.mode_from_command(p[0], p[1], p[2])
        if mode is None:
            return self.personality.result_refused
        return self.autopilot.set_mode(mode, now, self.state)

    def _cmd_takeoff(self, p: list[float], frame: int | None, now: float) -> int:
        # COMMAND_LONG: ArduPilot reads param7 above home, PX4 as AMSL; COMMAND_INT: frame.
        amsl = self.personality.family == "px4" if frame is None else frame in FRAMES_AMSL
        return self.autopilot.takeoff(p[6], amsl, now, self.state)

    def _cmd_land(self, p: list[float], frame: int | None, now: float) -> int:
        return self._to_mode(self.personality.land_mode, now)

    def _cmd_return_to_launch(self, p: list[float], frame: int | None, now: float) -> int:
        return self._to_mode(self.personality.rtl_mode, now)

    def _to_mode(self, name: str | None, now: float) -> int:
        if name is None:
            return UNSUPPORTED
        return self.autopilot.set_mode(self.personality.mode(name), now, self.state)

    def _cmd_set_home(self, p: list[float], frame: int | None, now: float) -> int:
        return self.autopilot.set_home(p[0] > 0.5, p[4], p[5], p[6], self.state)

    def _cmd_set_message_interval(self, p: list[float], frame: int | None, now: float) -> int:
        if self.scheduler.set_interval_us(int(p[0]), p[1], now):
            return ACCEPTED
        # ArduCopter SITL answers DENIED for a message it cannot stream (seen, id 60000)
        return FAILED if self.personality.family == "px4" else int(mavlink.MAV_RESULT_DENIED)

    def _cmd_get_message_interval(self, p: list[float], frame: int | None, now: float) -> int:
        msg_id = int(p[0])
        self._send(
            self.codec.mav.message_interval_encode(msg_id, self.scheduler.interval_us(msg_id))
        )
        return ACCEPTED

    def _cmd_request_message(self, p: list[float], frame: int | None, now: float) -> int:
        return self._request_message(int(p[0]))

    def _cmd_request_capabilities(self, p: list[float], frame: int | None, now: float) -> int:
        return self._request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)

    def _cmd_reboot(self, p: list[float], frame: int | None, now: float) -> int:
        if int(p[0]) != 1:
            return UNSUPPORTED
        if self.autopilot.armed:
            return self.personality.result_refused
        self._reboot_requested = True  # after this tick's messages, once acked
        return ACCEPTED

    def _request_message(self, msg_id: int) -> int:
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._after_ack.append(
                tm.autopilot_version_message(
                    self.codec.mav, self.personality, self.config.system_id
                )
            )
            return ACCEPTED
        if msg_id not in NAME_OF_ID:
            return FAILED
        self._send_telemetry(msg_id, self.snapshot(), self._after_ack.append)
        return ACCEPTED

    # -------------------------------------------------------------------- lockstep
    async def _lockstep_wait(self) -> None:
        self.stats.lockstep_waits += 1
        ts1 = round(self.t_s * 1e9)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.config.lockstep.timeout_s
        self._reply_event.clear()
        self._lockstep_ts1 = ts1
        try:
            while self._destination() is None and not self._closed:
                self._peer_event.clear()
                await asyncio.wait_for(self._peer_event.wait(), deadline - loop.time())
            data = self.codec.encode(self.codec.mav.timesync_encode(0, ts1))
            self._sendto(data)
            self._flush_batch()
            await asyncio.wait_for(self._reply_event.wait(), max(deadline - loop.time(), 0.0))
        except TimeoutError:
            self.stats.lockstep_stalls += 1
            log.info("lockstep: no answer for t=%.3f s, carrying on", self.t_s)
        finally:
            self._lockstep_ts1 = None
