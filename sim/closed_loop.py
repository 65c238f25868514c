"""Moved to `harness.closed_loop`; this name stays for `sim.sitl` until it moves too."""

from harness.closed_loop import TRACE_COLUMNS, RunResult

__all__ = ["TRACE_COLUMNS", "RunResult"]
