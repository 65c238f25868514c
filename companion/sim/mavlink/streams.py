"""Which messages the simulator streams, by name and MAVLink id (pymavlink's generated ids).

A leaf module: `companion.sim.mavlink.config` validates `rates_hz` against these names and
`companion.sim.mavlink.telemetry` schedules them, so neither imports the other for it.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

STREAMED_MESSAGES: dict[str, int] = {
    "HEARTBEAT": mavlink.MAVLINK_MSG_ID_HEARTBEAT,
    "ATTITUDE": mavlink.MAVLINK_MSG_ID_ATTITUDE,
    "GLOBAL_POSITION_INT": mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "SYS_STATUS": mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    "SYSTEM_TIME": mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
    "DISTANCE_SENSOR": mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,
    "LOCAL_POSITION_NED": mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    "HOME_POSITION": mavlink.MAVLINK_MSG_ID_HOME_POSITION,
    "EXTENDED_SYS_STATE": mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    "TIMESYNC": mavlink.MAVLINK_MSG_ID_TIMESYNC,
}
"""Messages the simulator can stream, by name (also the keys of `rates_hz`), in the order
they go out when due at the same tick: ArduPilot's (its `ap_message` enum, the order in
which a stream bucket is sent: ATTITUDE, then the position, ..., DISTANCE_SENSOR, ...).
TIMESYNC is no stream on ArduPilot (it sends one every 10 s on its own); here it is last."""
NAME_OF_ID = {v: k for k, v in STREAMED_MESSAGES.items()}
