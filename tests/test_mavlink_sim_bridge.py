"""The SITL sensor bridge against a stand-in SITL (the simulator itself) over UDP."""

from __future__ import annotations

import asyncio
import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.mavlink.bridge import SensorBridge
from companion.sim.mavlink.config import BridgeConfig
from tests.test_mavlink_sim_support import PlaneAndWall, make_server, sensors

pytestmark = [pytest.mark.sim, pytest.mark.timeout(30)]


class _Collector(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.parser = mavlink.MAVLink(None)
        self.messages: list[Any] = []

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.messages.extend(self.parser.parse_buffer(data) or [])


async def _until(cond: Any, timeout_s: float = 10.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not cond():
        if asyncio.get_running_loop().time() > deadline:
            raise TimeoutError("condition not reached")
        await asyncio.sleep(0.01)


async def test_bridge_to_the_companion_as_px4_reports() -> None:
    # The stand-in SITL sends no DISTANCE_SENSOR of its own.
    sitl = make_server(personality="px4", speedup=2.0, rates_hz={"DISTANCE_SENSOR": 0})
    loop = asyncio.get_running_loop()
    companion, collector = await loop.create_datagram_endpoint(
        _Collector, local_addr=("127.0.0.1", 0)
    )
    port = companion.get_extra_info("sockname")[1]
    async with sitl:
        sitl.start_background()
        config = BridgeConfig(
            connect=f"udpout:127.0.0.1:{sitl.port}",
            send_to="companion",
            companion_address=f"127.0.0.1:{port}",
            rate_hz=20.0,
            system_id=1,
            component_id=1,
        )
        bridge = SensorBridge(config, PlaneAndWall(wall_x=10.0), sensors())
        await bridge.start()
        task = loop.create_task(bridge.run(5.0))
        try:
            await _until(lambda: len(collector.messages) >= 10)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await bridge.close()
            companion.close()
    msgs = [m for m in collector.messages if m.get_type() == "DISTANCE_SENSOR"]
    by_id = {m.id: m for m in msgs}
    assert sorted(by_id) == [0, 1, 2, 3, 4]  # PX4 numbers sensors by its own index
    assert msgs[0].get_srcSystem() == 1
    # The stand-in SITL's vehicle sits on the ground at home: the wall is 10 m ahead.
    assert abs(by_id[0].current_distance - 1000) <= 2
    assert abs(by_id[1].current_distance - 1000 / math.cos(math.radians(15))) <= 2
    assert by_id[2].current_distance >= 65534  # PX4: nothing in range
    assert by_id[1].orientation == 100 and any(by_id[1].quaternion)
    assert bridge.core.autopilot_family == "px4" and bridge.core.home is not None


async def test_bridge_to_the_autopilot() -> None:
    sitl = make_server(personality="ardupilot", speedup=2.0)
    async with sitl:
        sitl.start_background()
        config = BridgeConfig(connect=f"udpout:127.0.0.1:{sitl.port}", rate_hz=20.0)
        bridge = SensorBridge(config, PlaneAndWall(wall_x=10.0), sensors())
        await bridge.start()
        task = asyncio.get_running_loop().create_task(bridge.run(5.0))
        try:
            # ArduPilot streams nothing until asked: the bridge asks, then sends.
            await _until(lambda: sitl.stats.received_by_type["DISTANCE_SENSOR"] >= 10)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await bridge.close()
    assert sitl.stats.received_by_type["COMMAND_LONG"] >= 3
    assert bridge.core.autopilot_family == "ardupilot"
