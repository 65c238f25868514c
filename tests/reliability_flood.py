"""A flooding autopilot in a separate process: valid MAVLink datagrams at a set rate.

Run as `python -m tests.reliability_flood HOST PORT RATE SECONDS BOOT`: sends ATTITUDE,
GLOBAL_POSITION_INT and DISTANCE_SENSOR (ids 0-2) from system 1 component 1, one message per
datagram as autopilots do, time-stamped (time_boot_ms) from BOOT on the system's monotonic
clock (the fake autopilot's boot time, so both agree), paced in 10 ms batches; prints the
number sent. A separate process, so the flood does not share the service's interpreter.
"""

from __future__ import annotations

import socket
import sys
import time

from pymavlink.dialects.v20 import ardupilotmega as m

HOME = (47.397742, 8.545594, 488.0)


def main(host: str, port: int, rate: float, seconds: float, boot_s: float) -> int:
    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
    t0 = time.monotonic()
    sent = 0
    while (now := time.monotonic()) - t0 < seconds:
        due = int((now - t0) * rate)
        while sent < due:
            boot = int((time.monotonic() - boot_s) * 1000)
            k = sent % 5
            if k == 0:
                msg = m.MAVLink_attitude_message(boot, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            elif k == 1:
                msg = m.MAVLink_global_position_int_message(
                    boot, round(HOME[0] * 1e7), round(HOME[1] * 1e7), 493_000, 5_000, 0, 0, 0, 0
                )
            else:
                sid = k - 2
                msg = m.MAVLink_distance_sensor_message(
                    boot, 10, 1000, 700, 0, sid, (0, 39, 100)[sid], 0, 0, 0, [0, 0, 0, 0]
                )
            s.sendto(msg.pack(mav), (host, port))
            sent += 1
        time.sleep(0.01)
    print(sent)
    return 0


if __name__ == "__main__":
    a = sys.argv
    sys.exit(main(a[1], int(a[2]), float(a[3]), float(a[4]), float(a[5])))
