"""Terrain-following, obstacle-avoiding path planning for ArduPilot and PX4 companions."""

__version__ = "0.1.0"
