"""Which autopilot this companion flies: found from heartbeats before the lock, watched after.

Before the lock, each HEARTBEAT offered by the connection is checked against the config
(system id, component id, autopilot type); with `autopilot.system_id: auto` the only
autopilot heard for `auto_id_listen_s` is chosen, none if several are. After the lock, the
heartbeat of another autopilot (not a ground station or onboard computer) is noticed: with
system_id auto it blocks any take-over, as this companion may not be where it thinks.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from companion.config import ServiceConfig
from companion.service.codec import MavCodec, MAVLinkMessage, mavlink2
from companion.service.connection import Connection
from companion.service.identity import companion_system_id
from companion.service.modes import AutopilotKind, autopilot_kind
from companion.service.notify import SystemdNotifier
from companion.service.setpoints import SetpointFrame
from companion.service.statustext import Severity

log = logging.getLogger("companion.service")

_NOT_AUTOPILOTS = frozenset({mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER})
"""MAV_TYPEs of a heartbeat that is not a vehicle's, whatever its MAV_AUTOPILOT says."""


@dataclass(slots=True)
class AutopilotInfo:
    """The autopilot locked onto: None/0 until then."""

    kind: AutopilotKind | None = None
    vehicle_type: int = 0
    """MAV_TYPE of its heartbeat."""
    setpoint_frame: SetpointFrame | None = None


def setpoint_frame_for(configured: str, kind: AutopilotKind) -> SetpointFrame:
    """`autopilot.setpoint_frame` (auto, global, relative) as the MAV_FRAME setpoints use."""
    if configured == "auto":
        return (
            SetpointFrame.GLOBAL if kind is AutopilotKind.PX4 else SetpointFrame.GLOBAL_RELATIVE_ALT
        )
    return SetpointFrame.GLOBAL if configured == "global" else SetpointFrame.GLOBAL_RELATIVE_ALT


class AutopilotFinder:
    """Connection callbacks `on_unlocked` and `on_other`; `seen` is set at the lock."""

    def __init__(
        self,
        cfg: ServiceConfig,
        conn: Connection,
        codec: MavCodec,
        info: AutopilotInfo,
        *,
        notifier: SystemdNotifier,
        counters: Counter[str],
        say: Callable[[str, Severity], None],
    ) -> None:
        self.cfg = cfg
        self.conn = conn
        self.codec = codec
        self.info = info
        self.notifier = notifier
        self.counters = counters
        self._say = say
        self.seen = asyncio.Event()
        self.stranger_blocks = False
        """A second autopilot was heard with system_id auto: no take-over, no auto start."""
        self._heard: dict[int, float] = {}
        self._listen_since: float | None = None
        self._ambiguous_said: list[int] = []
        self._strangers: set[int] = set()

    def on_unlocked(self, msg: MAVLinkMessage, t_rx: float) -> None:
        """A HEARTBEAT before the lock: lock onto it if it is the autopilot configured."""
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        ap = self.cfg.autopilot
        if isinstance(ap.system_id, int) and src_sys != ap.system_id:
            return
        if src_comp != ap.component_id:
            return
        kind = autopilot_kind(int(msg.autopilot))
        if kind is None or (ap.type != "auto" and kind.value != ap.type):
            self.counters["unsupported_autopilot"] += 1
            if self.counters["unsupported_autopilot"] == 1:
                log.warning(
                    "ignoring system %d: autopilot type %d (%s expected)",
                    src_sys,
                    int(msg.autopilot),
                    ap.type,
                )
            return
        if ap.system_id == "auto" and not self._choose(src_sys, t_rx):
            return
        info = self.info
        info.kind = kind
        info.vehicle_type = int(msg.type)
        self.conn.lock(src_sys, src_comp)
        sid = companion_system_id(self.cfg.identity.system_id, src_sys)
        self.codec.set_source(sid, self.cfg.identity.component_id)
        info.setpoint_frame = setpoint_frame_for(ap.setpoint_frame, kind)
        log.info(
            "autopilot: %s (MAV_TYPE %d) at system %d component %d; we are %d/%d; "
            "setpoints in frame %d",
            kind.value,
            info.vehicle_type,
            src_sys,
            src_comp,
            sid,
            self.cfg.identity.component_id,
            int(info.setpoint_frame),
        )
        self.seen.set()

    def _choose(self, src_sys: int, t_rx: float) -> bool:
        """`autopilot.system_id: auto`: True when `src_sys` is the only autopilot heard for
        auto_id_listen_s since the first heartbeat; with more than one, choose none."""
        listen = self.cfg.autopilot.auto_id_listen_s
        self._heard[src_sys] = t_rx
        if self._listen_since is None:
            self._listen_since = t_rx
            if listen > 0:
                log.info(
                    "autopilot heartbeat from system %d: listening %.1f s for others",
                    src_sys,
                    listen,
                )
        if t_rx - self._listen_since < listen:
            return False
        recent = sorted(s for s, t in self._heard.items() if t_rx - t <= 2 * listen + 1.0)
        if len(recent) > 1:
            if self._ambiguous_said != recent:
                self._ambiguous_said = recent
                log.error(
                    "autopilots of systems %s heard and autopilot.system_id is auto: not "
                    "choosing one; set autopilot.system_id to the one this companion is wired to",
                    ", ".join(map(str, recent)),
                )
                self.notifier.status(f"several autopilots heard: {recent}; set system_id")
            return False
        return True

    def on_other(self, msg: MAVLinkMessage, t_rx: float) -> None:
        """A heartbeat of another system after the lock: another autopilot means this
        companion may not be where it thinks; with system_id auto, no take-over from now."""
        if autopilot_kind(int(msg.autopilot)) is None or int(msg.type) in _NOT_AUTOPILOTS:
            return
        sys_id = msg.get_srcSystem()
        if sys_id in self._strangers:
            return
        self._strangers.add(sys_id)
        if self.cfg.autopilot.system_id == "auto":
            self.stranger_blocks = True
            log.error(
                "a second autopilot (system %d) is heard besides system %s: no take-over and no "
                "auto start until autopilot.system_id is set",
                sys_id,
                self.conn.target_system,
            )
            self._say(f"second autopilot {sys_id} heard: set system_id", Severity.CRITICAL)
        else:
            log.warning("another autopilot (system %d) is heard; ignored", sys_id)


__all__ = ["AutopilotFinder", "AutopilotInfo", "setpoint_frame_for"]
