"""The service config: defaults in sync with config/default.yaml, errors that name the key."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import pytest
import yaml

from companion.config import (
    AutopilotConfig,
    ConfigError,
    ControlConfig,
    FailsafeConfig,
    IdentityConfig,
    LinkConfig,
    LoggingConfig,
    ServiceConfig,
    SigningConfig,
    StatustextConfig,
    check_config,
    load_config,
    parse_config,
)
from companion.tuning import PlannerConfig

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "config"


def minimal() -> dict[str, Any]:
    data = yaml.safe_load((CONFIGS / "default.yaml").read_text())
    return {"sensors": data["sensors"]}


def errors_of(data: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    return info.value.errors


def test_default_yaml_spells_out_every_schema_default() -> None:
    data = yaml.safe_load((CONFIGS / "default.yaml").read_text())
    cfg = parse_config(data)
    defaults = {
        "link": LinkConfig(),
        "identity": IdentityConfig(),
        "autopilot": AutopilotConfig(),
        "control": ControlConfig(),
        "planner": PlannerConfig(),
        "failsafe": FailsafeConfig(),
        "signing": SigningConfig(),
        "logging": LoggingConfig(),
        "statustext": StatustextConfig(),
    }
    for name, default in defaults.items():
        assert getattr(cfg, name) == default, name
    assert cfg.route == ServiceConfig.model_fields["route"].default
    # and the file names every key of the schema (nothing left implicit)
    dumped = cfg.model_dump(mode="json")
    for section, value in dumped.items():
        if isinstance(value, dict):
            assert set(value) == set(data[section]), section


@pytest.mark.parametrize("name", ["default", "sitl-copter", "px4-sitl", "paper"])
def test_shipped_configs_are_valid(name: str) -> None:
    out = io.StringIO()
    assert check_config(CONFIGS / f"{name}.yaml", out) == 0
    assert "OK" in out.getvalue()
    assert "sensor layout: flags a wall ahead as steep" in out.getvalue()


def test_check_config_says_where_the_layout_does_not_look_level() -> None:
    """The paper's layout (the default config's) has level beams only ahead and abeam."""
    out = io.StringIO()
    assert check_config(CONFIGS / "default.yaml", out) == 0
    line = out.getvalue().splitlines()[1]
    assert "the widest 90 deg (90 deg left to the nose)" in line
    # (the yaw sweep counts the beams tilted 25 degrees up: gaps of 45 degrees)
    assert line.endswith(
        "moving, the heading swings 22 deg either way over 4 m of travel (yaw_sweep_period_m)"
    )


def test_minimal_config_takes_defaults() -> None:
    cfg = parse_config(minimal())
    assert cfg.control.rate_hz == 20.0
    assert cfg.identity.component_id == 191
    assert cfg.route.source == "mission"
    assert len(cfg.sensor_table()) == 11


@pytest.mark.parametrize(
    ("patch", "expected"),
    [
        ({"planner": {"h_d_m": -1}}, "planner.h_d_m: expected a number greater than 0, found -1"),
        ({"planner": {"hd": 2}}, "planner.hd: expected no such key"),
        (
            {"planner": {"yaw_sweep_period_m": -4}},
            "planner.yaw_sweep_period_m: expected a number greater than or equal to 0, found -4",
        ),
        ({"control": {"rate_hz": "fast"}}, "control.rate_hz: expected a valid number"),
        ({"identity": {"system_id": 255}}, "identity.system_id"),
        (
            {"link": {"connection": "bogus"}},
            "link.connection: expected a valid value: unknown connection string",
        ),
        ({"link": {"connection": "udpin:host:99999"}}, "port must be 0..65535"),
        (
            {"route": {"source": "config"}},
            "route: expected a valid value: source 'config' needs exactly one",
        ),
        (
            {"signing": {"enabled": True}},
            "signing: expected a valid value: signing is enabled: key_file",
        ),
        ({"signing": {"allow_unsigned": ["NOPE"]}}, "unknown MAVLink message name 'NOPE'"),
        ({"failsafe": {"optional_sensor_ids": [99]}}, "optional_sensor_ids [99] are not in"),
        ({"control": {"time_source": "gps"}}, "control.time_source: expected 'monotonic' or 'sim'"),
        ({"bogus": 1}, "bogus: expected no such key"),
    ],
)
def test_errors_name_key_expected_and_found(patch: dict[str, Any], expected: str) -> None:
    data = minimal() | patch
    errs = errors_of(data)
    assert any(expected in e for e in errs), errs
    assert all(": expected " in e and ", found " in e for e in errs), errs


def test_sensor_errors_name_the_entry() -> None:
    data = minimal()
    data["sensors"][2] = {**data["sensors"][2], "max_range_m": "far"}
    errs = errors_of(data)
    assert any(e.startswith("sensors.2.max_range_m: expected a valid number") for e in errs)
    data = minimal()
    data["sensors"][3]["id"] = 0  # duplicate id
    assert any("duplicate sensor ids [0]" in e for e in errors_of(data))
    data = minimal()
    data["sensors"] = [s for s in data["sensors"] if s["group"] != "back"]
    assert any("'back' surface sensor" in e for e in errors_of(data))


def test_missing_sensors_and_not_a_mapping() -> None:
    assert errors_of({}) == ["sensors: expected a value (required key), found nothing"]
    assert "expected a mapping of sections" in errors_of([1, 2])[0]


def test_every_required_key_missing_in_turn() -> None:
    route = {"source": "config", "points": [[1.0, 2.0]]}
    for key in ("id", "role", "group"):
        data = minimal() | {"route": route}
        del data["sensors"][0][key]
        errs = errors_of(data)
        assert f"sensors.0.{key}: expected a value (required key), found nothing" in errs


def test_check_config_prints_errors_and_exit_code(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("planner:\n  h_d_m: -2\n  v_d_mps: .inf\nsensors: []\n")
    out = io.StringIO()
    assert check_config(bad, out) == 2
    text = out.getvalue()
    assert "planner.h_d_m: expected a number greater than 0, found -2" in text
    assert "planner.v_d_mps:" in text and "found inf" in text
    assert "sensors: expected" in text


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    out = io.StringIO()
    assert check_config(tmp_path / "missing.yaml", out) == 2
    assert "cannot read the file" in out.getvalue()
    broken = tmp_path / "broken.yaml"
    broken.write_text("planner: [1, 2\n")
    out = io.StringIO()
    assert check_config(broken, out) == 2
    assert "(YAML) line" in out.getvalue()


def test_relative_paths_resolve_against_the_config_file(tmp_path: Path) -> None:
    f = tmp_path / "c.yaml"
    data = minimal() | {"logging": {"flight_log_dir": "logs"}}
    f.write_text(yaml.safe_dump(data))
    cfg = load_config(f)
    assert cfg.logging.flight_log_dir == tmp_path / "logs"


def test_signing_key_file_checked_by_check_config(tmp_path: Path) -> None:
    key = tmp_path / "key"
    key.write_text("abc")
    f = tmp_path / "c.yaml"
    f.write_text(yaml.safe_dump(minimal() | {"signing": {"enabled": True, "key_file": "key"}}))
    out = io.StringIO()
    assert check_config(f, out) == 2
    assert "signing.key_file:" in out.getvalue()
    key.write_text("ab" * 32)
    assert check_config(f, io.StringIO()) == 0
