"""`companion simulate`: fly a scenario in process and write what a user looks at.

Writes DIR/metrics.json, DIR/trace.csv, DIR/events.txt and (with matplotlib installed)
DIR/fig6.png and DIR/fig7.png; prints the metrics table.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any, TextIO

from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import RunResult, run, write_trace
from companion.sim.scenario import Scenario, load_scenario
from companion.sim.world import World


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    return value


def write_outputs(
    out_dir: Path,
    scenario: Scenario,
    world: World,
    result: RunResult,
    metrics: dict[str, Any],
    plots: bool = True,
) -> list[Path]:
    """metrics.json, trace.csv, events.txt and the figures; returns the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "metrics.json", out_dir / "trace.csv", out_dir / "events.txt"]
    doc = {"scenario": scenario.name, **_json_ready(metrics)}
    written[0].write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    write_trace(written[1], result.trace)
    written[2].write_text(
        "".join(f"{t:9.2f}  {text}\n" for t, text in result.events), encoding="utf-8"
    )
    if plots:
        from companion.harness.plots import PlotParams, write_figures

        written += write_figures(
            out_dir,
            world,
            scenario.route_obj(),
            result.trace,
            PlotParams.from_planner(scenario.params()),
            phi_star=result.phi_star,
            thresholds=result.thresholds,
            memory_xy=result.memory_xy,
            events=result.events,
            title=scenario.name,
        )
    return written


def simulate(
    scenario_path: Path, out_dir: Path, plots: bool = True, stream: TextIO = sys.stdout
) -> int:
    """Run the scenario in process, print the metrics table, write the outputs. Exit code."""
    scenario = load_scenario(scenario_path)
    world = World.from_config(scenario.world, scenario_path.parent)
    interactive = stream.isatty()

    def progress(t: float, to_goal: float) -> None:
        if interactive:
            stream.write(f"\r  t = {t:7.1f} s   distance to goal {to_goal:7.1f} m")
            stream.flush()

    result = run(scenario, world, progress=progress)
    if interactive:
        stream.write("\r" + " " * 60 + "\r")
    m = metrics_mod.for_run(scenario, world, result)
    written = write_outputs(out_dir, scenario, world, result, m, plots)
    stream.write(f"scenario {scenario.name}: {scenario.description}\n")
    stream.write(metrics_mod.format_table(m) + "\n")
    for t, text in result.events:
        stream.write(f"  {t:8.2f} s  {text}\n")
    stream.write("wrote " + ", ".join(str(p) for p in written) + "\n")
    return 0
