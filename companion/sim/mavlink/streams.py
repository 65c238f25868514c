"""Which messages the simulator streams, by name and MAVLink id (pymavlink's generated ids).

A leaf module: `companion.sim.mavlink.config` validates `rates_hz` against these names and
`companion.sim.mavlink.telemetry` schedules them, so neither imports the other for it.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

STREAMED_MESSAGES: dict[str, int] = {
    "HEARTBEAT": mavlink.MAVLINK_MSG_ID_HEARTBEAT,
    "SYS_STATUS": mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    "SYSTEM_TIME": mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
    "ATTITUDE": mavlink.MAVLINK_MSG_ID_ATTITUDE,
    "GLOBAL_POSITION_INT": mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "LOCAL_POSITION_NED": mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    "HOME_POSITION": mavlink.MAVLINK_MSG_ID_HOME_POSITION,
    "DISTANCE_SENSOR": mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,
    "EXTENDED_SYS_STATE": mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    "TIMESYNC": mavlink.MAVLINK_MSG_ID_TIMESYNC,
}
"""Messages the simulator can stream, by name (also the keys of `rates_hz`)."""
NAME_OF_ID = {v: k for k, v in STREAMED_MESSAGES.items()}
