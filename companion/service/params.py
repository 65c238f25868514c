"""The planner's tunables as MAVLink parameters of the companion's own component.

A ground station (QGroundControl, MAVProxy) reads and changes them with MAVLink's parameter
protocol, addressed to our (system id, component id):

    PARAM_REQUEST_LIST  -> every parameter as PARAM_VALUE (param_count, param_index)
    PARAM_REQUEST_READ  -> one PARAM_VALUE, by param_id (param_index -1) or by param_index
    PARAM_SET           -> PARAM_VALUE with the value in force afterwards: the new one when
                           accepted, the old one when refused (the reason goes to the pilot
                           as a STATUSTEXT and to the log)

Requests to the broadcast ids (target system 0, target component MAV_COMP_ID_ALL) are
answered too, as the protocol asks of every component; requests to other components are
left alone. Every value is MAV_PARAM_TYPE_REAL32, in the `planner:` section's units (metres,
radians, seconds, m/s); ids carry the prefix PARAM_PREFIX and are at most 16 characters.

A PARAM_SET is validated by the config's own model (`companion.config.planner_with`) and
applied through the planner's host (`PlannerHost.retune`), the one owner of the values at
run time: it reaches the planner at the next cycle, whole or not at all. A value the planner
cannot take now is refused with the reason. Unknown ids are not answered (there is no value
to report); a PARAM_SET of one addressed to our component (not to all) is said to the pilot,
as an id asked of every component is most likely another's (the autopilot's). Accepted
values can be written back to the config file (`persist`).
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from companion.config import ConfigError, load_config
from companion.service.codec import MAVLinkMessage, mavlink2
from companion.service.statustext import Severity
from companion.tuning import PlannerConfig

log = logging.getLogger("companion.service.params")

PARAM_PREFIX = "TFC_"
"""Prefix of every parameter id (terrain-following companion)."""
PARAM_ID_LEN = 16
MAV_PARAM_TYPE_REAL32: int = mavlink2.MAV_PARAM_TYPE_REAL32
MAV_COMP_ID_ALL: int = mavlink2.MAV_COMP_ID_ALL
REQUESTS = frozenset({"PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"})


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One MAVLink parameter: its id and the `planner:` key it stands for."""

    param_id: str
    key: str
    unit: str
    meaning: str


PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("TFC_H_D", "h_d_m", "m", "H_d, the desired height above the surface"),
    ParamSpec("TFC_V_D", "v_d_mps", "m/s", "v_d, the desired speed along the path"),
    ParamSpec("TFC_D_MIN", "d_min_m", "m", "D_min, the least distance kept from obstacles"),
    ParamSpec("TFC_PHI_MAX", "phi_max_rad", "rad", "phi_max, the steepest climb or descent"),
    ParamSpec("TFC_TURN_R_MIN", "min_turn_radius_m", "m", "least turn radius of a path"),
    ParamSpec("TFC_LAT_ACC_MAX", "lat_accel_max_mps2", "m/s^2", "lateral acceleration bound"),
    ParamSpec("TFC_ACC_MAX", "accel_max_mps2", "m/s^2", "speed ramp and braking budget"),
    ParamSpec("TFC_CLR_MARGIN", "clearance_margin_m", "m", "margin added to D_min in plans"),
    ParamSpec("TFC_LOOKAHEAD", "lookahead_m", "m", "how far ahead conflicts are checked"),
    ParamSpec("TFC_REACT_T", "reaction_time_s", "s", "reaction allowance of a stop"),
    ParamSpec("TFC_GOAL_TOL", "goal_tolerance_m", "m", "distance that counts as arrived"),
    ParamSpec("TFC_LEASH", "leash_m", "m", "how far the vehicle may be from the setpoint"),
)
"""The table, in param_index order (a new entry goes at the end: indices are kept)."""

_BY_ID = {p.param_id: i for i, p in enumerate(PARAMS)}


class Tunable(Protocol):
    """What the parameter server needs of the planner's host."""

    @property
    def tuning(self) -> PlannerConfig: ...

    def retune(self, changes: Mapping[str, float]) -> None: ...


class Ids(Protocol):
    """Our MAVLink identity (the codec's, which follows the autopilot's system id)."""

    @property
    def system_id(self) -> int: ...

    @property
    def component_id(self) -> int: ...


Send = Callable[[MAVLinkMessage], None]
Say = Callable[[str, Severity], None]
Persist = Callable[[Mapping[str, float]], None]


def from_real32(value: float) -> float:
    """The number a ground station meant by a REAL32 value: the shortest decimal that
    rounds to the same float32 (0.1 arrives as 0.100000001490116...)."""
    return float(str(np.float32(value))) if math.isfinite(value) else float(value)


def _param_id(raw: object) -> str:
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.split("\x00", 1)[0][:PARAM_ID_LEN]


class ParamServer:
    """Answers the parameter protocol for our component (see the module's docstring).

    host: the owner of the values. ids: our system and component id, read at each request.
    send: where PARAM_VALUE goes (the connection). say: STATUSTEXT and log. persist: called
    with every accepted change ({planner key: value}), e.g. to write the config file; a
    failure there is said, the change stays in force.
    """

    def __init__(
        self, host: Tunable, ids: Ids, send: Send, say: Say, persist: Persist | None = None
    ) -> None:
        self.host = host
        self.ids = ids
        self.send = send
        self.say = say
        self.persist = persist
        self.counters: dict[str, int] = {"requests": 0, "set": 0, "refused": 0, "unknown": 0}

    # --- receive ---------------------------------------------------------------------------

    def handle(self, msg: MAVLinkMessage) -> bool:
        """Take a parameter request (True); anything else is not ours to take (False). A
        request for another component is taken and dropped: none of ours is for it."""
        mtype = msg.get_type()
        if mtype not in REQUESTS:
            return False
        if not self._for_us(int(msg.target_system), int(msg.target_component)):
            return True
        self.counters["requests"] += 1
        if mtype == "PARAM_REQUEST_LIST":
            for i in range(len(PARAMS)):
                self._send_value(i)
            return True
        # an id we do not have, asked of every component, is some other component's
        mine = int(msg.target_component) == self.ids.component_id
        if mtype == "PARAM_REQUEST_READ":
            self._read(int(msg.param_index), _param_id(msg.param_id), mine)
        else:
            self._set(_param_id(msg.param_id), float(msg.param_value), int(msg.param_type), mine)
        return True

    def _for_us(self, target_system: int, target_component: int) -> bool:
        ids = self.ids
        return target_system in (0, ids.system_id) and target_component in (
            MAV_COMP_ID_ALL,
            ids.component_id,
        )

    def _read(self, index: int, param_id: str, mine: bool) -> None:
        if index >= 0:
            if index < len(PARAMS):
                self._send_value(index)
            else:
                log.debug("PARAM_REQUEST_READ index %d: no such parameter", index)
            return
        i = _BY_ID.get(param_id)
        if i is None:
            if mine:
                self.counters["unknown"] += 1
                log.info("PARAM_REQUEST_READ %r: no such parameter", param_id)
            return
        self._send_value(i)

    def _set(self, param_id: str, value: float, param_type: int, mine: bool) -> None:
        i = _BY_ID.get(param_id)
        if i is None:
            if mine:
                self.counters["unknown"] += 1
                self.say(f"cannot set {param_id!r}: no such parameter", Severity.WARNING)
            return
        spec = PARAMS[i]
        old = self.value(i)
        wanted = from_real32(value)
        why = ""
        if param_type != MAV_PARAM_TYPE_REAL32:
            why = f"type {param_type}, not REAL32 ({MAV_PARAM_TYPE_REAL32})"
        else:
            try:
                self.host.retune({spec.key: wanted})
            except ValueError as exc:
                why = str(exc)
        if why:
            self.counters["refused"] += 1
            self.say(f"{param_id} {wanted:g} refused: {why}", Severity.WARNING)
        else:
            self.counters["set"] += 1
            if self.value(i) != old:
                self.say(f"{param_id} set to {self.value(i):g} (was {old:g})", Severity.INFO)
                self._persist({spec.key: self.value(i)})
        self._send_value(i)  # the value in force: the new one, or the old one when refused

    def _persist(self, changes: Mapping[str, float]) -> None:
        if self.persist is None:
            return
        try:
            self.persist(changes)
        except (OSError, ValueError) as exc:
            self.say(f"parameter not saved to the config: {exc}", Severity.WARNING)

    # --- send ------------------------------------------------------------------------------

    def value(self, index: int) -> float:
        """The value in force of parameter `index` (the host's, its `planner:` units)."""
        return float(getattr(self.host.tuning, PARAMS[index].key))

    def _send_value(self, index: int) -> None:
        self.send(param_value_message(index, self.value(index)))


# --- writing accepted values back to the config file ---------------------------------------

_SECTION = re.compile(r"^planner:[ \t]*(#.*)?$")


def write_planner_values(path: Path, changes: Mapping[str, float]) -> None:
    """Write `changes` ({planner key: value}) into the `planner:` section of the YAML config
    at `path`, atomically (a temporary file in the same directory, checked, then renamed
    over it) and keeping every other line, comments included: a key's line has its value
    replaced (its comment kept), a missing key is added at the top of the section, a missing
    section at the end of the file. ValueError, and the file untouched, when the section is
    in flow style (`planner: {...}`) or the edited file would not load as these values."""
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    start = next((i for i, ln in enumerate(lines) if _SECTION.match(ln.rstrip("\r\n"))), None)
    if start is None:
        if any(ln.startswith("planner:") for ln in lines):
            raise ValueError("its planner: section is in flow style; edit that file by hand")
        lines.append("planner:\n")
        start = len(lines) - 1
    end = start + 1
    while end < len(lines) and (lines[end][:1] in (" ", "\t") or not lines[end].strip()):
        end += 1
    indent = "  "
    for ln in lines[start + 1 : end]:
        if ln.strip() and not ln.lstrip().startswith("#"):
            indent = ln[: len(ln) - len(ln.lstrip())]
            break
    for key, value in changes.items():
        entry = re.compile(rf"^{re.escape(indent)}{re.escape(key)}:[ \t]*([^#\r\n]*?)([ \t]*#.*)?$")
        for i in range(start + 1, end):
            m = entry.match(lines[i].rstrip("\r\n"))
            if m is not None:
                comment = m.group(2) or ""
                lines[i] = f"{indent}{key}: {value!r}{comment}\n"
                break
        else:
            lines.insert(start + 1, f"{indent}{key}: {value!r}\n")
            end += 1
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write("".join(lines))
            f.flush()
            os.fsync(f.fileno())
        try:
            planner = load_config(tmp).planner
        except ConfigError as exc:
            raise ValueError(f"the edited file would not load: {exc}") from None
        wrong = [k for k, v in changes.items() if getattr(planner, k) != v]
        if wrong:
            raise ValueError(f"could not place {', '.join(wrong)} in its planner: section")
        shutil.copymode(path, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def persist_to(path: Path) -> Persist:
    """A `ParamServer.persist` writing accepted values into the config file at `path`."""

    def persist(changes: Mapping[str, float]) -> None:
        write_planner_values(path, changes)
        log.info("saved %s to %s", ", ".join(f"planner.{k}" for k in changes), path)

    return persist


def param_value_message(index: int, value: float) -> MAVLinkMessage:
    """PARAM_VALUE of table entry `index` with `value` (REAL32)."""
    pid = PARAMS[index].param_id.encode("ascii")
    return mavlink2.MAVLink_param_value_message(
        pid, value, MAV_PARAM_TYPE_REAL32, len(PARAMS), index
    )


def param_table_markdown() -> str:
    """The parameter table for the docs (id, config key, unit, meaning, config range)."""
    fields = PlannerConfig.model_fields
    rows = ["| id | `planner:` key | unit | range | meaning |", "| --- | --- | --- | --- | --- |"]
    for p in PARAMS:
        bounds = []
        for m in fields[p.key].metadata:
            for name, sign in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
                v = getattr(m, name, None)
                if v is not None:
                    bounds.append(f"{sign} {v:.6g}")
        rows.append(
            f"| `{p.param_id}` | `{p.key}` | {p.unit} | {', '.join(bounds)} | {p.meaning} |"
        )
    return "\n".join(rows)


__all__ = [
    "MAV_PARAM_TYPE_REAL32",
    "PARAMS",
    "PARAM_PREFIX",
    "ParamServer",
    "ParamSpec",
    "Tunable",
    "from_real32",
    "param_table_markdown",
    "param_value_message",
    "persist_to",
    "write_planner_values",
]
