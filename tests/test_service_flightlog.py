"""Flight log: written per cycle by the service, read back into arrays."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest

from companion.service import Service, memory_pair
from companion.service.flightlog import FlightLogWriter, read_flight_log
from companion.service.notify import SystemdNotifier
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(20)


def test_writer_rotates_prunes_and_reader_tolerates_torn_lines(tmp_path: Path) -> None:
    w = FlightLogWriter(tmp_path, max_bytes=2_000, keep_files=2)
    w.header({"sensors": [{"id": 0}, {"id": 1}]})
    for i in range(100):
        w.write({"type": "cycle", "t": i * 0.05, "pos": [i, 0, math.nan], "ranges": [1.0, None]})
        if i % 10 == 0:
            w.flush()
    w.close()
    files = sorted(tmp_path.glob("flight-*.jsonl"))
    assert len(files) == 2
    last = max(files, key=lambda p: p.stat().st_mtime)
    with last.open("a") as f:
        f.write('{"type": "cycle", "t": 9')  # torn by a crash
    log = read_flight_log(last)
    assert log.header["sensors"] == [{"id": 0}, {"id": 1}]
    assert len(log) > 0 and log.ranges_m.shape == (len(log), 2)
    assert np.isnan(log.position_enu[:, 2]).all() and np.isnan(log.ranges_m[:, 1]).all()


async def test_service_writes_a_cycle_per_line(tmp_path: Path) -> None:
    cfg = make_config(logging={"flight_log_dir": str(tmp_path)})
    a, b = memory_pair()
    svc = Service(cfg, a, planner_factory=PlannerBox(), notifier=SystemdNotifier({}))
    ap = FakeAutopilot(b)
    task = asyncio.create_task(svc.run())
    await ap.start()
    while not svc.status().configured:
        await asyncio.sleep(0.01)
    ap.set_mode(4)
    await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
    svc.stop()
    assert await asyncio.wait_for(task, 5) == 0
    await ap.stop()
    (path,) = tmp_path.glob("flight-*.jsonl")
    log = read_flight_log(path)
    assert len(log.header["sensors"]) == 3
    assert len(log) == svc.counters["cycles"]
    active = [i for i, h in enumerate(log.health) if h == "active"]
    assert len(active) >= 10
    i = active[-1]
    assert log.setpoint_kind[i] == "planner" and log.decision[i] == "vertical"
    assert log.setpoint_velocity_enu[i] == pytest.approx([1.0, 0.0, 0.0])
    np.testing.assert_allclose(log.ranges_m[i], [0.0, 7.0, 7.0])
    assert log.frames and log.frames[0]["origin"][0] == pytest.approx(47.397742)
    assert any(text == "flying route" for _, text in log.events)
    assert log.counters["service.cycles"] >= len(log) - 1


def test_dumps_record_is_the_same_text_as_cleaning_first() -> None:
    """The direct encoding and the `clean` fallback write the same line for every record."""
    import json

    import numpy as np

    from companion.service.flightlog import clean, dumps_record

    records = [
        {"t": 1.5, "pos": np.array([1.0, -0.0, 3.25]), "sp": {"yaw": np.float64(0.1)}},
        {"ranges": np.array([1.0, np.nan, 0.0]), "min_range": np.inf, "n": np.int64(3)},
        {"rpy": [np.float32(0.5), 2.0, -1e-300], "events": ["a", "NaN"], "x": None},
        {"m": np.arange(6, dtype=np.float64).reshape(2, 3), "k": (1, 2), "f": -np.inf},
        {"i": np.arange(3), "flag": True, "nested": [{"a": float("nan")}, np.float64(2.0)]},
    ]
    for rec in records:
        line = dumps_record(rec)
        assert line == json.dumps(clean(rec), separators=(",", ":"))
        assert "NaN" not in line.replace('"NaN"', "") and "Infinity" not in line


def test_floats_writes_what_clean_writes() -> None:
    """A record built with `floats` (as the cycle builds its own) is the same line as the
    raw record: finite arrays as lists, NaN and inf as null, other values untouched."""
    import json

    import numpy as np

    from companion.service.flightlog import clean, dumps_record, floats

    arrays = [
        np.array([1.0, -0.0, 3.25]),
        np.array([1.0, np.nan, 0.0, np.inf, -np.inf]),
        np.array([], dtype=np.float64),
        np.array([0.1, 2e-308], dtype=np.float32),
    ]
    for a in arrays:
        raw = {"ranges": a, "sp": {"p": a}}
        built = {"ranges": floats(a), "sp": {"p": floats(a)}}
        assert isinstance(built["ranges"], list)
        assert dumps_record(built) == dumps_record(raw)
        assert dumps_record(built) == json.dumps(clean(raw), separators=(",", ":"))
    # not a 1-D float array: unchanged, left to the encoder
    for other in (np.arange(3), np.zeros((2, 2)), [1.0, 2.0], 0.5, None, "x"):
        assert floats(other) is other
