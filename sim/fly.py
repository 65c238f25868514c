"""Moved to `harness.fly`; this name stays for `sim.sitl` until it moves too.

Importing it imports the service (as `sim.sitl` does); nothing else under `sim` imports it.
"""

from harness.fly import trace_from_log

__all__ = ["trace_from_log"]
