"""Worlds, vehicle models and a MAVLink vehicle simulator to fly the companion against."""
