"""A scenario flown by the companion service against a real autopilot's SITL.

Three parts, all on 127.0.0.1:
- the SITL, started here in its own process group. ArduCopter (`Sitl`,
  `../shared/sitl/arducopter-sitl`): its MAVLink stream (serial0) goes to the companion's UDP
  port; serial1 (TCP 5762 + 10 I) is left to a ground station; the sensor bridge uses
  serial2 (TCP 5763 + 10 I). PX4 with SIH physics (`Px4Sitl`, `../shared/sitl/px4/`): its
  onboard link sends to UDP 14540 + I, where the companion listens; the bridge gets a MAVLink
  instance of its own, started once PX4 runs;
- the sensor bridge (`companion.sim.mavlink.bridge`), ray-casting the scenario's world at the pose
  SITL reports. Topology `companion`: it sends DISTANCE_SENSOR straight to the companion as
  ArduPilot would. Topology `autopilot`: it feeds SITL's MAVLink rangefinders (RNGFNDn_TYPE
  10) and proximity sensor (PRX1_TYPE 2), and the companion reads what SITL re-publishes;
- the service (`companion.service.Service`, monotonic clock, auto start).

Frames: SITL's home sits at world (start x, y, the lowest terrain height near the route:
`home_height`), so world ENU = that point + ENU offset from home; the route points handed to
the service are relative to home. SITL's own ground is flat at home altitude, below all the
relief the route flies over (a home at the start's height put SITL's ground above any
descent, and the vehicle sat on it); the world's relief and obstacles exist in the sensors
only. The take-off climbs from that ground to the start's height (through the virtual
ground where the start lies higher) before the planner takes over. The truth used for the
metrics is the pose SITL reports (GLOBAL_POSITION_INT and ATTITUDE, as received by the
bridge), so the figures say how the real autopilot flew.

Time: the service runs on the wall clock, so a flight takes its route length / v_d in wall
seconds whatever SITL's speed-up; see docs/simulator.md for why flights use speed-up 1.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Self, TextIO

import numpy as np
import yaml
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.config import parse_config
from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import RunResult
from companion.harness.fly import trace_from_log
from companion.planner.sensors import (
    MAV_SENSOR_ROTATION_CUSTOM,
    SensorSpec,
    mav_orientation_for_boresight,
)
from companion.service import Service
from companion.service.flightlog import read_flight_log
from companion.service.link import UdpInLink
from companion.service.notify import SystemdNotifier
from companion.sim.mavlink.bridge import SensorBridge
from companion.sim.mavlink.config import BridgeConfig
from companion.sim.scenario import Scenario, load_scenario
from companion.sim.world import World

Topology = Literal["companion", "autopilot"]

SITL_DIR = Path("..") / "shared" / "sitl"
"""Where the SITL lies, relative to the repository root."""

PROXIMITY_ID_BASE = 10
"""ArduPilot re-reports proximity sector k (orientation YAW_45 * k) as DISTANCE_SENSOR id 10+k."""
MAX_RANGEFINDERS = 10
CMAC = (-35.363261, 149.165230, 584.0)
"""The launcher's default home (lat, lon deg, alt m AMSL)."""
GOAL_RADIUS_M = 0.5
SETTLE_AFTER_FINISH_S = 5.0
"""After the route is done the vehicle holds at the goal; the flight goes on this long so
that `reached_goal` is judged on where SITL's vehicle got to, not on its lag at the last
planner cycle. PX4 takes longer (`Px4Sitl.settle_after_finish_s`)."""


def repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def find_sitl(root: Path | None = None) -> Path | None:
    """The launcher `../shared/sitl/arducopter-sitl` when it and the binary exist, else None."""
    base = (root or repo_root()) / SITL_DIR
    launcher = base / "arducopter-sitl"
    if launcher.is_file() and (base / "arducopter").is_file():
        return launcher.resolve()
    return None


PX4_DIR = SITL_DIR / "px4"
"""The PX4 SITL bundle (SIH physics), relative to the repository root."""
PX4_HOME = (47.397742, 8.545594, 489.4)
"""SIH's default home (lat, lon deg, alt m AMSL)."""
PX4_MAX_INSTANCE = 9
"""PX4 sends to 14540 + I only up to I = 9 (14549 for every instance above)."""


def find_px4(root: Path | None = None) -> Path | None:
    """The PX4 bundle `../shared/sitl/px4/` when its launcher and binary exist, else None."""
    base = (root or repo_root()) / PX4_DIR
    if (base / "px4-sitl").is_file() and (base / "bin" / "px4").is_file():
        return base.resolve()
    return None


def runnable_px4_bundle(src: Path, dest: Path) -> Path:
    """A copy of the PX4 bundle at `dest` (made once) whose module clients run.

    PX4's rcS calls `px4-param`, `px4-mavlink`, ... which are symlinks to `bin/px4`; a copy
    of the bundle that lost its links (an archive unpacked without them: 3-byte files
    reading "px4") fails every one of those calls with "Permission denied" and PX4 never
    gets its airframe. Such files become links again here; the original is left as it is.
    """
    if not (dest / "bin" / "px4").is_file():
        tmp = dest.with_name(dest.name + ".part")
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(src, tmp, symlinks=True)
        for path in (tmp / "bin").glob("px4-*"):
            flattened = not path.is_symlink() and path.stat().st_size <= 8
            if flattened and path.read_bytes().strip() == b"px4":
                path.unlink()
                path.symlink_to("px4")
        for path in tmp.rglob("*"):  # the original may be read-only
            if not path.is_symlink():
                path.chmod(path.stat().st_mode | 0o200)
        tmp.rename(dest)
    return dest


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def goal_distance(track: np.ndarray, goal_xy: np.ndarray, since: float) -> float | None:
    """Closest horizontal distance (m) to the goal of SITL's positions (track rows t, x, y,
    ...) at or after `since` (monotonic s, when the route was seen done); None without one.

    Not "after the planner's last row": the planner writes a row for each position the
    service gets (20 Hz) while it holds at the goal, the bridge records SITL's position at
    10 Hz, so whether one came after the very last row was a coin toss at stop (wired wall:
    goal_distance_m nan in 13 of 20 flights that all ended 2.7 mm from the goal)."""
    after = track[track[:, 0] >= since] if len(track) else track
    if len(after) == 0:
        return None
    return float(np.hypot(after[:, 1] - goal_xy[0], after[:, 2] - goal_xy[1]).min())


class SitlError(RuntimeError):
    """SITL did not start or answer."""


class _SitlProcess:
    """What both SITLs share: a launcher run in its own process group, its console in
    workdir/sitl.out, and the UDP port the companion listens on (`port`)."""

    label = "SITL"
    settle_after_finish_s = SETTLE_AFTER_FINISH_S
    port: int
    workdir: Path | None
    proc: subprocess.Popen[bytes] | None
    started_at: float
    _log: TextIO | None

    def _spawn(self, cmd: list[str]) -> None:
        assert self.workdir is not None
        self._log = (self.workdir / "sitl.out").open("w", encoding="utf-8")
        self.proc = subprocess.Popen(
            cmd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # its own process group, killed as a whole
        )
        self.started_at = time.monotonic()

    def stop(self) -> None:
        """SIGTERM to the process group, SIGKILL after 5 s; idempotent."""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5.0)
        if self._log is not None:
            self._log.close()
            self._log = None

    def output(self) -> str:
        if self.workdir is None or not (self.workdir / "sitl.out").exists():
            return ""
        return (self.workdir / "sitl.out").read_text(encoding="utf-8", errors="replace")

    def wait_heartbeat(self, timeout_s: float = 60.0) -> float:
        """Block until a HEARTBEAT of the autopilot (component 1) arrives on `port`;
        seconds since start. Binds the port for the wait only: the companion takes it
        afterwards.
        """
        mav = mavlink.MAVLink(None)
        mav.robust_parsing = True
        deadline = time.monotonic() + timeout_s
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", self.port))
            s.settimeout(0.5)
            while time.monotonic() < deadline:
                if self.proc is not None and self.proc.poll() is not None:
                    raise SitlError(
                        f"{self.label} exited ({self.proc.returncode}): {self.output()[-400:]}"
                    )
                try:
                    data = s.recv(65536)
                except TimeoutError:
                    panic = [ln for ln in self.output().splitlines() if "PANIC" in ln]
                    if panic:  # SITL stops there without exiting
                        raise SitlError(f"{self.label} failed to start: {panic[0]}") from None
                    continue
                for msg in mav.parse_buffer(data) or []:
                    if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                        return time.monotonic() - self.started_at
        raise SitlError(
            f"no {self.label} heartbeat on udp 127.0.0.1:{self.port} in {timeout_s:.0f} s"
        )

    @property
    def system_id(self) -> int:
        """The autopilot's MAVLink system id."""
        return 1

    def bridge_link(self) -> str:
        """The pymavlink connection string the sensor bridge reaches the autopilot with."""
        raise NotImplementedError

    def detached(self) -> _SitlProcess:
        """A copy without the process handle, to hand to another process (picklable)."""
        return dataclasses.replace(self, proc=None, _log=None)  # type: ignore[type-var]

    def __enter__(self) -> Self:
        self.start()
        return self

    def start(self) -> None:
        raise NotImplementedError

    def __exit__(self, *exc: object) -> None:
        self.stop()


@dataclass
class Sitl(_SitlProcess):
    """One ArduCopter SITL process (its own process group; stop() kills the group).

    instance: SITL's -I (serial1 TCP 5762 + 10 I, serial2 5763 + 10 I); give every SITL
    running at once its own. port: the UDP port its MAVLink stream (serial0) is sent to.
    params: extra parameters (name -> value) loaded at boot with the default ones.
    """

    launcher: Path
    instance: int
    port: int
    speedup: float = 1.0
    fast_ekf: bool = True
    params: dict[str, float] = field(default_factory=dict)
    workdir: Path | None = None
    heading_deg: float | None = None
    """Initial heading, degrees clockwise from north (the launcher's default home, CMAC)."""
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    _log: TextIO | None = None
    label = "ArduCopter SITL"

    @property
    def gcs_port(self) -> int:
        """TCP port of SERIAL1 (a ground station)."""
        return 5762 + 10 * self.instance

    @property
    def bridge_port(self) -> int:
        """TCP port of SERIAL2 (the sensor bridge)."""
        return 5763 + 10 * self.instance

    def bridge_link(self) -> str:
        return f"tcp:127.0.0.1:{self.bridge_port}"

    def command(self) -> list[str]:
        cmd = [
            str(self.launcher),
            "--instance",
            str(self.instance),
            "--port",
            str(self.port),
            "--speedup",
            f"{self.speedup:g}",
        ]
        if self.workdir is not None:
            cmd += ["--workdir", str(self.workdir)]
        if self.heading_deg is not None:
            cmd += ["--home", f"{CMAC[0]},{CMAC[1]},{CMAC[2]},{self.heading_deg:g}"]
        if self.fast_ekf:
            cmd.append("--fast-ekf")
        for name, value in self.params.items():
            cmd += ["--param", f"{name}={value:g}"]
        return cmd

    def start(self) -> None:
        if self.workdir is None:
            self.workdir = Path(tempfile.mkdtemp(prefix=f"sitl-{self.instance}-"))
        self.workdir = self.workdir.resolve()  # the launcher changes into it
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._spawn(self.command())

    def wait_ready(self, timeout_s: float = 120.0, port: int | None = None) -> float:
        """Block until SITL can fly GUIDED: a 3D GPS fix and an estimator with an absolute
        horizontal position (EKF_STATUS_REPORT flags POS_HORIZ_ABS and PRED_POS_HORIZ_ABS).
        Seconds since start. Asks over TCP `port` (default serial2) and disconnects after.

        Before that, ArduCopter may accept DO_SET_MODE GUIDED and fall back to STABILIZE a
        moment later (seen with --fast-ekf right after boot), or refuse it.
        """
        from pymavlink import mavutil

        need = mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS
        deadline = time.monotonic() + timeout_s
        conn = None
        while conn is None:
            try:
                conn = mavutil.mavlink_connection(
                    f"tcp:127.0.0.1:{port or self.bridge_port}",
                    source_system=1,
                    source_component=mavlink.MAV_COMP_ID_USER1,
                    autoreconnect=False,
                )
            except OSError:
                if time.monotonic() >= deadline:
                    raise SitlError("SITL's TCP port never opened") from None
                time.sleep(0.2)
        try:
            fix = False
            ekf = False
            next_request = 0.0
            while time.monotonic() < deadline:
                if time.monotonic() >= next_request:
                    next_request = time.monotonic() + 2.0
                    for msg_id in (
                        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT,
                        mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
                    ):
                        conn.mav.command_long_send(
                            1,
                            1,
                            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                            0,
                            msg_id,
                            2e5,
                            0,
                            0,
                            0,
                            0,
                            0,
                        )
                msg = conn.recv_match(
                    type=["GPS_RAW_INT", "EKF_STATUS_REPORT"], blocking=True, timeout=0.5
                )
                if msg is None:
                    continue
                if msg.get_type() == "GPS_RAW_INT":
                    fix = msg.fix_type >= 3
                else:
                    ekf = msg.flags & need == need
                if fix and ekf:
                    return time.monotonic() - self.started_at
        finally:
            conn.close()
        raise SitlError(f"SITL not ready to fly in {timeout_s:.0f} s (GPS fix, EKF position)")


@dataclass
class Px4Sitl(_SitlProcess):
    """One PX4 SITL process with SIH physics (`../shared/sitl/px4/px4-sitl`, its own process
    group; stop() kills the group).

    instance: PX4's -i, 0..9 (its onboard link sends to UDP 14540 + I and listens on
    14580 + I; one instance number per machine at a time). The bundle is copied into
    workdir/bundle (`runnable_px4_bundle`) and run from there, parameters fresh, no ULog.
    bridge_ports: (PX4 listens, PX4 sends to) of the MAVLink instance the sensor bridge gets,
    free UDP ports by default.
    """

    bundle: Path
    instance: int = 0
    speedup: float = 1.0
    workdir: Path | None = None
    home: tuple[float, float, float] = PX4_HOME
    bridge_ports: tuple[int, int] | None = None
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    _log: TextIO | None = None
    _bridge_started: bool = False
    label = "PX4 SITL"
    settle_after_finish_s = 10.0
    """PX4 overshoots a stop by about 0.5 m and comes back at under 0.1 m/s (its reported
    position, SIH): the goal is judged over 10 s."""

    def __post_init__(self) -> None:
        if not 0 <= self.instance <= PX4_MAX_INSTANCE:
            raise ValueError(f"PX4 instance {self.instance} outside 0..{PX4_MAX_INSTANCE}")

    @property
    def port(self) -> int:  # type: ignore[override]
        """The UDP port PX4's onboard link sends to (the companion listens there)."""
        return 14540 + self.instance

    @property
    def system_id(self) -> int:
        """PX4 SITL's MAV_SYS_ID is instance + 1."""
        return self.instance + 1

    def command(self, bundle: Path) -> list[str]:
        assert self.workdir is not None
        return [
            str(bundle / "px4-sitl"),
            "--instance",
            str(self.instance),
            "--workdir",
            str(self.workdir / "px4"),
            "--speedup",
            f"{self.speedup:g}",
            "--home",
            ",".join(f"{v:.7f}" for v in self.home),
            "--fresh",
            "--no-log",
        ]

    def start(self) -> None:
        if self.workdir is None:
            self.workdir = Path(tempfile.mkdtemp(prefix=f"px4-{self.instance}-"))
        self.workdir = self.workdir.resolve()
        self.workdir.mkdir(parents=True, exist_ok=True)
        bundle = runnable_px4_bundle(self.bundle, self.workdir / "bundle")
        if self.bridge_ports is None:
            self.bridge_ports = (free_udp_port(), free_udp_port())
        self._bridge_started = False
        self._spawn(self.command(bundle))

    def wait_ready(self, timeout_s: float = 60.0) -> float:
        """Block until PX4 says it is armable ("Ready for takeoff!" on its console: EKF2
        aligned, about 4 s after start); seconds since start."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc is not None and self.proc.poll() is not None:
                raise SitlError(f"PX4 exited ({self.proc.returncode}): {self.output()[-400:]}")
            if "Ready for takeoff" in self.output():
                return time.monotonic() - self.started_at
            time.sleep(0.2)
        raise SitlError(f"PX4 not ready for take-off in {timeout_s:.0f} s")

    def bridge_link(self) -> str:
        """Starts (once) a MAVLink instance for the bridge in the running PX4 (`mavlink start
        -u LISTEN -o SEND -m onboard`, through PX4's module client) and returns where the
        bridge listens. The companion keeps the onboard link 14540 + I to itself."""
        assert self.workdir is not None and self.bridge_ports is not None
        listen, send = self.bridge_ports
        if not self._bridge_started:
            client = self.workdir / "bundle" / "bin" / "px4-mavlink"
            done = subprocess.run(
                [
                    str(client),
                    "--instance",
                    str(self.instance),
                    "start",
                    "-u",
                    str(listen),
                    "-o",
                    str(send),
                    "-m",
                    "onboard",
                    "-r",
                    "400000",
                ],
                cwd=self.workdir / "px4",
                capture_output=True,
                text=True,
                timeout=10.0,
                check=False,
            )
            if done.returncode != 0:
                raise SitlError(
                    f"PX4 refused the bridge's MAVLink instance: {done.stdout}{done.stderr}"
                )
            self._bridge_started = True
        return f"udpin:127.0.0.1:{send}"


AnySitl = Sitl | Px4Sitl


# --- topology (a): sensors wired to the flight controller ----------------------------------


@dataclass(frozen=True)
class WiredSensors:
    """SITL parameters making the sensors MAVLink rangefinders / proximity, and the sensor
    table as the companion sees SITL's re-reports (ids and limits as SITL sends them)."""

    params: dict[str, float]
    companion_sensors: list[dict[str, Any]]
    optional_ids: list[int]
    """The proximity sectors: ArduPilot sends nothing for a sector that has never seen an
    object in range, so the companion must take their absence as "nothing detected"."""


def wire_to_autopilot(sensors: Sequence[Any]) -> WiredSensors:
    """ArduPilot parameters for `sensors` (scenario SensorConfig) fed over MAVLink.

    Horizontal sensors (orientation YAW_0..YAW_315) go to the proximity sensor (PRX1_TYPE 2,
    re-reported as id 10 + sector); the others to rangefinders RNGFND1.. (TYPE 10, ORIENT =
    the MAV_SENSOR_ORIENTATION, re-reported as id = instance - 1). ArduPilot tells MAVLink
    rangefinders apart by orientation only, so two of them may not share one; a sensor with
    no standard orientation (ROTATION_CUSTOM) cannot be wired and raises ValueError.
    """
    params: dict[str, float] = {}
    table: list[dict[str, Any]] = []
    used: set[int] = set()
    n_rf = 0
    for cfg in sensors:
        spec: SensorSpec = cfg.to_spec()
        orient = mav_orientation_for_boresight(spec.boresight_frd)
        if orient == MAV_SENSOR_ROTATION_CUSTOM:
            raise ValueError(
                f"sensor {spec.sensor_id} ({spec.name}): ArduPilot's MAVLink rangefinders need "
                "a standard MAV_SENSOR_ORIENTATION, not a custom rotation"
            )
        if orient in used:
            raise ValueError(
                f"sensor {spec.sensor_id} ({spec.name}): orientation {orient} is taken; "
                "ArduPilot tells MAVLink rangefinders apart by orientation only"
            )
        used.add(orient)
        entry = cfg.model_dump(exclude_none=True)
        if orient <= mavlink.MAV_SENSOR_ROTATION_YAW_315:
            params["PRX1_TYPE"] = 2
            entry["id"] = PROXIMITY_ID_BASE + orient
        else:
            n_rf += 1
            if n_rf > MAX_RANGEFINDERS:
                raise ValueError(f"more than {MAX_RANGEFINDERS} rangefinders")
            key = "RNGFND" + ("A" if n_rf == 10 else str(n_rf))
            params[f"{key}_TYPE"] = 10
            params[f"{key}_ORIENT"] = orient
            params[f"{key}_MIN"] = spec.min_range_m
            params[f"{key}_MAX"] = spec.max_range_m
            entry["id"] = n_rf - 1
        table.append(entry)
    optional = [e["id"] for e in table if e["id"] >= PROXIMITY_ID_BASE]
    return WiredSensors(params, table, optional)


# --- the flight ----------------------------------------------------------------------------


def _heartbeat_frames(data: bytes) -> list[bytes]:
    """The MAVLink 2 HEARTBEAT frames in a datagram, found from the headers alone (cheap: the
    service decodes everything anyway)."""
    frames = []
    i = 0
    while i + 12 <= len(data):
        if data[i] != 0xFD:
            i += 1
            continue
        size = 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)
        if data[i + 7] == 0 and data[i + 8] == 0 and data[i + 9] == 0:
            frames.append(data[i : i + size])
        i += size
    return frames


class TapLink(UdpInLink):
    """UdpInLink that records what the service sends and the autopilot heartbeats it gets.

    sent: (monotonic s, message type, command or custom_mode or None);
    texts: the STATUSTEXTs the service sent, in order;
    heartbeats: (monotonic s, custom_mode, armed) of the autopilot (component 1).
    """

    def __init__(self, host: str, port: int) -> None:
        super().__init__(host, port)
        self._out = mavlink.MAVLink(None)
        self._in = mavlink.MAVLink(None)
        self._out.robust_parsing = True
        self._in.robust_parsing = True
        self.sent: list[tuple[float, str, int | None]] = []
        self.texts: list[str] = []
        self.heartbeats: list[tuple[float, int, bool]] = []

    def send(self, data: bytes) -> None:
        now = time.monotonic()
        for msg in self._out.parse_buffer(data) or []:
            kind = msg.get_type()
            detail = None
            if kind in ("COMMAND_LONG", "COMMAND_INT"):
                detail = int(msg.command)
            elif kind == "SET_MODE":
                detail = int(msg.custom_mode)
            elif kind == "STATUSTEXT":
                self.texts.append(str(msg.text))
            self.sent.append((now, kind, detail))
        super().send(data)

    def _deliver(self, data: bytes, peer: Any) -> None:
        now = time.monotonic()
        for frame in _heartbeat_frames(data):
            for msg in self._in.parse_buffer(frame) or []:
                if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                    armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    self.heartbeats.append((now, int(msg.custom_mode), armed))
        super()._deliver(data, peer)


@dataclass
class SitlFlight:
    """What a flight on SITL produced. Times are monotonic seconds (the service's clock)."""

    scenario: Scenario
    topology: Topology
    finished: bool
    engaged_at: float | None
    result: RunResult | None
    metrics: dict[str, Any]
    counters: dict[str, int]
    track: np.ndarray
    """(n, 7): t, x, y, z, roll, pitch, yaw of SITL's reported pose in the world frame."""
    sent: list[tuple[float, str, int | None]]
    heartbeats: list[tuple[float, int, bool]]
    log_path: Path | None
    statustexts: list[str]
    """What the service told the pilot (STATUSTEXT), in order."""
    events: list[str]
    """The planner's events after the take-over."""
    wall_s: float


def service_config(
    scenario: Scenario,
    port: int,
    anchor_xy: np.ndarray,
    log_dir: Path,
    sensors: list[dict[str, Any]],
    takeoff_alt_m: float,
    extra: dict[str, Any] | None = None,
) -> Any:
    """The service configuration flying `scenario` against SITL's stream on udp `port`;
    takeoff_alt_m: the start's height above SITL's home, metres."""
    points = (np.array(scenario.route.points[1:], dtype=float) - anchor_xy).tolist()
    raw: dict[str, Any] = {
        "link": {"connection": f"udpin:127.0.0.1:{port}"},
        "control": {
            "rate_hz": 1.0 / scenario.dt_s,
            "auto_start": {"enabled": True, "takeoff_alt_m": float(takeoff_alt_m)},
        },
        "route": {
            "source": "config",
            "points": points,
            "arrival_heading_deg": scenario.route.arrival_heading_deg,
        },
        "planner": scenario.planner.model_dump(),
        "sensors": sensors,
        "logging": {"flight_log_dir": str(log_dir), "level": "warning"},
    }
    for key, value in (extra or {}).items():
        raw[key] = {**raw.get(key, {}), **value}
    return parse_config(raw)


HOME_MARGIN_M = 20.0
"""`home_height` samples the terrain this far round the route's base points (metres): a
corrected path may leave the route by that much."""


def home_height(scenario: Scenario, world: World, step_m: float = 1.0) -> float:
    """The lowest terrain height (world z, metres) over the box round the route's base
    points grown by HOME_MARGIN_M, sampled every step_m: where SITL's home (and its flat
    ground) goes, so that no relief the vehicle follows lies below it."""
    pts = np.array(scenario.route.points, dtype=float)
    lo = pts.min(axis=0) - HOME_MARGIN_M
    hi = pts.max(axis=0) + HOME_MARGIN_M
    xs = np.arange(lo[0], hi[0] + step_m, step_m)
    ys = np.arange(lo[1], hi[1] + step_m, step_m)
    gx, gy = np.meshgrid(xs, ys)
    # The base points themselves too: the home is never above the start.
    x = np.concatenate([gx.ravel(), pts[:, 0]])
    y = np.concatenate([gy.ravel(), pts[:, 1]])
    return float(np.min(world.height(x, y)))


class Flight:
    """Service + bridge against a started SITL; `run()` flies until the route is done."""

    def __init__(
        self,
        scenario: Scenario,
        base_dir: Path,
        sitl: AnySitl,
        out_dir: Path,
        topology: Topology = "companion",
        service_extra: dict[str, Any] | None = None,
    ) -> None:
        self.scenario = scenario
        self.sitl = sitl
        self.topology = topology
        self.out_dir = out_dir
        self.world = World.from_config(scenario.world, base_dir)
        start = scenario.start(self.world)
        self.anchor = np.array([start[0], start[1], home_height(scenario, self.world)])
        extra = dict(service_extra or {})
        if topology == "autopilot" and isinstance(sitl, Px4Sitl):
            raise ValueError("sensors wired to the autopilot: ArduCopter only (PX4 not done)")
        if topology == "autopilot":
            wired = wire_to_autopilot(scenario.sensors)
            sensors = wired.companion_sensors
            fs = extra.get("failsafe", {})
            extra["failsafe"] = {**fs, "optional_sensor_ids": wired.optional_ids}
        else:
            sensors = [s.model_dump(exclude_none=True) for s in scenario.sensors]
        self.log_dir = out_dir / "flightlog"
        self.cfg = service_config(
            scenario,
            sitl.port,
            self.anchor[:2],
            self.log_dir,
            sensors,
            float(start[2] - self.anchor[2]),
            extra,
        )
        # Rates in wall time: 10 Hz, twice what the service's 0.5 s sensor age limit needs
        # (every DISTANCE_SENSOR costs the service a decode: 11 sensors at 20 Hz were half
        # its CPU). ArduPilot drops a MAVLink rangefinder after 500 ms (simulated) without
        # data, so it is fed at 10 Hz of simulated time.
        rate = 10.0 * max(sitl.speedup, 1.0) if topology == "autopilot" else 10.0
        bridge_cfg = BridgeConfig(
            connect=sitl.bridge_link(),
            send_to=topology,
            companion_address=f"127.0.0.1:{sitl.port}" if topology == "companion" else None,
            rate_hz=rate,
            system_id=sitl.system_id,
            component_id=1 if topology == "companion" else 158,
            anchor_xy=(float(self.anchor[0]), float(self.anchor[1])),
            anchor_z=float(self.anchor[2]),
        )
        self.bridge = SensorBridge(bridge_cfg, self.world, [s.to_spec() for s in scenario.sensors])
        self.bridge.core.track = []
        self.link = TapLink("127.0.0.1", sitl.port)
        self.service = Service(self.cfg, self.link, notifier=SystemdNotifier({}))
        self.statustexts: list[str] = []
        self.finished_at: float | None = None
        """Monotonic s when `wait` saw the route done (the goal is judged from then on)."""
        self._task: asyncio.Task[int] | None = None

    @property
    def engaged(self) -> bool:
        return self.service.ownership.engaged

    async def start(self) -> None:
        await self.bridge.start()
        self._bridge_task = asyncio.create_task(self.bridge.run())
        self._task = asyncio.create_task(self.service.run())

    async def wait(
        self, timeout_s: float, until: Callable[[], bool] | None = None, poll_s: float = 0.2
    ) -> bool:
        """Wait until `until()` (default: route finished) or timeout; False on timeout."""
        pred = until or self.service.route_finished.is_set
        deadline = time.monotonic() + timeout_s
        while not pred():
            if self._task is not None and self._task.done():
                raise RuntimeError(f"service stopped: {self._task.result()}")
            if self.sitl.proc is not None and self.sitl.proc.poll() is not None:
                raise SitlError(f"SITL exited: {self.sitl.output()[-400:]}")
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(poll_s)
        if until is None and self.finished_at is None:
            self.finished_at = time.monotonic()
        return True

    async def stop(self) -> None:
        self.service.stop()
        if self._task is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._task, 10.0)
        self._bridge_task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._bridge_task
        await self.bridge.close()

    def outcome(self, wall_s: float) -> SitlFlight:
        track = np.array(self.bridge.core.track, dtype=float).reshape(-1, 7)
        logs = sorted(self.log_dir.glob("flight-*.jsonl"))
        log = read_flight_log(logs[-1]) if logs else None
        result: RunResult | None = None
        m: dict[str, Any] = {}
        engaged_at = None
        finished = self.service.route_finished.is_set()
        if log is not None and len(track):
            planner_rows = [i for i, k in enumerate(log.setpoint_kind) if k == "planner"]
            if planner_rows:
                engaged_at = float(log.t_s[planner_rows[0]])
                result = trace_from_log(log, self.world, self.anchor, track[:, 0], track[:, 1:])
                result.finished = finished
                # times from the take-over on
                result.trace["t"] = result.trace["t"] - engaged_at
                result.events = [(t - engaged_at, e) for t, e in result.events]
                m = metrics_mod.compute(
                    result.trace,
                    self.scenario.route_obj(),
                    self.world,
                    self.scenario.planner.h_d_m,
                    self.scenario.planner.v_d_mps,
                    finished,
                )
                goal = np.array(self.scenario.route.points[-1], dtype=float)
                since = self.finished_at
                if since is None:  # done, but nobody waited for it: its last planner row
                    since = float(log.t_s[planner_rows[-1]])
                d = goal_distance(track, goal, since) if finished else None
                if d is not None:
                    m["goal_distance_m"] = d
                    m["reached_goal"] = d < GOAL_RADIUS_M
                done = np.flatnonzero(log.finished)
                if len(done):  # the height error while the route was flown, without the stop
                    t_done = float(log.t_s[done[0]]) - engaged_at
                    err = np.abs(result.trace["height"] - self.scenario.planner.h_d_m)
                    settled = np.flatnonzero(err <= metrics_mod.SETTLE_BAND_M)
                    on_route = result.trace["t"] <= t_done
                    if len(settled):
                        on_route[: settled[0]] = False
                    m["max_height_error_route_m"] = float(np.max(err[on_route], initial=0.0))
                m["phi_max_rad"] = self.scenario.planner.phi_max_rad
                m["d_min_m"] = self.scenario.planner.d_min_m
        texts = [e for _, e in result.events] if result is not None else []
        return SitlFlight(
            self.scenario,
            self.topology,
            finished,
            engaged_at,
            result,
            m,
            self.service.counter_values(),
            track,
            list(self.link.sent),
            list(self.link.heartbeats),
            logs[-1] if logs else None,
            list(self.link.texts),
            texts,
            wall_s,
        )


async def fly_on_sitl(
    scenario: Scenario,
    base_dir: Path,
    sitl: AnySitl,
    out_dir: Path,
    topology: Topology = "companion",
    timeout_s: float | None = None,
) -> SitlFlight:
    """Fly the scenario on a started SITL (heartbeat seen) until the route is done."""
    t0 = time.monotonic()
    flight = Flight(scenario, base_dir, sitl, out_dir, topology)
    await flight.start()
    try:
        if await flight.wait(timeout_s if timeout_s is not None else scenario.duration_s + 90.0):
            await asyncio.sleep(sitl.settle_after_finish_s)
    finally:
        await flight.stop()
    return flight.outcome(time.monotonic() - t0)


def start_heading_deg(scenario: Scenario) -> float:
    """The scenario's start heading as SITL's home heading (compass degrees), so that the
    vehicle boots facing the way the scenario starts, as `companion fly` starts it."""
    return (90.0 - math.degrees(scenario.route_obj().start_heading_rad)) % 360.0


def sitl_params(scenario: Scenario, topology: Topology) -> dict[str, float]:
    """Parameters SITL boots with for this scenario and topology."""
    if topology == "autopilot":
        return dict(wire_to_autopilot(scenario.sensors).params)
    return {}


def run_cli(
    scenario_path: Path,
    out_dir: Path,
    topology: Topology = "companion",
    instance: int = 0,
    speedup: float = 1.0,
    fast_ekf: bool = True,
    sensors_path: Path | None = None,
    stream: TextIO = sys.stdout,
    autopilot: Literal["arducopter", "px4"] = "arducopter",
) -> int:
    """`python -m companion.harness sitl`: fly a scenario on the real SITL, print the metrics table.
    sensors_path: a sensor table (YAML list) replacing the scenario's."""
    scenario = load_scenario(scenario_path)
    if sensors_path is not None:
        with sensors_path.open(encoding="utf-8") as f:
            table = yaml.safe_load(f)
        scenario = Scenario.model_validate({**scenario.model_dump(), "sensors": table})
    sitl: AnySitl
    if autopilot == "px4":
        bundle = find_px4()
        if bundle is None:
            stream.write(f"error: no PX4 SITL at {PX4_DIR}/px4-sitl next to the repository\n")
            return 2
        if topology == "autopilot":
            stream.write("error: --sensors-to autopilot is done for ArduCopter only\n")
            return 2
        if not 0 <= instance <= PX4_MAX_INSTANCE:
            stream.write(f"error: PX4 --instance must be 0..{PX4_MAX_INSTANCE}\n")
            return 2
        sitl = Px4Sitl(bundle, instance, speedup=speedup, workdir=out_dir / "sitl")
    else:
        launcher = find_sitl()
        if launcher is None:
            stream.write(f"error: no SITL at {SITL_DIR}/arducopter-sitl next to the repository\n")
            return 2
        sitl = Sitl(
            launcher,
            instance,
            free_udp_port(),
            speedup=speedup,
            fast_ekf=fast_ekf,
            params=sitl_params(scenario, topology),
            workdir=out_dir / "sitl",
            heading_deg=start_heading_deg(scenario),
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        with sitl:
            sitl.wait_heartbeat()
            boot = sitl.wait_ready()
            flown = asyncio.run(
                fly_on_sitl(scenario, scenario_path.parent, sitl, out_dir, topology)
            )
    except SitlError as exc:
        stream.write(f"error: {exc} ({sitl.label} output: {sitl.workdir}/sitl.out)\n")
        return 1
    how = "SIH" if isinstance(sitl, Px4Sitl) else ("EKF3" if not fast_ekf else "fast EKF")
    stream.write(
        f"scenario {scenario.name} on {sitl.label} (speed-up {speedup:g}, {how}, sensors to "
        f"the {topology}); ready after {boot:.1f} s, flight {flown.wall_s:.0f} s wall\n"
    )
    if flown.metrics and flown.result is not None:
        import importlib.util

        from companion.harness.runner import write_outputs

        plots = importlib.util.find_spec("matplotlib") is not None
        world = World.from_config(scenario.world, scenario_path.parent)
        write_outputs(out_dir, scenario, world, flown.result, flown.metrics, plots=plots)
        stream.write(metrics_mod.format_table(flown.metrics) + "\n")
        if "max_height_error_route_m" in flown.metrics:
            stream.write(
                f"max |H - H_d| (settled) until the route was done: "
                f"{flown.metrics['max_height_error_route_m']:.3f} m (the row above includes "
                f"the {sitl.settle_after_finish_s:g} s held at the goal)\n"
            )
        if "goal_distance_m" in flown.metrics:
            stream.write(
                f"closest to the goal after the route was done: "
                f"{flown.metrics['goal_distance_m']:.2f} m (SITL's position)\n"
            )
    else:
        stream.write("the service never took over\n")
    for t, text in flown.result.events if flown.result is not None else []:
        stream.write(f"  {t:8.2f} s  {text}\n")
    return 0 if flown.metrics.get("reached_goal") else 1
