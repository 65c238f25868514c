"""Moved to `harness.metrics`; this name stays for `sim.sitl` until it moves too."""

from harness.metrics import compute, format_table

__all__ = ["compute", "format_table"]
