"""What drives a flight: the in-process closed loop, the flight over MAVLink against the
simulator, metrics, figures and the random-world sweep.

Doors: the harness imports `companion` (planner, config, service) and `sim` (worlds, vehicles,
the MAVLink simulator); neither of them imports the harness.
"""
