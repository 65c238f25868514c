"""The companion service over UDP loopback against companion/sim/'s MAVLink simulator.

Three measurements, each the real service (`companion.service.Service`) talking MAVLink 2
to the real simulator (`companion.sim.mavlink`) in another process, flying the paper scenario
with its
11 range sensors (auto start, ArduPilot personality, flight log on):

- real time: the simulator at 1x streams ATTITUDE, GLOBAL_POSITION_INT and the 11
  DISTANCE_SENSOR at 50 Hz, the service loops at 50 Hz in this process. The service's link
  is a `UdpOutLink` that notes when each datagram is handed to the service and when each
  setpoint leaves (`TimedLink`, injected like any link: the service is not patched).
  Latency = setpoint send - arrival of the newest datagram before it (also per input
  type); how long before the burst's last DISTANCE_SENSOR the newest GLOBAL_POSITION_INT
  came (the simulator's stream phases against ArduCopter SITL's); jitter = |interval
  between setpoints - 20 ms|; CPU = this process's CPU time / wall time while flying. The
  service is pinned to one core and the simulator to another where the machine has two
  (`os.sched_setaffinity`, as `taskset` would), as on a companion computer's single core; a
  Raspberry Pi 4 runs pure Python about 10x slower than this class of x86-64 core, so the
  figure x 10 is the Pi estimate printed beside it.
- the floor: what pymavlink alone costs per cycle (parse the 13 inputs, pack a setpoint;
  the median of blocks measured before and after the real-time run), and the service's CPU
  per cycle as a multiple of it.
- where a cycle's CPU goes: the service's own parts in process (codec, telemetry, pairing,
  geodesy, flight log) on the inputs as the simulator sends them, the planner's step as
  flown in the real-time run (thread CPU around each step, through the service's
  `planner_factory`), and the rest: the service's CPU per cycle less all of those (event
  loop, sockets, dispatch, the cycle's bookkeeping, and the parts' cost in a live process
  against a warm loop). Live, the same run also splits the CPU per cycle three ways:
  receiving (thread CPU around each wake-up of the service's socket: recv and the receive
  callback, through `TimedLink`), the planner's step, and all else.
- lockstep: the simulator in this process, lockstep and as fast as possible; the service as
  `companion run` in a child process (sim time). Simulated s per wall s while flying the
  route, and the service's resident memory after 1 simulated minute and after 1 hour.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.flight import SCENARIO_DIR
from bench.report import REPO, Section, percentiles_us
from companion.config import parse_config
from companion.harness.fly import service_config
from companion.service import Service
from companion.service.host import PlannerLike, default_planner_factory
from companion.service.link import Receiver, UdpOutLink
from companion.service.notify import SystemdNotifier
from companion.sim.mavlink import SimServer
from companion.sim.scenario import Scenario, load_scenario

PAPER = SCENARIO_DIR / "paper.yaml"
RATE_HZ = 50.0
SETPOINT_MSGID = mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT
INPUT_TYPES = {
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: "DISTANCE_SENSOR",
    mavlink.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "GLOBAL_POSITION_INT",
}
"""The inputs a cycle uses, by message id (latency is measured per type)."""


def _msgid(frame: bytes) -> int | None:
    """Message id of a MAVLink frame (v2 or v1), None if it is not one."""
    if len(frame) >= 10 and frame[0] == 0xFD:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    if len(frame) >= 6 and frame[0] == 0xFE:
        return frame[5]
    return None


class TimedLink(UdpOutLink):
    """A `UdpOutLink` that notes when each datagram reaches the service and when each
    setpoint is sent (perf_counter seconds), and the thread CPU time the service spends
    receiving (`rx_cpu_ns`: each wake-up of the socket, every datagram it reads: recv,
    decode, dispatch, telemetry). The CPU clock is read twice a wake-up, not twice a
    datagram: a read costs a system call (about 1 us), which a per-datagram reading would
    add 13 times a cycle to the CPU it measures."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(host, port)
        self.last_rx: float | None = None
        self.setpoints: list[tuple[float, float | None]] = []
        """(send time, arrival time of the newest datagram before it)."""
        self.by_type: dict[str, list[float]] = {name: [] for name in INPUT_TYPES.values()}
        """Per input type: setpoint send time - arrival of the newest datagram of that type,
        for the setpoints that followed one (s)."""
        self._pending: dict[int, float] = {}
        self._newest: dict[int, float] = {}
        self.position_lead: list[float] = []
        """Per setpoint: arrival of the newest DISTANCE_SENSOR - arrival of the newest
        GLOBAL_POSITION_INT before it (s): how long before its burst's end the position
        came (ArduCopter SITL: 0.25 ms median, 6.1 ms p99)."""
        self.rx_cpu_ns = 0

    async def open(self, receiver: Receiver) -> None:
        def timed(data: bytes, peer: Any) -> None:
            self.last_rx = now = time.perf_counter()
            msgid = _msgid(data)
            if msgid is not None and msgid in INPUT_TYPES:
                self._pending[msgid] = now
                self._newest[msgid] = now
            receiver(data, peer)

        await super().open(timed)

    def _readable(self) -> None:
        t0 = time.thread_time_ns()
        super()._readable()
        self.rx_cpu_ns += time.thread_time_ns() - t0

    def send(self, data: bytes) -> None:
        if _msgid(data) == SETPOINT_MSGID:
            now = time.perf_counter()
            self.setpoints.append((now, self.last_rx))
            for msgid, t_rx in self._pending.items():
                self.by_type[INPUT_TYPES[msgid]].append(now - t_rx)
            if mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR in self._pending:
                t_ds = self._newest[mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR]
                t_pos = self._newest.get(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
                if t_pos is not None:
                    self.position_lead.append(t_ds - t_pos)
            self._pending.clear()
        super().send(data)


class TimedPlanner:
    """The service's planner, with the thread CPU time of each step added up (ns)."""

    def __init__(self, planner: PlannerLike, totals: dict[str, int]) -> None:
        self._planner = planner
        self._totals = totals

    def step(self, state: Any, ranges_m: Any, dt_s: float) -> Any:
        t0 = time.thread_time_ns()
        try:
            return self._planner.step(state, ranges_m, dt_s)
        finally:
            self._totals["step_ns"] += time.thread_time_ns() - t0
            self._totals["steps"] += 1

    def set_desired_height(self, h_d_m: float) -> None:
        self._planner.set_desired_height(h_d_m)


PI4_SLOWDOWN = 10.0
"""A Raspberry Pi 4 (Cortex-A72, 1.5-1.8 GHz) against one x86-64 core of this class, for pure
Python: an estimate, not a measurement."""


def _cores() -> list[int]:
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []


@contextlib.contextmanager
def _pinned(core: int | None) -> Iterator[None]:
    """This process on one core for the duration (no-op where affinity is unsupported)."""
    if core is None or not hasattr(os, "sched_setaffinity"):
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {core})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(scenario: Scenario, port: int, log_dir: Path, **control: Any) -> dict[str, Any]:
    """`companion fly`'s service configuration for the scenario, as a plain mapping, with
    `control:` keys replaced. Home is where the simulator starts the vehicle."""
    start = scenario.start_position or (*scenario.route.points[0], 0.0)
    cfg = service_config(scenario, port, np.array(start[:2], dtype=float), log_dir)
    doc: dict[str, Any] = cfg.model_dump(mode="json")
    doc["control"].update(control)
    return doc


def pymavlink_floor(cycles: int = 2000, blocks: int = 5) -> dict[str, Any]:
    """Microseconds per cycle for pymavlink to parse one cycle's inputs (11 DISTANCE_SENSOR,
    ATTITUDE, GLOBAL_POSITION_INT) and pack one SET_POSITION_TARGET_GLOBAL_INT: the median
    over `blocks` blocks of the cycles (`blocks_us`), so a burst of load from elsewhere on
    the machine during one block does not move the floor."""
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    tx.robust_parsing = True
    frames = [
        tx.distance_sensor_encode(1000, 10, 1200, 350, 0, i, 0, 0).pack(tx) for i in range(11)
    ]
    frames.append(tx.attitude_encode(1000, 0.01, -0.02, 1.5, 0.0, 0.0, 0.0).pack(tx))
    frames.append(
        tx.global_position_int_encode(1000, 473977420, 85455940, 50000, 2000, 10, 0, 0, 9000).pack(
            tx
        )
    )
    rx = mavlink.MAVLink(None, srcSystem=2, srcComponent=191)
    out = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    parsed = 0
    per_block = max(cycles // blocks, 1)
    blocks_us = []
    for b in range(blocks):
        t0 = time.perf_counter_ns()
        for k in range(b * per_block, (b + 1) * per_block):
            for f in frames:
                msgs = rx.parse_buffer(f)
                parsed += len(msgs) if msgs else 0
            out.set_position_target_global_int_encode(
                k, 1, 1, 6, 0x9C0, 473977420, 85455940, 2.0, 0.5, 0.1, 0.0, 0.0, 0.0, 0.0, 1.5, 0.0
            ).pack(out)
        blocks_us.append((time.perf_counter_ns() - t0) / per_block / 1e3)
    if parsed != blocks * per_block * len(frames):
        raise RuntimeError(f"parsed {parsed} messages, expected {blocks * per_block * len(frames)}")
    return {
        "per_cycle_us": float(np.median(blocks_us)),
        "blocks_us": blocks_us,
        "messages_per_cycle": len(frames) + 1,
    }


def service_parts(cycles: int = 2000) -> dict[str, float]:
    """Microseconds per cycle of the service's own work on one cycle's inputs, in process,
    part by part (the planner's step is measured in the real-time run): the codec (the
    service's `MavCodec` decoding the 13 frames and encoding a setpoint), telemetry
    validation of the 13 messages, pairing the ranges with the attitude of their time, the
    geodesy of a cycle (position to ENU, setpoint to geodetic) and the flight-log record's
    encoding. The frames are the simulator's: custom orientations with their quaternion,
    half the readings "nothing", the configured median filter."""
    from companion.geo import GeoPoint, LocalFrame
    from companion.planner.sensors import (
        MAV_SENSOR_ROTATION_CUSTOM,
        mav_orientation_for_boresight,
        quaternion_from_boresight_frd,
    )
    from companion.service.codec import MavCodec
    from companion.service.flightlog import dumps_record, floats
    from companion.service.setpoints import SetpointFrame, position_target
    from companion.service.telemetry import Telemetry

    scenario = load_scenario(PAPER)
    cfg = service_config(scenario, 14540, np.zeros(2), Path("."))
    table = cfg.sensor_table()
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    # each sensor as the simulator sends it: its orientation, the quaternion of a custom one,
    # its limits in cm; every other sensor sees nothing (ArduPilot: max + 1 m), the others
    # a distance that drifts as in flight
    wire = []
    for spec in table.specs:
        orientation = mav_orientation_for_boresight(spec.boresight_frd)
        q = [0.0] * 4
        if orientation == MAV_SENSOR_ROTATION_CUSTOM:
            q = [float(v) for v in quaternion_from_boresight_frd(spec.boresight_frd)]
        lo, hi = round(spec.min_range_m * 100), round(spec.max_range_m * 100)
        wire.append((spec.sensor_id, orientation, q, lo, hi))

    def frames(k: int) -> list[bytes]:
        tb = 1000 + 20 * k
        out = []
        for i, (sid, orientation, q, lo, hi) in enumerate(wire):
            drift = 0.5 + 0.4 * math.sin(0.02 * k + i)
            cm = hi + 100 if i % 2 == 0 else int(lo + (hi - lo) * drift)
            out.append(
                tx.distance_sensor_encode(
                    tb, lo, hi, cm, 0, sid, orientation, 0, 0.0, 0.0, q, 0
                ).pack(tx)
            )
        out.append(tx.attitude_encode(tb, 0.01, -0.02, 1.5, 0.0, 0.0, 0.0).pack(tx))
        lat = 473977420 + k
        out.append(
            tx.global_position_int_encode(tb, lat, 85455940, 50000, 2000, 10, 0, 0, 0).pack(tx)
        )
        return out

    inputs = [frames(k) for k in range(cycles)]
    codec = MavCodec()
    tel = Telemetry(table, median_samples=cfg.failsafe.range_median_samples)
    plane = LocalFrame(GeoPoint(47.397742, 8.545594, 488.0))
    rng = np.random.default_rng(0)
    obstacles = len(table.obstacle_index)
    pos_enu, sp_p, sp_v = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    phi_star, threshold = rng.normal(size=obstacles), rng.uniform(size=obstacles)
    t = {"codec": 0, "telemetry": 0, "pairing": 0, "geodesy": 0, "flight_log": 0}
    accepted = 0
    for k, fs in enumerate(inputs):
        t_rx = 1.0 + 0.02 * k
        t0 = time.perf_counter_ns()
        msgs = [m for f in fs for m in codec.decode(f)]
        t1 = time.perf_counter_ns()
        accepted += sum(tel.update(m, t_rx) is not None for m in msgs)
        t2 = time.perf_counter_ns()
        tel.paired_ranges(t_rx, 0.5)
        t2p = time.perf_counter_ns()
        pos = tel.position
        assert pos is not None
        plane.to_enu(GeoPoint(pos.lat_deg, pos.lon_deg, pos.alt_amsl_m))
        sp = position_target(
            np.array([1.0, 2.0, 3.0]), np.array([0.5, 0.0, 0.1]), 0.3, frame=plane,
            mav_frame=SetpointFrame.GLOBAL_RELATIVE_ALT, home_alt_amsl_m=488.0,
            time_boot_ms=k, target_system=1, target_component=1,
        )  # fmt: skip
        t3 = time.perf_counter_ns()
        codec.encode(sp)
        t4 = time.perf_counter_ns()
        # the cycle's record as `ControlCycle` builds it (arrays through `floats`), encoded
        record = {
            "type": "cycle", "t": t_rx, "health": "active", "own": "engaged", "verdict": "run",
            "reason": "", "pos": floats(pos_enu), "rpy": [0.01, -0.02, 1.5],
            "ranges": floats(tel.range_vector(t_rx, 0.5)),
            "sp": {"p": floats(sp_p), "v": floats(sp_v), "yaw": 1.5, "pitch": 0.1},
            "sp_kind": "planner", "decision": "follow", "mode": "nominal", "side": "none",
            "min_range": 3.5, "phi_star": floats(phi_star),
            "phi_star_threshold": floats(threshold), "phi_d": 0.1, "v_ref": 1.0,
            "replanned": False, "finished": False, "events": [],
        }  # fmt: skip
        dumps_record(record)
        t5 = time.perf_counter_ns()
        t["codec"] += (t1 - t0) + (t4 - t3)
        t["telemetry"] += t2 - t1
        t["pairing"] += t2p - t2
        t["geodesy"] += t3 - t2p
        t["flight_log"] += t5 - t4
    if accepted != cycles * 13:
        raise RuntimeError(f"telemetry accepted {accepted} of {cycles * 13} messages")
    return {k: v / cycles / 1e3 for k, v in t.items()}


async def _wait(pred: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


async def realtime(seconds: float) -> dict[str, Any]:
    """The service at 50 Hz against the simulator at 1x, measured for `seconds` while the
    planner flies."""
    scenario = load_scenario(PAPER)
    port = _free_udp_port()
    serve = ["serve", str(PAPER), "--port", str(port), "--speedup", "1", "--prearm-delay", "0.5"]
    cores = _cores()
    service_core = cores[0] if len(cores) >= 2 else None
    sim = subprocess.Popen(
        [sys.executable, "-m", "companion.sim", *serve],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    if service_core is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(sim.pid, set(cores[1:]))
    try:
        with _pinned(service_core), tempfile.TemporaryDirectory(prefix="bench-service-") as tmp:
            doc = _config(scenario, port, Path(tmp), time_source="monotonic", rate_hz=RATE_HZ)
            link = TimedLink("127.0.0.1", port)
            planner_cpu = {"step_ns": 0, "steps": 0}

            def timed_planner(*args: Any) -> PlannerLike:
                return TimedPlanner(default_planner_factory(*args), planner_cpu)

            svc = Service(
                parse_config(doc),
                link,
                planner_factory=timed_planner,
                notifier=SystemdNotifier({}),
            )
            task = asyncio.create_task(svc.run())
            try:
                await _wait(lambda: svc.counters["planner_starts"] >= 1, 90.0, "the planner")
                await asyncio.sleep(1.0)
                link.setpoints.clear()
                for samples in link.by_type.values():
                    samples.clear()
                link.position_lead.clear()
                cycles0 = svc.counters["cycles"]
                step0, steps0 = planner_cpu["step_ns"], planner_cpu["steps"]
                rx0 = link.rx_cpu_ns
                cpu0, wall0 = time.process_time(), time.perf_counter()
                await asyncio.sleep(seconds)
                cpu1, wall1 = time.process_time(), time.perf_counter()
                cycles = svc.counters["cycles"] - cycles0
                step_ns = planner_cpu["step_ns"] - step0
                steps = planner_cpu["steps"] - steps0
                rx_ns = link.rx_cpu_ns - rx0
                setpoints = list(link.setpoints)
                by_type = {k: [int(v * 1e9) for v in vs] for k, vs in link.by_type.items()}
                lead_ns = [int(v * 1e9) for v in link.position_lead]
                counters = svc.counter_values()
            finally:
                svc.stop()
                await asyncio.wait_for(task, 10.0)
    finally:
        sim.terminate()
        sim.wait(10)
    sends = np.array([t for t, _ in setpoints])
    latency_ns = [int((t - rx) * 1e9) for t, rx in setpoints if rx is not None]
    jitter_ns = np.abs(np.diff(sends) - 1.0 / RATE_HZ) * 1e9
    cpu_s = cpu1 - cpu0
    return {
        "seconds": wall1 - wall0,
        "cycles": cycles,
        "setpoints": len(setpoints),
        "latency_us": percentiles_us(latency_ns),
        "latency_by_type_us": {k: percentiles_us(v) for k, v in by_type.items()},
        "position_lead_us": percentiles_us(lead_ns),
        "jitter_us": percentiles_us(jitter_ns),
        "cpu_percent": 100.0 * cpu_s / (wall1 - wall0),
        "cpu_per_cycle_us": 1e6 * cpu_s / max(cycles, 1),
        "planner_steps": steps,
        "planner_step_per_cycle_us": step_ns / 1e3 / max(cycles, 1),
        "receive_per_cycle_us": rx_ns / 1e3 / max(cycles, 1),
        "pinned_core": service_core,
        "cycle_overruns": counters.get("service.cycle_overruns", 0),
        "cycles_by_input": counters.get("service.cycles_by_input", 0),
        "cycles_by_timer": counters.get("service.cycles_by_timer", 0),
        "planner_errors": counters.get("service.planner_errors", 0),
    }


def _rss_mb(pid: int) -> float:
    """Resident set size of a process (Linux /proc), MB; NaN where unavailable."""
    try:
        with open(f"/proc/{pid}/status", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


async def lockstep(hour_s: float, flight_s: tuple[float, float] = (20.0, 120.0)) -> dict[str, Any]:
    """The simulator here (lockstep, as fast as possible), the service as `companion run` in
    a child process. Speed over the flight's sim-time window flight_s; RSS at 60 s and at
    hour_s of simulated time."""
    scenario = load_scenario(PAPER)
    server = SimServer.from_scenario(
        scenario,
        SCENARIO_DIR,
        port=0,
        speedup=math.inf,
        lockstep={"enabled": True, "period_s": scenario.dt_s},
        prearm_delay_s=0.5,
    )
    await server.start()
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench-lockstep-") as tmp:
        home = server.autopilot.home_enu
        cfg = service_config(scenario, server.port, np.array(home[:2], dtype=float), Path(tmp))
        cfg_path = Path(tmp) / "service.yaml"
        cfg_path.write_text(yaml.safe_dump(cfg.model_dump(mode="json")), encoding="utf-8")
        proc = subprocess.Popen(
            [sys.executable, "-m", "companion.cli", "run", "--config", str(cfg_path)],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            await server.run_until(flight_s[0])
            t0 = time.perf_counter()
            await server.run_until(flight_s[1])
            out["flight_speed_x"] = (flight_s[1] - flight_s[0]) / (time.perf_counter() - t0)
            await server.run_until(60.0)
            out["rss_1min_mb"] = _rss_mb(proc.pid)
            t0 = time.perf_counter()
            await server.run_until(hour_s)
            out["hold_speed_x"] = (hour_s - 60.0) / (time.perf_counter() - t0)
            out["rss_end_mb"] = _rss_mb(proc.pid)
            out["sim_s"] = hour_s
            out["lockstep_stalls"] = server.stats.lockstep_stalls
            truth = server.truth
            goal = np.array(scenario.route.points[-1], dtype=float)
            out["final_distance_to_goal_m"] = float(
                np.hypot(*(np.asarray(truth[-1].position_enu[:2]) - goal))
            )
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
            await server.close()
    return out


PART_LABELS = (
    ("codec", "the service's codec: decode 13 frames + encode 1"),
    ("telemetry", "telemetry validation of 13 messages"),
    ("pairing", "ranges paired with the attitude of their time"),
    ("geodesy", "geodesy of a cycle (position -> ENU, setpoint -> lat/lon)"),
    ("flight_log", "flight-log record, built and encoded"),
)
"""The in-process parts of `service_parts`, in table order."""


def rest_us(cpu_per_cycle_us: float, parts: dict[str, float], planner_us: float) -> float:
    """The service's CPU per cycle not in a measured part: what the event loop, the sockets,
    the dispatch of messages and the cycle's own bookkeeping cost, plus what the parts cost
    more in the live process than in a warm loop."""
    return cpu_per_cycle_us - planner_us - sum(parts[name] for name, _ in PART_LABELS)


def run(quick: bool = False) -> Section:
    sec = Section("service over UDP")
    before = pymavlink_floor(500 if quick else 2000)
    parts = service_parts(500 if quick else 2000)
    rt = asyncio.run(realtime(8.0 if quick else 30.0))
    # the floor on both sides of the real-time run, as the median of all its blocks
    after = pymavlink_floor(500 if quick else 2000)
    blocks = before["blocks_us"] + after["blocks_us"]
    floor = {**before, "per_cycle_us": float(np.median(blocks)), "blocks_us": blocks}
    ls = asyncio.run(lockstep(600.0 if quick else 3600.0))
    sec.details.update(
        {"pymavlink_floor": floor, "service_parts": parts, "realtime": rt, "lockstep": ls}
    )
    lat, jit = rt["latency_us"], rt["jitter_us"]
    sec.add(
        "service.latency.median_us",
        f"input -> setpoint latency, 50 Hz loop, median (n={lat.get('n', 0)})",
        lat.get("median", math.nan),
        "us",
    )
    sec.add(
        "service.latency.p99_us",
        "input -> setpoint latency, p99",
        lat.get("p99", math.nan),
        "us",
        ("<=", 1000),
    )
    for name, lt in rt["latency_by_type_us"].items():
        sec.add(
            f"service.latency.{name.lower()}.p99_us",
            f"newest {name} -> setpoint latency, p99 (n={lt.get('n', 0)})",
            lt.get("p99", math.nan),
            "us",
        )
    lead = rt["position_lead_us"]
    sec.add(
        "service.position_lead.median_us",
        "GLOBAL_POSITION_INT before the burst's last DISTANCE_SENSOR, median "
        f"(n={lead.get('n', 0)})",
        lead.get("median", math.nan),
        "us",
    )
    sec.add(
        "service.position_lead.p99_us",
        "same, p99 (ArduCopter SITL: 250 us median, 6,100 us p99)",
        lead.get("p99", math.nan),
        "us",
    )
    sec.add(
        "service.jitter.p99_us",
        "loop jitter (|interval - 20 ms|), p99",
        jit.get("p99", math.nan),
        "us",
    )
    pinned = "pinned to one core" if rt["pinned_core"] is not None else "not pinned"
    sec.add(
        "service.cpu_percent",
        f"service CPU at 50 Hz, 11 sensors, % of one core ({pinned})",
        rt["cpu_percent"],
        "%",
        ("<=", 10),
    )
    sec.add(
        "service.pi4_cpu_percent_estimate",
        f"estimate for a Raspberry Pi 4 core (x {PI4_SLOWDOWN:g}, not measured)",
        rt["cpu_percent"] * PI4_SLOWDOWN,
        "%",
    )
    sec.add("service.cpu_per_cycle_us", "service CPU per cycle", rt["cpu_per_cycle_us"], "us")
    sec.add(
        "service.floor_us",
        "pymavlink parse (13 msgs) + pack (1) per cycle",
        floor["per_cycle_us"],
        "us",
    )
    for part, label in PART_LABELS:
        sec.add(f"service.part.{part}_us", f"per cycle, in process: {label}", parts[part], "us")
    cpu_us, planner_us, rx_us = (
        rt["cpu_per_cycle_us"],
        rt["planner_step_per_cycle_us"],
        rt["receive_per_cycle_us"],
    )
    sec.add(
        "service.part.planner_us",
        f"per cycle, live: the planner's step ({rt['planner_steps']} steps)",
        planner_us,
        "us",
    )
    sec.add(
        "service.part.rest_us",
        "per cycle: service CPU less the in-process parts and the planner",
        rest_us(cpu_us, parts, planner_us),
        "us",
    )
    sec.add(
        "service.live.receive_us",
        "per cycle, live: receiving 13 datagrams (recv, decode, dispatch, telemetry)",
        rx_us,
        "us",
    )
    sec.add(
        "service.live.cycle_rest_us",
        "per cycle, live: all else (cycle, setpoint, flight log, event loop, send)",
        cpu_us - rx_us - planner_us,
        "us",
    )
    sec.add(
        "service.floor_ratio",
        "service CPU per cycle / pymavlink floor",
        rt["cpu_per_cycle_us"] / floor["per_cycle_us"],
        "x",
        ("<=", 3),
    )
    sec.add(
        "sim.udp_lockstep.speed_x",
        "simulator + service over UDP, lockstep, flying",
        ls["flight_speed_x"],
        "x real time",
        (">=", 50),
    )
    sec.add(
        "sim.udp_lockstep.hold_speed_x",
        "same, holding at the goal",
        ls["hold_speed_x"],
        "x real time",
    )
    growth = ls["rss_end_mb"] - ls["rss_1min_mb"]
    sec.add(
        "service.rss_growth_mb",
        f"service RSS growth, 1 min -> {ls['sim_s'] / 60:.0f} min simulated",
        growth,
        "MB",
        ("<=", 5),
    )
    sec.add("service.rss_mb", "service RSS after 1 min", ls["rss_1min_mb"], "MB")
    return sec


if __name__ == "__main__":  # a smoke run of this benchmark alone
    from bench.report import table

    print(table([run(quick="--quick" in sys.argv)]))
