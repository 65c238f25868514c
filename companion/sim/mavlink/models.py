"""What the MAVLink simulator needs from the world and the vehicle model.

`sim.world.World` and the models of `companion.sim.vehicle` satisfy these protocols; tests may pass
simpler stand-ins. Frames: world ENU, metres; see companion.planner.types.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from companion.planner.types import Setpoint, VehicleState


class RangeWorld(Protocol):
    def height(self, x: Any, y: Any) -> Any:
        """Terrain z (metres, ENU) at x, y."""
        ...

    def raycast(self, origins: Any, directions: Any, max_range: Any) -> Any:
        """Ranges (n,) in metres along unit directions (n, 3) from origins (n, 3); inf = no
        hit within max_range."""
        ...


class VehicleModel(Protocol):
    def step(self, setpoint: Setpoint, dt_s: float) -> VehicleState:
        """Advance by dt_s towards the setpoint; returns the new state."""
        ...


VehicleFactory = Callable[[VehicleState], VehicleModel]
"""Makes a vehicle model starting at the given state (called at every lift-off)."""
