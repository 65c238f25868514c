"""A long flight at speed-up: the real service and planner in simulator time, in process.

A minimal lockstep autopilot on an in-memory link (no sockets, no physics: the vehicle is
where the last setpoint put it, over flat ground 2 m below with nothing in the way) drives
the service tick by tick as fast as it answers, so hours of simulated flight take minutes.
The route is a long zig-zag, flown with the flight log on (rotating at 1 MB, 2 files kept).
Every `sample_every_s` of simulated time it records the number of Python objects alive
(after a garbage collection), the process's resident memory and the mean CPU time of a
service cycle (tick sent to answer received; process time, so other load on the machine
does not count); `soak()` returns the samples and the fitted
growth per hour. (tracemalloc would slow every cycle ~4x, so it is not used here.)

Run: `python -m tests.reliability_soak HOURS` (prints a JSON summary).
"""

from __future__ import annotations

import asyncio
import gc
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from companion.config import parse_config
from companion.geo import GeoPoint, LocalFrame
from companion.service import Service, memory_pair
from companion.service.codec import MavCodec, mavlink2
from companion.service.notify import SystemdNotifier

M = mavlink2
HOME = GeoPoint(47.397742, 8.545594, 488.0)
H_D = 2.0
SENSORS = yaml.safe_load(
    (Path(__file__).resolve().parents[1] / "config" / "sensors" / "paper-11.yaml").read_text()
)


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _ranges_cm(spec: dict[str, Any], z: float) -> int:
    """Flat ground at z = 0: surface sensors (45 degrees down) see it, the others nothing."""
    if spec["role"] == "surface":
        return round(z / math.cos(math.radians(45.0)) * 100)
    return 0


async def soak(hours: float, log_dir: Path, sample_every_s: float = 600.0) -> dict[str, Any]:
    dt = 0.05
    legs = max(4, int(hours * 3600 / 50) + 4)  # legs of 20 m and ~100 m at ~1 m/s
    points = [[100.0 * (i // 2 + 1), 20.0 * (i % 2)] for i in range(legs)]
    cfg = parse_config(
        {
            "link": {"connection": "udpin:127.0.0.1:0"},
            "control": {"time_source": "sim", "rate_hz": 1 / dt, "min_engage_height_m": 1.0},
            "route": {"source": "config", "points": points},
            "planner": {"h_d_m": H_D, "d_min_m": 2.0, "phi_max_rad": 0.6, "v_d_mps": 1.0},
            "sensors": SENSORS,
            "logging": {"flight_log_dir": str(log_dir), "max_file_mb": 1.0, "keep_files": 2},
            "statustext": {"max_per_s": 50, "burst": 50},
        }
    )
    a, b = memory_pair()
    svc = Service(cfg, a, notifier=SystemdNotifier({}))
    ap = MavCodec(1, 1)
    frame = LocalFrame(HOME)
    pos = np.array([0.0, 0.0, H_D])
    yaw_enu = 0.0
    answered = asyncio.Event()
    answer_ts = [0]

    def on_bytes(data: bytes, _peer: Any) -> None:
        nonlocal pos, yaw_enu
        for msg in ap.decode(data):
            kind = msg.get_type()
            if kind == "TIMESYNC" and msg.tc1 != 0:
                answer_ts[0] = int(msg.ts1)
                answered.set()
            elif kind == "COMMAND_LONG":
                b.send(ap.encode(M.MAVLink_command_ack_message(msg.command, 0, 0, 0, 1, 191)))
                if int(msg.command) == 512:
                    send_home()
            elif kind == "SET_POSITION_TARGET_GLOBAL_INT":
                e, n, _ = frame.to_enu(GeoPoint(msg.lat_int * 1e-7, msg.lon_int * 1e-7, 0.0))
                pos = np.array([e, n, float(msg.alt)])  # frame 6: above home
                yaw_enu = math.pi / 2 - float(msg.yaw)

    def send_home() -> None:
        b.send(
            ap.encode(
                M.MAVLink_home_position_message(
                    round(HOME.lat_deg * 1e7), round(HOME.lon_deg * 1e7),
                    round(HOME.alt_m * 1000), 0, 0, 0, [1, 0, 0, 0], 0, 0, 0,
                )
            )
        )  # fmt: skip

    await b.open(on_bytes)
    task = asyncio.create_task(svc.run())
    while a._receiver is None:  # the service has opened its end
        await asyncio.sleep(0.01)
    samples: list[dict[str, float]] = []
    steps = int(hours * 3600 / dt)
    per = int(sample_every_s / dt)
    cycle_cpu = 0.0
    wall0 = time.monotonic()
    try:
        for k in range(1, steps + 1):
            t = k * dt
            tb = int(t * 1000)
            if k % 20 == 1:  # 1 Hz heartbeat: GUIDED, armed
                b.send(ap.encode(M.MAVLink_heartbeat_message(2, 3, 129 | 1, 4, 4, 3)))
            geo = frame.to_geodetic(*(float(v) for v in pos))
            b.send(ap.encode(M.MAVLink_attitude_message(tb, 0, 0, math.pi / 2 - yaw_enu, 0, 0, 0)))
            b.send(
                ap.encode(
                    M.MAVLink_global_position_int_message(
                        tb, round(geo.lat_deg * 1e7), round(geo.lon_deg * 1e7),
                        round(geo.alt_m * 1000), round(pos[2] * 1000), 0, 0, 0, 0,
                    )
                )
            )  # fmt: skip
            for s in SENSORS:
                b.send(
                    ap.encode(
                        M.MAVLink_distance_sensor_message(
                            tb, 10, round(s["max_range_m"] * 100), _ranges_cm(s, pos[2]),
                            0, s["id"], 100, 0, 0, 0, [0, 0, 0, 0],
                        )
                    )
                )  # fmt: skip
            if k % 40 == 1:
                send_home()
            ns = round(t * 1e9)
            answered.clear()
            c0 = time.process_time()
            b.send(ap.encode(M.MAVLink_timesync_message(0, ns)))
            while answer_ts[0] != ns:
                await asyncio.wait_for(answered.wait(), 5.0)
                answered.clear()
            cycle_cpu += time.process_time() - c0
            if k % per == 0:
                samples.append(
                    {
                        "t_h": t / 3600,
                        "objects": float(len(gc.get_objects())) if gc.collect() >= 0 else 0.0,
                        "rss_mb": _rss_bytes() / 1e6,
                        "cycle_ms": 1000 * cycle_cpu / per,
                        "engaged": float(svc.status().owner == "engaged"),
                        "x_m": float(pos[0]),
                    }
                )
                cycle_cpu = 0.0
    finally:
        svc.stop()
        await asyncio.wait_for(task, 10)
    wall = time.monotonic() - wall0
    return {
        "hours": hours,
        "wall_s": wall,
        "samples": samples,
        "counters": svc.counter_values(),
        **growth(samples),
    }


def growth(samples: list[dict[str, float]]) -> dict[str, float]:
    """Least-squares slopes per hour, ignoring the first sample (warm-up)."""
    s = samples[1:] if len(samples) > 3 else samples
    if len(s) < 2:
        return {}
    t = np.array([x["t_h"] for x in s])
    out = {}
    for key in ("objects", "rss_mb", "cycle_ms"):
        y = np.array([x[key] for x in s])
        out[f"{key}_per_h"] = float(np.polyfit(t, y, 1)[0])
        out[f"{key}_first"] = float(y[0])
        out[f"{key}_last"] = float(y[-1])
    return out


if __name__ == "__main__":
    import json
    import sys
    import tempfile

    hours = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0
    every = float(sys.argv[2]) if len(sys.argv) > 2 else 600.0
    with tempfile.TemporaryDirectory() as d:
        result = asyncio.run(soak(hours, Path(d), every))
    result.pop("counters")
    print(json.dumps(result, indent=1))
