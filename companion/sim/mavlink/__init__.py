"""A MAVLink vehicle simulator over UDP that behaves like ArduPilot or PX4 on the wire.

    from companion.sim.mavlink import MavlinkSimConfig, SimServer

    server = SimServer.from_scenario(scenario, base_dir, port=0, speedup=10.0)
    await server.start(); port = server.port
    await server.run_until(30.0)   # or server.start_background()
    await server.close()

Modules: `config` (the scenario's `mavlink:` section), `personality` (ArduCopter / ArduSub /
PX4 heartbeat, modes, result codes), `setpoints` (SET_POSITION_TARGET_GLOBAL_INT per
autopilot), `autopilot` (modes, arming, takeoff, failsafes), `control` (the position
controller's reference), `rangefinder` (DISTANCE_SENSOR from ray casts), `telemetry`
(message scheduling and filling), `mission` (mission protocol), `faults`, `clock` (pacing),
`codec`, `server` (the UDP endpoint, lockstep), `threaded` (run it beside blocking clients),
`bridge` (DISTANCE_SENSOR for a real SITL). See docs/simulator.md.
"""

from companion.sim.mavlink.config import (
    BridgeConfig,
    FaultsConfig,
    HomeConfig,
    LinkFaultConfig,
    LockstepConfig,
    MavlinkSimConfig,
    ModeChangeFault,
    MotionLimits,
    PersonalityName,
    PositionJumpFault,
    RebootFault,
    SensorFaultConfig,
)
from companion.sim.mavlink.server import SimServer, SimStats, TruthSample
from companion.sim.mavlink.threaded import ThreadedSim

__all__ = [
    "BridgeConfig",
    "FaultsConfig",
    "HomeConfig",
    "LinkFaultConfig",
    "LockstepConfig",
    "MavlinkSimConfig",
    "ModeChangeFault",
    "MotionLimits",
    "PersonalityName",
    "PositionJumpFault",
    "RebootFault",
    "SensorFaultConfig",
    "SimServer",
    "SimStats",
    "ThreadedSim",
    "TruthSample",
]
