"""sim.mavlink.server's command table: the COMMAND_ACK result of the commands the flight
tests do not reach, over real UDP on 127.0.0.1 with a plain pymavlink client."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.mavlink import ThreadedSim
from tests.test_mavlink_sim_support import Client, make_server

pytestmark = [pytest.mark.sim, pytest.mark.timeout(60)]
R = mavlink


def test_unknown_commands_and_bad_reboot_params_are_unsupported() -> None:
    with ThreadedSim(lambda: make_server()) as sim, Client(sim.port) as c:
        c.recv("HEARTBEAT")
        assert c.command(R.MAV_CMD_DO_CHANGE_SPEED, 1, 5) == R.MAV_RESULT_UNSUPPORTED
        assert c.command(R.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 2) == R.MAV_RESULT_UNSUPPORTED


def test_capabilities_are_answered_after_the_ack() -> None:
    with ThreadedSim(lambda: make_server()) as sim, Client(sim.port) as c:
        c.recv("HEARTBEAT")
        assert c.command(R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1) == R.MAV_RESULT_ACCEPTED
        version = c.recv("AUTOPILOT_VERSION")
        assert version.flight_sw_version >> 24 == 4  # ArduCopter 4.x
        assert version.flight_sw_version & 0xFF == R.FIRMWARE_VERSION_TYPE_DEV


def test_a_submarine_cannot_land_and_returns_by_surfacing() -> None:
    make = lambda: make_server(personality="ardusub")  # noqa: E731
    with ThreadedSim(make) as sim, Client(sim.port) as c:
        c.recv("HEARTBEAT")
        assert c.command(R.MAV_CMD_NAV_LAND) == R.MAV_RESULT_UNSUPPORTED
        assert c.command(R.MAV_CMD_NAV_RETURN_TO_LAUNCH) == R.MAV_RESULT_ACCEPTED
        surface = c.recv("HEARTBEAT", cond=lambda m: m.custom_mode == R.SUB_MODE_SURFACE)
        assert surface.type == R.MAV_TYPE_SUBMARINE


def test_set_home_here_or_at_a_position() -> None:
    with ThreadedSim(lambda: make_server()) as sim, Client(sim.port) as c:
        c.recv("HEARTBEAT")
        home = sim.server.config.home_or_default
        assert c.command(R.MAV_CMD_DO_SET_HOME, 1) == R.MAV_RESULT_ACCEPTED
        north = home.lat_deg + 10.0 / 111_000.0  # about 10 m north
        assert (
            c.command(R.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, north, home.lon_deg, home.alt_m)
            == R.MAV_RESULT_ACCEPTED
        )
        home_enu = np.asarray(sim.server.autopilot.home_enu)
        # COMMAND_LONG carries lat/lon as float32 degrees: about a metre of resolution
        assert home_enu[1] == pytest.approx(10.0, abs=1.5)
        assert abs(home_enu[0]) < 1.5
        assert (
            c.command(R.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, math.nan, home.lon_deg, home.alt_m)
            == R.MAV_RESULT_FAILED
        )
