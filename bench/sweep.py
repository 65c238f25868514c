"""Random-world sweep throughput: worlds per minute through `companion sweep`'s own executor
(a process pool of 2 workers, the default on this 2-core class of machine), and (not in a quick
run) the same tasks in this process (1 worker) for the pool's speed-up measured in the same
run.

Each task is one seeded world flown in process (`companion.sim.sweep.run_task`: generate the world,
ray-cast the layout's sensors, the planner, the ideal vehicle model, the metrics), the paper's
sensor layout. Figures are wall-clock rates, so they move with the machine's load: compare the
pool against the single worker of the same run, not against another day's figure.
"""

from __future__ import annotations

import time

from bench.report import Section
from companion.harness.sweep import load_layout, run_local, tasks_for

WORKERS = 2


def _rate(n_tasks: int, workers: int, seeds: range) -> tuple[float, int]:
    """(worlds per minute, runs that reached the goal) for `seeds` with `workers` processes."""
    tasks = tasks_for(seeds, [load_layout("paper-11")], ["ideal"], ["none"])[:n_tasks]
    t0 = time.perf_counter()
    records = list(run_local(tasks, workers))
    wall = time.perf_counter() - t0
    reached = sum(1 for r in records if r.get("reached_goal") is True)
    return 60.0 * len(records) / wall, reached


def run(quick: bool = False) -> Section:
    sec = Section("random-world sweep")
    n = 4 if quick else 12
    seeds = range(1000, 1000 + n)
    pool, reached_2 = _rate(n, WORKERS, seeds)
    sec.details.update(
        {"tasks": n, "seeds": f"{seeds.start}:{seeds.stop}", "layout": "paper-11"}
        | {"reached_goal_pool": reached_2}
    )
    sec.add(
        "sweep.worlds_per_min",
        f"worlds per minute, process pool of {WORKERS} ({n} seeded worlds, paper-11, ideal)",
        pool,
        "worlds/min",
    )
    if quick:
        return sec
    single, reached_1 = _rate(n, 1, seeds)
    sec.details["reached_goal_1_worker"] = reached_1
    sec.add("sweep.worlds_per_min_1", "same tasks, 1 worker (in process)", single, "worlds/min")
    sec.add("sweep.pool_speedup", f"pool of {WORKERS} / 1 worker", pool / single, "x")
    return sec


if __name__ == "__main__":  # a smoke run of this benchmark alone
    import sys

    from bench.report import table

    print(table([run(quick="--quick" in sys.argv)]))
