"""`companion sweep`: fly many seeded random worlds and measure what the targets name.

One task = one seed x sensor layout x vehicle model x sensor fault: `run_task` generates the
world (`companion.sim.worldgen`), flies it in process (`companion.harness.closed_loop.run`)
and returns one flat record (RECORD_FIELDS). The same function runs in a local process pool
(default) or on a Ray cluster (`--ray`); everything in a record except the wall-clock fields
(TIMING_FIELDS) is a function of the task alone, so the same seeds give the same records on either.

The driver writes DIR/results.csv row by row as tasks finish (an interrupted sweep keeps the
rows written; `--resume` skips the tasks already there), prints a live progress line, then
a summary per layout x vehicle x fault (DIR/summary.txt). Every failure (goal not reached,
a collision, or clearance below D_min) gets DIR/failures/KEY.yaml, the world as a scenario
file, a line in DIR/failures.txt with the one command that reproduces it, and (with
matplotlib) its figures, trace and events in DIR/failures/KEY/.

Clearance is the true distance from the vehicle to the nearest obstacle surface from the
world's geometry (`World.obstacle_distance`), not a sensor range. Height error |H - H_d| is
counted once the vehicle first settled within 0.15 m of H_d, on cycles with no obstacle
within 2 D_min.
"""

from __future__ import annotations

import contextlib
import csv
import importlib.util
import math
import multiprocessing
import signal
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import yaml

from companion.config import FailsafeConfig
from companion.harness.closed_loop import STALL_BOX_M
from companion.planner.types import VehicleState
from companion.service.pairing import off_pose
from companion.service.telemetry import MEDIAN_GAP_S, spike_filtered
from companion.sim.mavlink.config import SensorFaultConfig
from companion.sim.mavlink.faults import SensorFaults
from companion.sim.vehicle import VehicleModelConfig
from companion.sim.worldgen import WorldGenConfig, generate, scenario, scenario_yaml, to_scenario
from companion.tuning import SensorConfig

LAYOUT_DIR = Path(__file__).resolve().parents[2] / "config" / "sensors"
DEFAULT_LAYOUTS = ("paper-11", "horizontal-7", "ring-8")
VEHICLES = ("ideal", "multicopter")
FAULTS: dict[str, tuple[SensorFaultConfig, ...]] = {
    "none": (),
    "noise": (SensorFaultConfig(noise_std_m=0.05),),
    "dropout": (SensorFaultConfig(dropout_probability=0.1),),
    "spikes": (SensorFaultConfig(spike_probability=0.01),),
}
"""Sensor faults applied to every sensor (companion/sim/mavlink's fault model, in process)."""

MEDIAN_SAMPLES = FailsafeConfig().range_median_samples
SPIKE_M = FailsafeConfig().range_spike_m
"""The service's spike filter in its default configuration (`spike_filtered` over each
sensor's last MEDIAN_SAMPLES readings, agreement within SPIKE_M metres)."""

GENTLE_REACH_H_D = 2.0
"""The height error on gentle relief counts the cycles whose surface within this many H_d
(horizontally) has a radius of curvature of at least 10 m (`metrics.gentle_relief`): where
the vehicle's shortest distance and its tilted surface sensors reach."""

STALL_WINDOW_S = 60.0
"""A run whose vehicle stays within a 1 m box this long (s) is stopped: stalled."""

RECORD_FIELDS = (
    "seed",
    "layout",
    "vehicle",
    "fault",
    "outcome",
    "reached_goal",
    "collision",
    "collision_cycles",
    "clearance_min_m",
    "steep_clearance_min_m",
    "height_err_p50_m",
    "height_err_p95_m",
    "height_err_max_m",
    "height_err_gentle_max_m",
    "planner_ms_p99",
    "planner_ms_max",
    "blocked_cycles",
    "replans",
    "sim_time_s",
    "wall_time_s",
    "stop_reason",
    "last_event",
    "route_length_m",
    "base_points",
    "motifs",
    "error",
)
TIMING_FIELDS = ("planner_ms_p99", "planner_ms_max", "wall_time_s")
"""Wall-clock measurements: the only fields that differ between two runs of a task."""
KEY_FIELDS = ("seed", "layout", "vehicle", "fault")


class SweepError(ValueError):
    """Bad sweep input (seed range, layout, Ray address, output directory); one line."""


@dataclass(frozen=True)
class Task:
    """One run. sensors: the layout's sensor entries as plain mappings (so a remote worker
    needs no file). figures_dir: where a failure's figures go (None: none)."""

    seed: int
    layout: str
    sensors: tuple[dict[str, Any], ...]
    vehicle: str
    fault: str = "none"
    gen: WorldGenConfig = field(default_factory=WorldGenConfig)
    figures_dir: str | None = None

    @property
    def key(self) -> str:
        fault = "" if self.fault == "none" else f"-{self.fault}"
        return f"random-{self.seed}-{self.layout}-{self.vehicle}{fault}"


# --------------------------------------------------------------------------- one task


class _HeldFaults:
    """Sensor faults in process, reaching the planner as they would through the service: a
    reading not delivered leaves the last one in place (what the service's reading store
    holds; before any, the sensor's max range), and a held reading whose attitude (roll,
    pitch or yaw) differs from this cycle's by more than PAIR_TOLERANCE_RAD, or by enough
    to move its point more than PAIR_TOLERANCE_M, is not used this cycle (NaN), as the
    service pairs each reading with the attitude of its own time and drops it then
    (`companion.service.pairing.off_pose`). Without that, a reading taken at another pitch
    became a point in the wrong place as if measured now (0.82 m of height error at a
    crease with 10 % dropout, 0.11 m through the service; with noise alone, a median 2.7
    degrees off at 5.8 m put a ground point 0.31 m high, and X_d 0.29 m above H_d on the
    descent past it).

    A ray that hit nothing (the closed loop reads the max range there) reaches the fault
    model as the MAVLink simulator's rangefinders give it, inf: noise moves only what was
    measured, so "nothing" does not turn into a reading just short of the max range (a
    spike still may, as in the simulator).

    Each delivered reading then passes the service's spike filter (`Telemetry._filtered`,
    `spike_filtered`, the default configuration): it passes as it is, or the median of its
    sensor's last readings ("nothing" counting as farthest) with the attitude that one was
    taken at, or nothing new (the last one passed holds); the history restarts after a gap
    of MEDIAN_GAP_S. A single spike never reaches the planner, as through the service; a
    step arrives (n - 1) / 2 readings late, as it does there."""

    def __init__(
        self,
        configs: Sequence[SensorFaultConfig],
        sensors: Any,
        seed: int,
        median_samples: int = MEDIAN_SAMPLES,
        spike_m: float = SPIKE_M,
    ) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([0x5EED, seed]))
        ids = [s.sensor_id for s in sensors.specs]
        self.faults = SensorFaults(configs, ids, sensors.min_range_m, sensors.max_range_m, rng)
        self.max_m = np.array(sensors.max_range_m, dtype=np.float64)
        self.held = self.max_m.copy()
        self.held_rpy = np.full((len(self.max_m), 3), np.nan)
        """The attitude each held reading was taken at (NaN before any)."""
        self.median_samples = median_samples
        self.spike_m = spike_m
        self.history: list[deque[tuple[float, float, np.ndarray, float]]] = [
            deque(maxlen=median_samples) for _ in range(len(self.max_m))
        ]
        """Per sensor: its last delivered readings as (sort key, range, attitude, time)."""

    def __call__(self, t_s: float, ranges_m: np.ndarray, state: VehicleState) -> np.ndarray:
        measured = np.where(ranges_m >= self.max_m, np.inf, ranges_m)
        out, send = self.faults.apply(t_s, measured)
        sent = np.asarray(send, dtype=bool)
        keys = np.where(np.isfinite(out), out, np.inf)
        out = np.where(np.isfinite(out), out, self.max_m)
        rpy = np.array([state.roll_rad, state.pitch_rad, state.yaw_rad])
        for i in np.flatnonzero(sent).tolist():
            passed = self._filtered(i, (float(keys[i]), float(out[i]), rpy, t_s))
            if passed is not None:  # (None: the last one passed holds)
                self.held[i], self.held_rpy[i] = passed
        turned = np.abs(np.angle(np.exp(1j * (self.held_rpy - rpy)))).max(axis=1)
        # A held reading, or a median taken at another attitude (NaN attitude: never sent).
        stale_pose = off_pose(turned, np.where(self.held >= self.max_m, 0.0, self.held))
        return np.where(stale_pose, np.nan, self.held)

    def _filtered(
        self, i: int, reading: tuple[float, float, np.ndarray, float]
    ) -> tuple[float, np.ndarray] | None:
        """Sensor i's value and attitude after the spike filter, given its new reading; None
        where the filter passes none on."""
        if self.median_samples <= 1:
            return reading[1], reading[2]
        history = self.history[i]
        if history and reading[3] - history[-1][3] > MEDIAN_GAP_S:
            history.clear()
        history.append(reading)
        if len(history) < self.median_samples:
            return reading[1], reading[2]
        k = spike_filtered([r[0] for r in history], self.spike_m)
        if k is None:
            return None
        return history[k][1], history[k][2]


def _stop_reason(reached: bool, finished: bool, t: np.ndarray, x: np.ndarray, y: np.ndarray) -> str:
    if reached:
        return "goal"
    if finished:
        return "finished off goal"
    recent = t >= t[-1] - STALL_WINDOW_S + 1e-9
    box = max(float(np.ptp(x[recent])), float(np.ptp(y[recent])))
    return "stalled" if t[-1] >= STALL_WINDOW_S and box < STALL_BOX_M else "timeout"


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else math.nan


def run_task(task: Task) -> dict[str, Any]:
    """Generate, fly and measure one task; a flat record with RECORD_FIELDS.

    A crash of the planner or the simulator is a record with outcome "error" and the
    message, not an exception: one bad world does not stop a sweep.
    """
    from companion.harness import metrics as metrics_mod
    from companion.harness.closed_loop import run
    from companion.sim.world import World

    wall0 = time.perf_counter()
    rec: dict[str, Any] = dict.fromkeys(RECORD_FIELDS, "")
    rec.update(seed=task.seed, layout=task.layout, vehicle=task.vehicle, fault=task.fault)
    try:
        sensors = [SensorConfig.model_validate(s) for s in task.sensors]
        vehicle = VehicleModelConfig(model=task.vehicle)
        gen = generate(task.seed, task.gen)
        sc = to_scenario(gen, sensors, vehicle, task.gen)
        world = World.from_config(sc.world)
        filt = None
        if FAULTS[task.fault]:
            filt = _HeldFaults(FAULTS[task.fault], sc.sensor_table(), task.seed)
        result = run(sc, world, sensor_filter=filt, stall_stop_s=STALL_WINDOW_S)
        m = metrics_mod.for_run(sc, world, result)
        steep_per_cycle = metrics_mod.steep_clearances(sc, result.trace)
    except Exception as exc:  # a crash is a finding, reported in the record
        rec.update(outcome="error", error=f"{type(exc).__name__}: {exc}"[:300])
        rec["wall_time_s"] = round(time.perf_counter() - wall0, 3)
        return rec
    tr = result.trace
    d_min = sc.planner.d_min_m
    below = steep_per_cycle[tr["clearance"] < d_min]
    steep = float(below.min()) if len(below) and below.min() < d_min else math.nan
    h_err = np.abs(tr["height"] - sc.planner.h_d_m)
    away = _over_relief(h_err, steep_per_cycle, d_min, metrics_mod.SETTLE_BAND_M)
    # (settled into the gentle target's own band first: a start over a slope begins up to
    # 0.18 m off H_d, and that transient is not the relief's)
    gentle = _over_relief(
        h_err, steep_per_cycle, d_min, metrics_mod.GENTLE_SETTLE_BAND_M
    ) & metrics_mod.gentle_relief(world, tr["x"], tr["y"], GENTLE_REACH_H_D * sc.planner.h_d_m)
    step_ms = result.step_time_s * 1000.0
    reached = bool(m["reached_goal"])
    clearance = float(m["min_clearance_m"])
    kinds = []
    if m["collisions"] > 0:
        kinds.append("collision")
    if clearance < d_min:
        kinds.append("clearance")
    stop = _stop_reason(reached, result.finished, tr["t"], tr["x"], tr["y"])
    if not reached:
        kinds.append(stop)
    rec.update(
        outcome="+".join(kinds) or "ok",
        reached_goal=reached,
        collision=m["collisions"] > 0,
        collision_cycles=int(m["collisions"]),
        clearance_min_m=round(clearance, 4),
        steep_clearance_min_m=_blank_nan(steep),
        height_err_p50_m=round(_pct(h_err[away], 50), 4),
        height_err_p95_m=round(_pct(h_err[away], 95), 4),
        height_err_max_m=round(float(h_err[away].max()) if away.any() else math.nan, 4),
        height_err_gentle_max_m=_blank_nan(
            float(h_err[gentle].max()) if gentle.any() else math.nan
        ),
        planner_ms_p99=round(_pct(step_ms, 99), 3),
        planner_ms_max=round(float(step_ms.max()) if len(step_ms) else math.nan, 3),
        blocked_cycles=int(m["decisions"]["blocked"]),
        replans=int(m["replans"]),
        sim_time_s=round(float(tr["t"][-1]), 2),
        stop_reason=stop,
        last_event=result.events[-1][1] if result.events else "",
        route_length_m=round(gen.route_length_m, 1),
        base_points=len(gen.route.points),
        motifs="+".join(gen.motifs),
    )
    if rec["outcome"] != "ok" and task.figures_dir is not None:
        rec["error"] = _write_failure_outputs(
            Path(task.figures_dir) / task.key, sc, world, result, m
        )
    rec["wall_time_s"] = round(time.perf_counter() - wall0, 3)
    return rec


def _write_failure_outputs(out: Path, sc: Any, world: Any, result: Any, m: dict[str, Any]) -> str:
    """Trace, events, metrics and (with matplotlib) figures of a failure; '' or the problem."""
    from companion.harness.runner import write_outputs

    try:
        import matplotlib  # noqa: F401

        plots = True
    except ImportError:
        plots = False
    try:
        write_outputs(out, sc, world, result, m, plots=plots)
    except Exception as exc:  # figures are a convenience: the record still counts
        return f"figures not written: {type(exc).__name__}: {exc}"[:300]
    return ""


# --------------------------------------------------------------------------- inputs


def parse_seeds(text: str) -> list[int]:
    """'17' (one seed), '0:100' (0..99) or a comma list of those. SweepError if bad."""
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        try:
            if ":" in part:
                a_s, b_s = part.split(":")
                a, b = int(a_s), int(b_s)
                if a < 0 or b <= a:
                    raise ValueError
                seeds.extend(range(a, b))
            else:
                a = int(part)
                if a < 0:
                    raise ValueError
                seeds.append(a)
        except ValueError:
            raise SweepError(
                f"bad seed range {text!r}: use N, A:B (0 <= A < B, B excluded) or a comma list"
            ) from None
    return list(dict.fromkeys(seeds))


def load_layout(name: str) -> tuple[str, tuple[dict[str, Any], ...]]:
    """(layout name, sensor entries) of a layout: a name in config/sensors or a YAML file."""
    path = Path(name) if name.endswith((".yaml", ".yml")) else LAYOUT_DIR / f"{name}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in LAYOUT_DIR.glob("*.yaml")))
        raise SweepError(f"unknown layout {name!r}: not a file, and not one of {known}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        entries = [SensorConfig.model_validate(d) for d in data]
        from companion.tuning import sensor_table

        sensor_table(entries)
    except Exception as exc:
        first = str(exc).splitlines()[0]
        raise SweepError(f"layout {name!r} ({path}) is not a valid sensor list: {first}") from None
    plain = tuple(e.model_dump(mode="json", exclude_defaults=True) for e in entries)
    return path.stem, plain


def _check_out_dir(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("", encoding="utf-8")
        probe.unlink()
    except OSError as exc:
        raise SweepError(f"cannot write output directory {out}: {exc.strerror or exc}") from None


def check_ray_address(address: str, timeout_s: float = 5.0) -> None:
    """A TCP connection to host:port of a Ray address (ray://host:port or host:port) opens,
    else SweepError naming it ('local' and 'auto' are not checked)."""
    if address in ("local", "auto"):
        return
    hostport = address.split("://", 1)[-1]
    host, _, port_s = hostport.rpartition(":")
    try:
        port = int(port_s)
    except ValueError:
        raise SweepError(f"bad Ray address {address!r}: use HOST:PORT or ray://HOST:PORT") from None
    try:
        with socket.create_connection((host or "127.0.0.1", port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise SweepError(f"cannot reach Ray cluster at {address}: {exc.strerror or exc}") from None


def tasks_for(
    seeds: Iterable[int],
    layouts: Sequence[tuple[str, tuple[dict[str, Any], ...]]],
    vehicles: Sequence[str],
    faults: Sequence[str],
    gen: WorldGenConfig | None = None,
    figures_dir: Path | None = None,
) -> list[Task]:
    """Every combination, seeds outermost (a partial sweep covers every layout)."""
    g = gen or WorldGenConfig()
    fig = str(figures_dir) if figures_dir is not None else None
    return [
        Task(seed, name, sensors, vehicle, fault, g, fig)
        for seed in seeds
        for name, sensors in layouts
        for vehicle in vehicles
        for fault in faults
    ]


# --------------------------------------------------------------------------- executors


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_local(tasks: Sequence[Task], workers: int) -> Iterator[dict[str, Any]]:
    """Records as tasks finish, from a pool of `workers` processes (1: in this process)."""
    if workers == 1:
        for t in tasks:
            yield run_task(t)
        return
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_ignore_sigint)
    pending: set[Future[dict[str, Any]]] = set()
    it = iter(tasks)
    try:
        for t in it:  # keep a bounded queue: a Ctrl-C leaves little to cancel
            pending.add(pool.submit(run_task, t))
            if len(pending) >= 2 * workers:
                break
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                nxt = next(it, None)
                if nxt is not None:
                    pending.add(pool.submit(run_task, nxt))
                yield fut.result()
    finally:
        for fut in pending:
            fut.cancel()
        procs = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=not pending, cancel_futures=True)  # a normal end waits for the workers
        for p in procs:  # do not wait for a long run in progress when interrupted
            if p.is_alive():
                p.terminate()


def run_ray(tasks: Sequence[Task], address: str, num_cpus: int) -> Iterator[dict[str, Any]]:
    """Records as tasks finish, from Ray: a local instance ('local') or a cluster."""
    try:
        import ray
    except ImportError:
        raise SweepError(
            "--ray needs the ray package: pip install 'terrain-companion[ray]'"
        ) from None
    check_ray_address(address)
    started = False
    if not ray.is_initialized():
        try:
            if address == "local":
                ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
        except Exception as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise SweepError(f"cannot start Ray at {address}: {first}") from None
        started = True
    remote = ray.remote(num_cpus=1)(run_task)
    refs = [remote.remote(t) for t in tasks]
    try:
        while refs:
            done, refs = ray.wait(refs, num_returns=1)
            for ref in done:
                yield ray.get(ref)
    finally:
        for ref in refs:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


# --------------------------------------------------------------------------- the driver


def _is_failure(rec: dict[str, Any]) -> bool:
    return str(rec["outcome"]) != "ok"


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float) and math.isnan(v):
        return ""
    return str(v)


def repro_command(task: Task, out: str = "out/repro") -> str:
    """The one command that flies this task again (same seed, layout, vehicle, fault)."""
    fault = "" if task.fault == "none" else f" --fault {task.fault}"
    return (
        f"companion sweep --seeds {task.seed}:{task.seed + 1} --layout {task.layout} "
        f"--vehicle {task.vehicle}{fault} --workers 1 --out {out}/{task.key}"
    )


def write_scenario_file(task: Task, path: Path, note: str = "") -> None:
    """The task's world as a scenario file (sensors inline)."""
    sensors = [SensorConfig.model_validate(s) for s in task.sensors]
    vehicle = VehicleModelConfig(model=task.vehicle)
    sc = scenario(task.seed, sensors, vehicle, task.gen)
    header = (
        f"Seeded random world {task.seed} (companion/sim/worldgen), layout {task.layout}, "
        f"vehicle {task.vehicle}, sensor fault {task.fault}.\n"
        f"Reproduce: {repro_command(task)}\n{note}"
    ).rstrip()
    path.write_text(scenario_yaml(sc, header=header), encoding="utf-8")


def _read_done(csv_path: Path) -> list[dict[str, str]]:
    """The rows of a sweep's results.csv to resume; SweepError if its columns are not this
    version's (rows appended under another header would be read back shifted)."""
    with csv_path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        header = tuple(reader.fieldnames or ())
    if header and header != RECORD_FIELDS:
        raise SweepError(
            f"cannot resume {csv_path}: its columns are another version's; use a new --out"
        )
    return [r for r in rows if all(k in r for k in KEY_FIELDS)]


def _key(rec: dict[str, Any]) -> tuple[str, ...]:
    return tuple(str(rec[k]) for k in KEY_FIELDS)


class _Progress:
    def __init__(self, total: int, stream: TextIO) -> None:
        self.total = total
        self.stream = stream
        self.tty = stream.isatty()
        self.t0 = time.monotonic()
        self.last = 0.0
        self.done = self.goal = self.failed = 0

    def update(self, rec: dict[str, Any]) -> None:
        self.done += 1
        self.goal += rec["reached_goal"] is True
        self.failed += _is_failure(rec)
        now = time.monotonic()
        if not self.tty and now - self.last < 30.0 and self.done < self.total:
            return
        self.last = now
        el = now - self.t0
        left = el / self.done * (self.total - self.done)
        line = (
            f"[{self.done}/{self.total}] goal {self.goal}/{self.done}, "
            f"failures {self.failed}, {_hms(el)} elapsed, ~{_hms(left)} left"
        )
        self.stream.write(f"\r{line:<78}" if self.tty else line + "\n")
        self.stream.flush()

    def clear(self) -> None:
        if self.tty:
            self.stream.write("\r" + " " * 78 + "\r")


def _hms(s: float) -> str:
    s = int(s)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _over_relief(
    height_err_m: np.ndarray, steep_clearance_m: np.ndarray, d_min_m: float, settle_m: float
) -> np.ndarray:
    """The cycles the height target counts, (n,) bool: from the first within settle_m of
    H_d on, with no solid the paper's rule goes round (`_steep_clearances`) within 2 D_min.
    A mesa eq. (7) climbs is relief, and its cycles count."""
    settled = np.flatnonzero(height_err_m <= settle_m)
    first = int(settled[0]) if len(settled) else len(height_err_m)
    away = np.zeros(len(height_err_m), dtype=bool)
    away[first:] = True
    away &= steep_clearance_m > 2.0 * d_min_m
    return away


def _blank_nan(v: float) -> float | str:
    """v rounded to 0.1 mm, or "" for NaN (a record compares equal to itself)."""
    return "" if math.isnan(v) else round(v, 4)


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def summarize(rows: Sequence[dict[str, Any]], d_min_m: float) -> str:
    """A table per layout x vehicle x fault. Clearance: the per-run minima (min, p1, p5,
    median across runs); height error: the worst per-run p95, max and max on gentle relief
    (radius of curvature >= 10 m, `metrics.gentle_relief`); planner time: the
    worst per-run p99 and max; wall time: mean and total per run."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((str(r["layout"]), str(r["vehicle"]), str(r["fault"])), []).append(r)
    head = (
        f"{'layout':<14}{'vehicle':<12}{'fault':<8}{'runs':>5}{'goal %':>8}{'coll':>5}"
        f"{'<Dmin':>6}{'steep':>6}{'err':>4}  {'clearance min/p1/p5/median (m)':<31}"
        f"{'h err p95/max/gentle':<21}{'plan ms p99/max':<16}{'wall s mean/total'}"
    )
    lines = [head, "-" * len(head)]
    for (layout, vehicle, fault), rs in sorted(groups.items()):
        n = len(rs)
        goal = sum(str(r["reached_goal"]) in ("True", "1") for r in rs)
        coll = sum(str(r["collision"]) in ("True", "1") for r in rs)
        errors = sum(str(r["outcome"]) == "error" for r in rs)
        clr = np.array([_num(r["clearance_min_m"]) for r in rs])
        clr = clr[np.isfinite(clr)]
        below = int(np.sum(clr < d_min_m))
        steep = sum(math.isfinite(_num(r.get("steep_clearance_min_m"))) for r in rs)
        c = "/".join(f"{np.percentile(clr, q):.2f}" for q in (0, 1, 5, 50)) if len(clr) else "-"

        def worst(col: str, fmt: str = ".3f", rs: list[dict[str, Any]] = rs) -> str:
            v = np.array([_num(r[col]) for r in rs])
            v = v[np.isfinite(v)]
            return format(float(v.max()), fmt) if len(v) else "-"

        wall = np.array([_num(r["wall_time_s"]) for r in rs])
        wall = wall[np.isfinite(wall)]
        lines.append(
            f"{layout:<14}{vehicle:<12}{fault:<8}{n:>5}{100.0 * goal / n:>8.1f}{coll:>5}"
            f"{below:>6}{steep:>6}{errors:>4}  {c:<31}"
            f"{'/'.join(worst(f'height_err_{q}_m') for q in ('p95', 'max', 'gentle_max')):<21}"
            f"{worst('planner_ms_p99', '.2f') + '/' + worst('planner_ms_max', '.2f'):<16}"
            f"{(f'{wall.mean():.1f}/{wall.sum():.0f}' if len(wall) else '-')}"
        )
    return "\n".join(lines)


@dataclass
class SweepOptions:
    """What `companion sweep` was asked for (validated by `sweep`)."""

    seeds: str
    layouts: Sequence[str] = DEFAULT_LAYOUTS
    vehicles: Sequence[str] = VEHICLES
    faults: Sequence[str] = ("none",)
    out: Path = Path("out/sweep")
    workers: int = 2
    ray: str | None = None
    resume: bool = False
    figures: bool = True
    write_scenarios: bool = False
    gen: WorldGenConfig = field(default_factory=WorldGenConfig)


def prepare(opts: SweepOptions) -> list[Task]:
    """Validate the options and build the task list; SweepError (one line) if bad."""
    seeds = parse_seeds(opts.seeds)
    layouts = [load_layout(name) for name in opts.layouts]
    for v in opts.vehicles:
        if v not in VEHICLES:
            raise SweepError(f"unknown vehicle {v!r}: use {', '.join(VEHICLES)}")
    for f in opts.faults:
        if f not in FAULTS:
            raise SweepError(f"unknown fault {f!r}: use {', '.join(FAULTS)}")
    if opts.workers < 1:
        raise SweepError(f"--workers must be >= 1, got {opts.workers}")
    _check_out_dir(opts.out)
    figures = opts.out / "failures" if opts.figures else None
    return tasks_for(seeds, layouts, opts.vehicles, opts.faults, opts.gen, figures)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a service manager, a CI timeout, `kill`) taken as Ctrl-C is: the results
    written so far are kept and the pool's workers are stopped, not left running."""


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Raise Terminated in the main thread on SIGTERM while the sweep runs (elsewhere, or
    off the main thread, SIGTERM keeps its handler)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def sweep(
    opts: SweepOptions,
    stream: TextIO = sys.stdout,
    executor: Callable[[Sequence[Task]], Iterator[dict[str, Any]]] | None = None,
) -> int:
    """Run the sweep; exit code (0 done, 130 interrupted by Ctrl-C, 143 by SIGTERM).
    SweepError for bad input."""
    tasks = prepare(opts)
    out = opts.out
    if opts.write_scenarios:
        for t in tasks:
            path = out / f"{t.key}.yaml"
            write_scenario_file(t, path)
            stream.write(f"wrote {path}\n")
        return 0
    if opts.ray is not None:
        if importlib.util.find_spec("ray") is None:
            raise SweepError("--ray needs the ray package: pip install 'terrain-companion[ray]'")
        check_ray_address(opts.ray)
    csv_path = out / "results.csv"
    kept: list[dict[str, Any]] = []
    if opts.resume and csv_path.is_file():
        kept = [dict(r) for r in _read_done(csv_path)]
        done_keys = {_key(r) for r in kept}
        tasks = [t for t in tasks if _key(t.__dict__) not in done_keys]
        stream.write(f"resuming: {len(kept)} runs already in {csv_path}, {len(tasks)} to go\n")
        fh = csv_path.open("a", newline="", encoding="utf-8")
        writer = csv.DictWriter(fh, RECORD_FIELDS, extrasaction="ignore")
    else:
        fh = csv_path.open("w", newline="", encoding="utf-8")
        writer = csv.DictWriter(fh, RECORD_FIELDS, extrasaction="ignore")
        writer.writeheader()
        fh.flush()
    fail_path = out / "failures.txt"
    fail_fh = fail_path.open("a" if opts.resume else "w", encoding="utf-8")
    by_key = {_key(t.__dict__): t for t in tasks}
    if executor is None:
        if opts.ray is not None:
            ray_addr = opts.ray

            def executor(ts: Sequence[Task]) -> Iterator[dict[str, Any]]:
                return run_ray(ts, ray_addr, opts.workers)
        else:

            def executor(ts: Sequence[Task]) -> Iterator[dict[str, Any]]:
                return run_local(ts, opts.workers)

    where = f"Ray ({opts.ray})" if opts.ray is not None else f"{opts.workers} worker(s)"
    stream.write(f"sweep: {len(tasks)} runs on {where}; results in {csv_path}\n")
    stream.flush()
    progress = _Progress(len(tasks), stream)
    rows = list(kept)
    failures: list[str] = []
    code = 0
    try:
        with _sigterm_as_interrupt():
            for rec in executor(tasks) if tasks else ():
                writer.writerow({k: _fmt(v) for k, v in rec.items()})
                fh.flush()
                rows.append({k: _fmt(v) for k, v in rec.items()})
                if _is_failure(rec):
                    failures.append(_report_failure(rec, by_key, out, fail_fh))
                progress.update(rec)
    except KeyboardInterrupt as exc:
        code = 143 if isinstance(exc, Terminated) else 130
        progress.clear()
        stream.write(f"\ninterrupted: {progress.done} runs of this sweep kept in {csv_path}\n")
    finally:
        fh.close()
        fail_fh.close()
    progress.clear()
    d_min = opts.gen.d_min_m
    table = summarize(rows, d_min) if rows else "no runs"
    (out / "summary.txt").write_text(table + "\n", encoding="utf-8")
    stream.write("\n" + table + "\n")
    if failures:
        stream.write(f"\n{len(failures)} failure(s) (all in {fail_path}):\n")
        for line in failures[:50]:
            stream.write(line + "\n")
        if len(failures) > 50:
            stream.write(f"... {len(failures) - 50} more in {fail_path}\n")
    stream.write(f"wrote {csv_path}, {out / 'summary.txt'}, {fail_path}\n")
    return code


def _report_failure(
    rec: dict[str, Any], by_key: dict[tuple[str, ...], Task], out: Path, fh: TextIO
) -> str:
    """Write the failure's scenario file and its line in failures.txt; return the line."""
    task = by_key.get(_key(rec))
    if task is None:
        return ""
    fail_dir = out / "failures"
    fail_dir.mkdir(exist_ok=True)
    path = fail_dir / f"{task.key}.yaml"
    note = (
        f"Found: {rec['outcome']}, clearance min {rec['clearance_min_m']} m, "
        f"stop: {rec['stop_reason']}, last event: {rec['last_event']}"
    )
    write_scenario_file(task, path, note)
    simulate = f"companion simulate {path} --out out/repro/{task.key}"
    how = simulate if task.fault == "none" else repro_command(task)
    line = (
        f"{task.key}: {rec['outcome']} (clearance {rec['clearance_min_m']} m, "
        f"stop {rec['stop_reason']}; {rec['last_event'] or 'no event'}) -> "
        f"{repro_command(task)}  |  {how}"
    )
    fh.write(line + "\n")
    fh.flush()
    return line
