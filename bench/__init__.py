"""Benchmarks of the planner, the simulator and the service (issues 6 and 14; where both
set a target, issue 14's).

`python -m bench` (or `make bench`) runs them all, prints a table and writes
bench/results.json: every figure with its unit and the issue's target, the raw percentiles
behind it, and the machine, date and commit. Benchmarks never fail on a number; a missed
target is marked in the table. Machines are noisy, so compare figures of one run as ratios.

Modules: `flight` (a timed closed-loop flight), `planner` (Planner.step, steady and
re-planning), `arc` (eq. (5) stepping, exact vs the paper's search), `simulator`
(in-process speed), `raycast` (World.raycast per ray), `service` (the service over UDP
against the MAVLink simulator: latency, jitter, CPU, the pymavlink floor, lockstep speed,
memory over a simulated hour), `report` (table, JSON, machine). Not a benchmark:
`same_flights` (`python -m bench.same_flights record DIR`, then `compare DIR` after a change)
checks that every scenario still flies the same, metrics and full-precision traces.
"""
