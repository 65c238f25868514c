"""sim.sensing: the rays of a sensor table, beams alone and with sectors."""

from __future__ import annotations

import numpy as np

from companion.planner.sensors import sector_fan_flu
from companion.sim.sensing import SECTOR_RAYS, SensorFan


def _fans(u: np.ndarray, fov: np.ndarray) -> np.ndarray:
    return np.vstack(
        [
            sector_fan_flu(b, float(w), SECTOR_RAYS if w > 0 else 1)
            for b, w in zip(u, fov, strict=True)
        ]
    )


def test_beams_are_their_boresights_as_the_sector_fans_give_them() -> None:
    rng = np.random.default_rng(2)
    u = rng.normal(size=(7, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    fan = SensorFan(u, np.zeros(7))
    assert fan.narrow and fan.owner.tolist() == list(range(7))
    np.testing.assert_array_equal(fan.directions_flu, _fans(u, np.zeros(7)))
    fan.directions_flu[0, 0] = 5.0  # its own copy
    assert u[0, 0] != 5.0


def test_sectors_and_beams_together() -> None:
    rng = np.random.default_rng(3)
    u = rng.normal(size=(5, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    fov = np.array([0.0, np.pi / 4, 0.0, np.pi / 4, np.pi / 8])
    fan = SensorFan(u, fov)
    assert not fan.narrow
    np.testing.assert_array_equal(fan.directions_flu, _fans(u, fov))
    k = SECTOR_RAYS
    assert fan.owner.tolist() == [0] + [1] * k + [2] + [3] * k + [4] * k
    assert fan.starts.tolist() == [0, 1, 1 + SECTOR_RAYS, 2 + SECTOR_RAYS, 2 + 2 * SECTOR_RAYS]
