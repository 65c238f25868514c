"""The input cache: the autopilot's latest heartbeat, attitude, position, home and ranges.

Every accepted input carries `t_rx`, the service clock's time when it was received, so the
loop can judge ages. Inputs are validated before they are stored: NaN/inf or out-of-range
fields are rejected and counted and never reach the planner; the previous (older) value stays
and simply ages, which is what trips the stale-input failsafe. Units are converted here, at the
edge: centimetres to metres, degrees*1e7 to degrees, millimetres to metres.

DISTANCE_SENSOR readings are mapped to the sensor table by id, and the message's orientation
must agree with the configured one (within 5 degrees; MAV_SENSOR_ROTATION_CUSTOM is checked
through its quaternion when one is given), and so must its min/max_distance (`limits_problem`):
a message whose limits contradict the configured ones is refused and reported, never used.
A reading of 0, at/over the configured maximum or 65535 means "nothing detected" and is stored
as 0.0: a fresh reading of nothing is valid data. A reading below the configured minimum is
"too close to measure" and is stored as the minimum range (something is there, at most that
far). NaN in `range_vector` is reserved for a missing or stale reading.

time_boot_ms ordering: an older stamp than the last one (reordered or duplicated datagrams)
is dropped. A stamp far ahead of the autopilot's clock, or more than REBOOT_BACKSTEP_MS back,
is dropped as suspect until several messages of two types agree on the new clock (see
`_in_order`): then a jump back is an autopilot reboot, which resets the cache and is reported
via `reboots`, and a jump ahead a re-sync.
"""

from __future__ import annotations

import bisect
import logging
import math
import statistics
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.planner.sensors import (
    MAV_SENSOR_ROTATION_CUSTOM,
    SensorTable,
    boresight_from_mav_orientation,
    boresight_from_quaternion_frd,
)
from companion.planner.types import FloatArray
from companion.service.codec import MAVLinkMessage
from companion.service.pairing import AttitudeHistory, Pairing, pair_ranges

log = logging.getLogger("companion.service.telemetry")

REBOOT_BACKSTEP_MS = 3000
FUTURE_TOLERANCE_MS = 250.0
"""A stamp this far ahead of the autopilot's clock as known is suspect (less than the
position's maximum age, so a forged one accepted inside it cannot starve the loop)."""
CLOCK_AGREE_MS = 1000.0
CLOCK_EVIDENCE_MSGS = 5
CLOCK_EVIDENCE_TYPES = 2
CLOCK_CANDIDATES = 8


@dataclass(slots=True)
class _ClockCandidate:
    """Stamps that disagree with the known clock (or come before any) but agree with each
    other: their offsets from the receipt clock, ms."""

    back: bool
    kinds: set[str]
    offsets_ms: list[float]

    def median_ms(self) -> float:
        # statistics, not numpy: np.median's first call imports numpy.ma (about 10 ms)
        return float(statistics.median(self.offsets_ms)) if self.offsets_ms else 0.0


LOG_AT_COUNTS = frozenset(10**k for k in range(19))
"""Counts at which a counter is logged: 1, 10, 100, ..."""
MEDIAN_GAP_S = 0.5
"""A range history older than this is not filtered with new readings."""
MAX_ACCEL_MPS2 = 10.0
"""Acceleration that explains a position off the velocity-predicted path after a gap."""
ORIENTATION_TOLERANCE_COS = math.cos(math.radians(5.0))
UINT16_MAX = 65535
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18


LIMIT_TOLERANCE_M = 0.05
"""How far a DISTANCE_SENSOR's own min/max may differ from the configured ones (cm rounding,
float truncation) before the two are taken to contradict each other."""


def limits_problem(min_cm: int, max_cm: int, min_m: float, max_m: float) -> str:
    """Why a DISTANCE_SENSOR's min/max_distance (cm) contradict the configured range
    [min_m, max_m), or "" if they do not. 0/0 (or a max of 0 or 65535) means "not given".

    Refused: min >= max; a sender minimum above the configured one (readings between them
    would be misread); a sender maximum below the configured one (its "nothing" would be taken
    as free space out to the configured maximum). A wider sender range is fine: the configured
    one is what the planner uses."""
    if max_cm in (0, UINT16_MAX):
        return ""
    if min_cm >= max_cm:
        return f"message limits {min_cm}-{max_cm} cm are not a range"
    if min_cm * 0.01 > min_m + LIMIT_TOLERANCE_M or max_cm * 0.01 < max_m - LIMIT_TOLERANCE_M:
        return (
            f"message limits {min_cm * 0.01:g}-{max_cm * 0.01:g} m "
            f"differ from the configured {min_m:g}-{max_m:g} m"
        )
    return ""


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """An autopilot HEARTBEAT. t_rx: service clock seconds."""

    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int
    t_rx: float

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & 128)  # MAV_MODE_FLAG_SAFETY_ARMED


@dataclass(frozen=True, slots=True)
class Attitude:
    """ATTITUDE: FRD body in NED, radians (yaw clockwise from north)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    time_boot_ms: int
    t_rx: float


@dataclass(frozen=True, slots=True)
class Position:
    """GLOBAL_POSITION_INT: degrees, metres AMSL / above home, velocity NED m/s."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    relative_alt_m: float
    velocity_ned_mps: tuple[float, float, float]
    time_boot_ms: int
    t_rx: float


@dataclass(frozen=True, slots=True)
class Home:
    """HOME_POSITION: degrees and metres AMSL."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    t_rx: float


@dataclass(frozen=True, slots=True)
class RangeReading:
    """One sensor's latest reading: metres, 0.0 = nothing detected."""

    distance_m: float
    time_boot_ms: int
    t_rx: float


def valid_lat_lon(lat_deg: float, lon_deg: float) -> bool:
    """Finite, in range, and not the 0/0 that autopilots send before a fix."""
    return (
        math.isfinite(lat_deg)
        and math.isfinite(lon_deg)
        and -90.0 <= lat_deg <= 90.0
        and -180.0 <= lon_deg <= 180.0
        and not (lat_deg == 0.0 and lon_deg == 0.0)
    )


def _north_east_m(lat1: float, lon1: float, lat2: float, lon2: float) -> tuple[float, float]:
    """Local north/east metres from point 1 to point 2 (small distances)."""
    north = math.radians(lat2 - lat1) * 6_371_000.0
    dlon = (lon2 - lon1 + 180.0) % 360.0 - 180.0
    east = math.radians(dlon) * 6_371_000.0 * math.cos(math.radians(0.5 * (lat1 + lat2)))
    return north, east


def _distance_m(last: Position, lat: float, lon: float, alt: float) -> float:
    d = _haversine_m(last.lat_deg, last.lon_deg, lat, lon)
    return math.hypot(d, alt - last.alt_amsl_m)


def _norm3(v: tuple[float, float, float]) -> float:
    """Euclidean length of a 3-vector."""
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _haversine_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2.0 * 6_371_000.0 * math.asin(min(1.0, math.sqrt(a)))


_SenderCheck = tuple[int | None, bool | None, str]
"""A DISTANCE_SENSOR sender's table index, orientation verdict and limits problem."""


class Telemetry:
    """Latest validated inputs from one autopilot, with receipt times and counters.

    `counters` (a Counter of names) records every rejection and notable input; the names are
    stable and appear in the flight log and docs/service.md.
    """

    def __init__(
        self,
        sensors: SensorTable,
        *,
        max_speed_mps: float = 40.0,
        jump_accept_s: float = 1.0,
        max_jump_m: float = 2.0,
        median_samples: int = 1,
        max_accepted_jump_m: float = 50.0,
        spike_m: float = 0.0,
    ) -> None:
        self.sensors = sensors
        self.median_samples = median_samples
        self.spike_m = spike_m
        self.max_speed_mps = max_speed_mps
        self.jump_accept_s = jump_accept_s
        self.max_jump_m = max_jump_m
        self.max_accepted_jump_m = max_accepted_jump_m
        self.jump_fault = ""
        """Why a persistent position jump is refused (larger than max_accepted_jump_m)."""
        self.jumps_accepted = 0
        self.last_jump_enu = np.zeros(3)
        """The last accepted jump: the position minus where the reported velocity put it."""
        self._residual_ned = (0.0, 0.0, 0.0)
        """The last position's offset from the velocity-predicted path (NED m)."""
        self._jump_ned = (0.0, 0.0, 0.0)
        """Position jumps accepted because they persisted (estimator resets): the position
        the loop works in has moved, so plans and holds made before it are void."""
        self.counters: Counter[str] = Counter()
        self._expected_boresight = [s.boresight_frd for s in sensors.specs]
        self._sensor_ok: dict[tuple[Any, ...], _SenderCheck] = {}
        """Per DISTANCE_SENSOR (id, orientation, min, max): `_sender_check`'s verdict.
        Per-message work done once per sensor."""
        self._custom_ok: dict[tuple[Any, ...], _SenderCheck] = {}
        """The same for MAV_SENSOR_ROTATION_CUSTOM, per (id, min, max, quaternion)."""
        self._wrong_aims: dict[int, set[tuple[Any, ...]]] = {}
        """Per configured sensor id, the distinct wrong orientations (and quaternions) it
        arrived with: two or more mean several rangefinders share the id."""
        self._order_keys = [f"DISTANCE_SENSOR.{i}" for i in range(len(sensors))]
        self._detects: dict[tuple[int, float], bool] = {}
        """The planner's detection rule (`SensorTable.valid`) per (index, reading): readings
        are whole centimetres, so a few hundred values per sensor."""
        self._boresight_cache: dict[int, FloatArray | None] = {}
        self._quaternion_cache: dict[tuple[float, ...], FloatArray | None] = {}
        self.reboots = 0
        self.notices: list[str] = []
        """Faults for the pilot (sensor limits refused, ...): the service drains and says them."""
        self._limit_problem: dict[int, str] = {}
        self.reset()

    def reset(self) -> None:
        """Forget everything but the counters (autopilot reboot or a new autopilot)."""
        self.heartbeat: Heartbeat | None = None
        self.attitude: Attitude | None = None
        self.attitudes = AttitudeHistory()
        """The last second of attitudes by stamp, rate-gated (`pairing.py`)."""
        self.position: Position | None = None
        self.home: Home | None = None
        self.ranges: list[RangeReading | None] = [None] * len(self.sensors)
        self._probe = np.full(len(self.sensors), math.nan)
        """One reading at a time through the planner's detection rule."""
        self._history: list[deque[tuple[float, RangeReading]]] = [
            deque(maxlen=max(1, self.median_samples)) for _ in range(len(self.sensors))
        ]
        """Per sensor: its last readings, each with its median order (0.0: +inf)."""
        self._last_boot_ms: dict[str, int] = {}
        self._clock_ref: float | None = None
        self._last_rx: dict[str, float] = {}
        self._offset_ms: dict[str, float] = {}
        """Per kind: its last accepted stamp minus its receipt time, milliseconds."""
        self._offsets_sorted: list[float] = []
        """The values of `_offset_ms`, sorted (kept so, one kind at a time)."""
        self._clock_candidates: list[_ClockCandidate] = []
        self._jump_since: float | None = None
        self._jump_dt = 0.0

    # -- dispatch ---------------------------------------------------------------------------

    def update(self, msg: MAVLinkMessage, t_rx: float) -> str | None:
        """Store `msg` if it is valid; returns what was updated ("ATTITUDE", ...) or None."""
        kind = msg.get_type()
        handler = _HANDLERS.get(kind)
        if handler is None:
            return None
        return kind if handler(self, msg, t_rx) else None

    def _count(self, name: str, level: int = logging.INFO, detail: str = "", *args: object) -> None:
        """Count `name`; log it the 1st, 10th, 100th, ... time (bounded log volume). `detail`
        is a %-format of `args`, formatted only when the line is logged (most inputs that
        are counted, e.g. a reading of nothing, are not)."""
        n = self.counters[name] + 1
        self.counters[name] = n
        if n in LOG_AT_COUNTS:
            log.log(level, "input.%s: %d so far" + detail, name, n, *args)

    def _reject(self, what: str, detail: str = "", *args: object) -> bool:
        self._count(f"rejected_{what}", logging.WARNING, detail and f" ({detail})", *args)
        return False

    def _in_order(self, key: str, time_boot_ms: int, t_rx: float) -> bool:
        """False for a stale, duplicate or suspect stamp. Where the autopilot's boot clock is
        now is the lower median, over the message kinds, of each kind's last accepted stamp
        plus the receipt time since (so one kind forged ahead cannot move it, and a clock that
        runs at another rate than ours is followed message by message). A stamp more than
        FUTURE_TOLERANCE_MS ahead of it, or more than
        REBOOT_BACKSTEP_MS behind the last stamp of its kind, is held as evidence of a new
        clock and dropped; only CLOCK_EVIDENCE_MSGS such stamps of CLOCK_EVIDENCE_TYPES
        message types agreeing with each other, with no stamp of the old clock among them,
        change the clock (back: a reboot, which resets the cache; ahead: a re-sync). One
        forged packet can neither reset the cache nor poison the ordering."""
        if time_boot_ms == 0:  # some senders do not stamp
            return True
        off = time_boot_ms - t_rx * 1000.0
        ref = self._clock_ref
        last = self._last_boot_ms.get(key)
        if ref is None:
            # the first stamps: ordered per kind only, until several agree on the clock
            self._first_clock(key, off, t_rx)
            if self._clock_ref is None:
                if last is not None and time_boot_ms <= last:
                    self._count("out_of_order" if time_boot_ms < last else "duplicate")
                    return False
                self._set_stamp(key, time_boot_ms, t_rx)
                return True
            # the clock has just been agreed on: this stamp is judged by it like any other
            last = self._last_boot_ms.get(key)
        expected = self._expected_stamp(t_rx)
        ahead = expected is not None and time_boot_ms > expected + FUTURE_TOLERANCE_MS
        back = last is not None and last - time_boot_ms > REBOOT_BACKSTEP_MS
        if ahead or back:
            return self._clock_evidence(key, time_boot_ms, off, t_rx, back)
        if self._clock_candidates:
            self._clock_candidates.clear()
        if last is not None and time_boot_ms <= last:
            self._count("out_of_order" if time_boot_ms < last else "duplicate")
            return False
        self._set_stamp(key, time_boot_ms, t_rx)
        return True

    def _set_stamp(self, key: str, time_boot_ms: int, t_rx: float) -> None:
        """Record a kind's last accepted stamp (ms) and its receipt time (s)."""
        self._last_boot_ms[key] = time_boot_ms
        self._last_rx[key] = t_rx
        off = time_boot_ms - t_rx * 1000.0
        srt = self._offsets_sorted
        old = self._offset_ms.get(key)
        if old is not None:
            del srt[bisect.bisect_left(srt, old)]
        self._offset_ms[key] = off
        bisect.insort(srt, off)

    def _clear_stamps(self) -> None:
        self._last_boot_ms.clear()
        self._last_rx.clear()
        self._offset_ms.clear()
        self._offsets_sorted.clear()

    def _expected_stamp(self, t_rx: float) -> float | None:
        """The autopilot's clock now (ms) from every kind's last accepted stamp, or None."""
        # the lower median of (stamp + time since its receipt) over the kinds: the offsets
        # are kept sorted as they change, so this is O(1) per message, not a sort
        srt = self._offsets_sorted
        return srt[(len(srt) - 1) // 2] + t_rx * 1000.0 if srt else None

    def _candidate(self, key: str, off: float, back: bool) -> _ClockCandidate | None:
        """Add a stamp to the group of stamps it agrees with (a new one if none; at most
        CLOCK_CANDIDATES groups, so stamps forged between good ones stay apart from them);
        the group once it is evidence enough (then all groups are dropped), else None."""
        for c in self._clock_candidates:
            if c.back == back and abs(off - c.median_ms()) <= CLOCK_AGREE_MS:
                break
        else:
            c = _ClockCandidate(back, set(), [])
            self._clock_candidates.append(c)
            if len(self._clock_candidates) > CLOCK_CANDIDATES:
                self._clock_candidates.pop(0)
        c.kinds.add(key.split(".")[0])
        c.offsets_ms.append(off)
        if len(c.offsets_ms) < CLOCK_EVIDENCE_MSGS or len(c.kinds) < CLOCK_EVIDENCE_TYPES:
            return None
        self._clock_candidates.clear()
        return c

    def _first_clock(self, key: str, off: float, t_rx: float) -> None:
        """Gather the first stamps; when enough agree, their median is the clock, and no
        kind's last stamp may stay ahead of it by more than FUTURE_TOLERANCE_MS (a forged
        first stamp far ahead would otherwise hold that kind back)."""
        c = self._candidate(key, off, back=False)
        if c is None:
            return
        self._clock_ref = c.median_ms()
        cap = int(self._clock_ref + t_rx * 1000.0 + FUTURE_TOLERANCE_MS)
        for k, v in list(self._last_boot_ms.items()):
            if v > cap:
                self._set_stamp(k, cap, t_rx)

    def _clock_evidence(
        self, key: str, time_boot_ms: int, off: float, t_rx: float, back: bool
    ) -> bool:
        c = self._candidate(key, off, back)
        if c is None:
            where = "back" if back else "ahead"
            self._count("time_boot_suspect", logging.WARNING, " (%s %s)", key, where)
            return False
        if back:
            self._count("time_boot_backwards", logging.WARNING, " (%s)", key)
            self.reboots += 1
            counters, reboots = self.counters, self.reboots
            self.reset()
            self.counters, self.reboots = counters, reboots
        else:
            self._count("time_boot_resync", logging.WARNING, " (%s)", key)
            self._clear_stamps()
        # the median: one odd stamp among the evidence does not set the clock
        self._clock_ref = c.median_ms()
        self._set_stamp(key, time_boot_ms, t_rx)
        return True

    # -- messages ---------------------------------------------------------------------------

    def _heartbeat(self, msg: MAVLinkMessage, t_rx: float) -> bool:
        self.heartbeat = Heartbeat(
            int(msg.autopilot),
            int(msg.type),
            int(msg.base_mode),
            int(msg.custom_mode),
            int(msg.system_status),
            t_rx,
        )
        return True

    def _attitude(self, msg: MAVLinkMessage, t_rx: float) -> bool:
        r, p, y = float(msg.roll), float(msg.pitch), float(msg.yaw)
        rates = (float(msg.rollspeed), float(msg.pitchspeed), float(msg.yawspeed))
        if not all(math.isfinite(v) for v in (r, p, y, *rates)):
            return self._reject("attitude_nonfinite", "roll %s pitch %s yaw %s", r, p, y)
        if abs(r) > math.pi + 1e-3 or abs(p) > math.pi / 2 + 1e-3 or abs(y) > 2 * math.pi + 1e-3:
            return self._reject("attitude_range", "roll %s pitch %s yaw %s", r, p, y)
        if not self._in_order("ATTITUDE", int(msg.time_boot_ms), t_rx):
            return False
        self.attitude = Attitude(r, p, y, int(msg.time_boot_ms), t_rx)
        if msg.time_boot_ms and not self.attitudes.add(int(msg.time_boot_ms), r, p, y):
            self._count("attitude_rate_untrusted", logging.WARNING, " (t %s ms)", msg.time_boot_ms)
        return True

    def _global_position(self, msg: MAVLinkMessage, t_rx: float) -> bool:
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        alt, rel = msg.alt * 1e-3, msg.relative_alt * 1e-3
        if not valid_lat_lon(lat, lon) or not (
            -1_000.0 <= alt <= 50_000.0 and -10_000.0 <= rel <= 50_000.0
        ):
            return self._reject("position_range", "lat %s lon %s alt %s rel %s", lat, lon, alt, rel)
        if not self._in_order("GLOBAL_POSITION_INT", int(msg.time_boot_ms), t_rx):
            return False
        vel = (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
        last = self.position
        if last is not None and self._is_jump(last, lat, lon, alt, vel, msg.time_boot_ms, t_rx):
            if self._jump_since is None:
                self._jump_since = t_rx
                self._jump_dt = max(self._dt(last, msg.time_boot_ms, t_rx), 0.05)
                # measured on its first sample, where the velocity prediction is best
                self._jump_ned = self._residual_ned
            if t_rx - self._jump_since < self.jump_accept_s:
                self._unaccept_position(last)
                return self._reject("position_jump")
            size = _norm3(self._jump_ned)
            if size > self.max_accepted_jump_m:
                # too big to be an estimator reset the plan can follow: a fault, never accepted
                self._unaccept_position(last)
                if not self.jump_fault:
                    limit = self.max_accepted_jump_m
                    self.jump_fault = f"position jump of {size:.0f} m over the {limit:g} m limit"
                    self.notices.append(f"{self.jump_fault}: stopped")
                    log.error("%s: not accepted; stopped", self.jump_fault)
                return self._reject("position_jump_fault")
            self._count("position_jump_accepted", logging.WARNING)
            n, e, d = self._jump_ned
            self.last_jump_enu = np.array([e, n, -d])
            self.jumps_accepted += 1
            log.warning(
                "position jump of %.1f m persisted %.1f s: accepted (estimator reset?)",
                _distance_m(last, lat, lon, alt),
                t_rx - self._jump_since,
            )
        self._jump_since = None
        self.jump_fault = ""
        self.position = Position(lat, lon, alt, rel, vel, int(msg.time_boot_ms), t_rx)
        return True

    def _is_jump(
        self,
        last: Position,
        lat: float,
        lon: float,
        alt: float,
        vel_ned: tuple[float, float, float],
        time_boot_ms: int,
        t_rx: float,
    ) -> bool:
        """A glitch: faster than max_speed_mps, or off the path the reported velocities
        predict by more than max_jump_m plus what MAX_ACCEL_MPS2 explains over the gap (the
        gap at the start of a jump episode: rejected samples do not make it grow)."""
        dt = self._dt(last, time_boot_ms, t_rx)
        north, east = _north_east_m(last.lat_deg, last.lon_deg, lat, lon)
        # plain floats: a 3-vector costs more as numpy arrays than as arithmetic
        v0, v1 = last.velocity_ned_mps, vel_ned
        self._residual_ned = (
            north - 0.5 * (v0[0] + v1[0]) * dt,
            east - 0.5 * (v0[1] + v1[1]) * dt,
            (last.alt_amsl_m - alt) - 0.5 * (v0[2] + v1[2]) * dt,
        )
        if _distance_m(last, lat, lon, alt) > self.max_speed_mps * max(dt, 0.05):
            return True
        residual = _norm3(self._residual_ned)
        dt_accel = dt if self._jump_since is None else min(dt, self._jump_dt)
        return residual > self.max_jump_m + 0.5 * MAX_ACCEL_MPS2 * dt_accel * dt_accel

    def _unaccept_position(self, last: Position) -> None:
        """A position passed the stamp checks but is rejected: its kind's clock stays at the
        last accepted one."""
        self._set_stamp("GLOBAL_POSITION_INT", last.time_boot_ms, last.t_rx)

    @staticmethod
    def _dt(last: Position, time_boot_ms: int, t_rx: float) -> float:
        """Seconds since `last`: the autopilot's stamps when both have one, else receipt."""
        dt_boot = (time_boot_ms - last.time_boot_ms) * 1e-3
        if time_boot_ms and last.time_boot_ms and dt_boot > 0:
            return dt_boot
        return max(t_rx - last.t_rx, 0.0)

    def _home(self, msg: MAVLinkMessage, t_rx: float) -> bool:
        lat, lon, alt = msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3
        if not valid_lat_lon(lat, lon) or not -1_000.0 <= alt <= 50_000.0:
            return self._reject("home_range")
        self.home = Home(lat, lon, alt, t_rx)
        return True

    def _msg_boresight(self, orientation: int, quaternion: list[float]) -> FloatArray | None:
        if orientation == MAV_SENSOR_ROTATION_CUSTOM:
            # A sensor sends the same quaternion every time: convert each one once.
            key = tuple(quaternion)
            if key not in self._quaternion_cache:
                if len(self._quaternion_cache) > 256:  # a sender varying it: stay bounded
                    self._quaternion_cache.clear()
                q = np.asarray(quaternion, dtype=np.float64)
                ok = q.shape == (4,) and np.all(np.isfinite(q)) and np.linalg.norm(q) >= 1e-6
                self._quaternion_cache[key] = boresight_from_quaternion_frd(q) if ok else None
            return self._quaternion_cache[key]
        if orientation not in self._boresight_cache:
            try:
                self._boresight_cache[orientation] = boresight_from_mav_orientation(orientation)
            except ValueError:
                self._boresight_cache[orientation] = None
        return self._boresight_cache[orientation]

    def _agrees(self, index: int, orientation: int, quaternion: list[float]) -> bool | None:
        """The message's orientation (and quaternion) against the configured boresight of
        sensor `index`: within 5 degrees, or None when it names no direction."""
        boresight = self._msg_boresight(orientation, quaternion)
        if boresight is None:
            return None
        return float(boresight @ self._expected_boresight[index]) >= ORIENTATION_TOLERANCE_COS

    def _sender_check(
        self,
        checks: dict[tuple[Any, ...], _SenderCheck],
        key: tuple[Any, ...],
        sensor_id: int,
        orientation: int,
        quaternion: tuple[float, ...],
        min_cm: int,
        max_cm: int,
    ) -> _SenderCheck:
        """What a DISTANCE_SENSOR's id, orientation (quaternion) and limits say, worked out
        once per sender's values (they do not change from message to message): the table
        index (None: unknown id), the orientation against the configured one (`_agrees`)
        and the limits' problem (`limits_problem`)."""
        index = self.sensors.index_of_id.get(sensor_id)
        if index is None:
            check: _SenderCheck = (None, None, "")
        else:
            spec = self.sensors.specs[index]
            check = (
                index,
                self._agrees(index, orientation, list(quaternion)),
                limits_problem(min_cm, max_cm, spec.min_range_m, spec.max_range_m),
            )
        if len(checks) > 1024:  # a sender varying them: stay bounded
            checks.clear()
        checks[key] = check
        return check

    def _note_shared_id(self, sensor_id: int, aim: tuple[Any, ...]) -> None:
        """Say once per id when it has come with two different wrong orientations: one id
        carries several rangefinders (PX4 passes on every rangefinder fed to it over one
        MAVLink link as a single sensor, the last reading's orientation with it)."""
        seen = self._wrong_aims.setdefault(sensor_id, set())
        if len(seen) >= 2 or aim in seen:
            return
        seen.add(aim)
        if len(seen) == 2:
            self.counters["sensor_id_shared"] += 1
            log.warning(
                "DISTANCE_SENSOR id %d arrives with several orientations (%s): more than one "
                "rangefinder shares this id, and only readings in the configured orientation "
                "are used. PX4 passes on the rangefinders fed to it over one MAVLink link as a "
                "single sensor: send them to the companion directly (docs/autopilots.md).",
                sensor_id,
                ", ".join(sorted(str(a[0]) for a in seen)),
            )

    def _distance_sensor(self, msg: MAVLinkMessage, t_rx: float) -> bool:
        sensor_id, orientation = int(msg.id), int(msg.orientation)
        mn, mx = int(msg.min_distance), int(msg.max_distance)
        quaternion: tuple[float, ...] = ()
        if orientation == MAV_SENSOR_ROTATION_CUSTOM:
            quaternion = tuple(getattr(msg, "quaternion", ()))
            checks = self._custom_ok
            key: tuple[Any, ...] = (sensor_id, mn, mx, quaternion)
        else:
            checks = self._sensor_ok
            key = (sensor_id, orientation, mn, mx)
        check = checks.get(key)
        if check is None:
            check = self._sender_check(checks, key, sensor_id, orientation, quaternion, mn, mx)
        index, ok, problem = check
        if index is None:
            return self._reject("sensor_unknown_id", "id %d", sensor_id)
        if ok is None:
            if orientation != MAV_SENSOR_ROTATION_CUSTOM:
                return self._reject(
                    "sensor_orientation_unknown", "id %d orientation %d", sensor_id, orientation
                )
            self._count("sensor_orientation_unverified")
        elif not ok:
            self._note_shared_id(sensor_id, (orientation, *(round(v, 2) for v in quaternion)))
            return self._reject(
                "sensor_orientation_mismatch", "id %d orientation %d", sensor_id, orientation
            )
        time_boot_ms = int(msg.time_boot_ms)
        if not self._in_order(self._order_keys[index], time_boot_ms, t_rx):
            return False
        spec = self.sensors.specs[index]
        if problem:
            # The sender's limits contradict the configured ones: one of the two is wrong,
            # and a reading cannot be trusted to mean what the planner will take it for.
            if self._limit_problem.get(index) != problem:
                self._limit_problem[index] = problem
                self.notices.append(f"sensor {spec.sensor_id} refused: {problem}")
            return self._reject("sensor_limits", "sensor %s: %s", spec.sensor_id, problem)
        if self._limit_problem:
            self._limit_problem.pop(index, None)
        lo = spec.min_range_m
        cur = int(msg.current_distance)
        # 65535 is MAVLink's "unknown"; 0 < d < min is "too close to measure", not "nothing":
        # something is there, at most at the minimum range. Everything else that means
        # "nothing detected" is the planner's rule (`SensorTable.valid`), applied here.
        d = 0.0 if cur == UINT16_MAX else cur * 0.01
        if 0.0 < d < lo:
            self._count("range_below_min", logging.INFO, " (sensor %s: %d cm)", spec.sensor_id, cur)
            d = lo
        dkey = (index, d)
        detects = self._detects.get(dkey)
        if detects is None:
            if len(self._detects) > 65536:
                self._detects.clear()
            probe = self._probe
            probe[index] = d
            detects = self._detects[dkey] = bool(self.sensors.valid(probe)[index])
            probe[index] = math.nan
        if not detects:
            why = "range_none" if d <= 0.0 else "range_at_max"
            self._count(why, logging.INFO, " (sensor %s: %d cm)", spec.sensor_id, cur)
            d = 0.0
        raw = RangeReading(d, time_boot_ms, t_rx)
        self.ranges[index] = self._filtered(index, raw)
        return True

    def _filtered(self, index: int, reading: RangeReading) -> RangeReading:
        """The reading passed on for this one (`spike_filtered` over the sensor's last
        `median_samples` readings, 0.0 = nothing counted as farther than any distance):
        itself, their median, or the one passed on before (with its own receipt time, so
        readings that keep disagreeing go stale), so a single-reading spike or dropout
        never reaches the planner; the history restarts after a gap of MEDIAN_GAP_S."""
        n = self.median_samples
        if n <= 1:
            return reading
        history = self._history[index]
        if history and reading.t_rx - history[-1][1].t_rx > MEDIAN_GAP_S:
            history.clear()
        d = reading.distance_m
        history.append((d if d > 0 else math.inf, reading))
        if len(history) < n:
            return reading
        k = spike_filtered([key for key, _ in history], self.spike_m)
        if k is None:  # the readings disagree: the last one passed on holds (it ages)
            self._count("range_filtered")
            held = self.ranges[index]
            return held if held is not None else reading
        median = history[k][1]
        if median is reading:
            return reading
        if median.distance_m != reading.distance_m:
            self._count("range_filtered")
        # the median keeps the stamp of the reading it is (its attitude is that time's); its
        # receipt time is the newest reading's (the sensor is as fresh as its last report)
        return RangeReading(median.distance_m, median.time_boot_ms, reading.t_rx)

    # -- queries ----------------------------------------------------------------------------

    @property
    def position_in_doubt(self) -> bool:
        """A position jump is being judged (glitch or estimator reset): until it is, the
        autopilot may already read targets in a frame the loop does not know."""
        return self._jump_since is not None

    def range_vector(
        self, now: float, max_age_s: float, out: FloatArray | None = None
    ) -> FloatArray:
        """Ranges aligned with the sensor table, metres; 0 = nothing, NaN = missing/stale."""
        r = out if out is not None else np.empty(len(self.ranges))
        for i, reading in enumerate(self.ranges):
            r[i] = (
                reading.distance_m
                if reading is not None and now - reading.t_rx <= max_age_s
                else math.nan
            )
        return r

    def paired_ranges(self, now: float, max_age_s: float) -> Pairing:
        """`range_vector` paired with the attitude of the ranges' time (`pairing.py`):
        readings unusable with it are NaN this cycle; counted as input.range_unpaired and
        input.cycle_attitude_untrusted."""
        ranges = self.range_vector(now, max_age_s)
        stamps = [0 if r is None else r.time_boot_ms for r in self.ranges]
        att = self.attitude
        latest = (
            None if att is None or not att.time_boot_ms else self.attitudes.at(att.time_boot_ms)
        )
        pairing = pair_ranges(self.attitudes, ranges, stamps, latest)
        if pairing.untrusted:
            self._count("cycle_attitude_untrusted", logging.WARNING)
        elif pairing.unpaired:
            self.counters["range_unpaired"] += pairing.unpaired
        return pairing

    def stale_sensors(self, now: float, max_age_s: float) -> list[int]:
        """Indices (table order) of sensors with no reading within max_age_s."""
        return [
            i
            for i, reading in enumerate(self.ranges)
            if reading is None or now - reading.t_rx > max_age_s
        ]


def spike_filtered(keys: Sequence[float], spike_m: float) -> int | None:
    """Which of a sensor's last readings (distances oldest first, "nothing" as inf, at
    least one) reaches the planner; None: none (the last one passed on holds).

    A reading agrees with another within spike_m metres (two "nothing"s agree). The newest
    passes when it continues the line through the two before it within spike_m, or agrees
    with at least max(1, (n - 1) // 2) of the others; else their median (the upper of the
    two middle ones for an even count; ties to the older) when it agrees so; else none.
    Noise and a steady change, however fast, pass at once, with the attitude and
    position of their own time; a single spike or dropout never gets through, nor do two
    spikes that disagree; a real step arrives once enough readings agree, (n - 1) / 2
    readings late. With spike_m 0 it is a plain median filter (the newest when it equals
    the median): each reading up to (n - 1) / 2 readings old, measured from where the
    vehicle was then, not where it is."""
    n = len(keys)
    newest = n - 1
    if n == 1:
        return newest
    if spike_m > 0.0 and n >= 3:
        # A steady change, faster than spike_m a reading (a sensor sweeping down a slope):
        # the newest continues the two before it. (The usual reading: no sort needed.)
        x, a, b = keys[newest], keys[newest - 1], keys[newest - 2]
        if abs(x - (2.0 * a - b)) <= spike_m:  # (False where one is inf)
            return newest
    median = sorted(range(n), key=keys.__getitem__)[n // 2]
    if spike_m <= 0.0:
        return newest if keys[newest] == keys[median] else median
    need = max(1, (n - 1) // 2)
    for k in (newest, median):
        x = keys[k]
        agree = sum(1 for j, y in enumerate(keys) if j != k and (x == y or abs(x - y) <= spike_m))
        if agree >= need:
            return k
    return None


_HANDLERS = {
    "HEARTBEAT": Telemetry._heartbeat,
    "ATTITUDE": Telemetry._attitude,
    "GLOBAL_POSITION_INT": Telemetry._global_position,
    "HOME_POSITION": Telemetry._home,
    "DISTANCE_SENSOR": Telemetry._distance_sensor,
}
