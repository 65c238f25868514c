"""The long reliability runs (deselected by default; `pytest -m long -s`).

- 1 024 000 fuzzed inputs into the receive path (ten times the default suite's);
- every fault of tests.reliability_flight x 20 seeds, ArduPilot and PX4: never below D_min
  of an obstacle, never touching the surface (true trajectory), never a crash;
- a simulated flight of RELIABILITY_SOAK_HOURS (default 1) at speed-up: no growth in memory
  or in the time a cycle takes.
Results are printed and written under out/reliability/ (the table in docs/reliability.md
comes from there). Expect about 40 minutes per personality for the sweep and ~10 minutes
per simulated hour of the soak on one core.
"""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path

import pytest

from tests import test_reliability_bytes as fuzz
from tests.reliability_flight import sweep, table
from tests.reliability_soak import soak

pytestmark = [pytest.mark.long, pytest.mark.timeout(4 * 3600)]

OUT = Path(__file__).resolve().parents[1] / "out" / "reliability"


def test_fuzz_a_million_inputs() -> None:
    n = fuzz.check_datagrams(10).fed.inputs + fuzz.check_stream(10) + fuzz.check_signed(10)
    print(f"fuzzed inputs: {n}")
    assert n >= 1_000_000


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_every_fault_20_seeds(personality: str) -> None:
    rows = sweep(personality, range(1, 21), OUT)
    print(table(rows))
    unsafe = [r for r in rows if not r["safe"]]
    assert not unsafe, unsafe


def test_soak(tmp_path: Path) -> None:
    hours = float(os.environ.get("RELIABILITY_SOAK_HOURS", "1"))
    result = asyncio.run(soak(hours, tmp_path, sample_every_s=min(600.0, hours * 360)))
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "soak.json").write_text(json.dumps({**result, "counters": None}, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k not in ("samples", "counters")}))
    assert all(s["engaged"] for s in result["samples"])
    assert result["rss_mb_per_h"] < 2.0  # MB per simulated hour
    assert result["objects_per_h"] < 2_000
    assert result["cycle_ms_last"] < 1.25 * result["cycle_ms_first"] + 1.0
