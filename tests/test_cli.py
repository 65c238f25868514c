"""The `companion` command's options: --version, -v/--log-level, --connection, --json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from companion import cli

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "paper.yaml"


@pytest.mark.parametrize(
    ("extra", "level"),
    [([], None), (["-v"], "info"), (["-vv"], "debug"), (["--log-level", "error"], "error")],
)
def test_run_passes_connection_and_log_level(
    extra: list[str], level: str | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    import companion.service

    seen: list[tuple[object, ...]] = []
    monkeypatch.setattr(companion.service, "main", lambda *a, **k: seen.append(a) or 0)
    argv = ["run", "--config", str(CONFIG), "--connection", "udp://:14541", *extra]
    assert cli.main(argv) == 0
    assert seen == [(CONFIG, "udpin:0.0.0.0:14541", level)]


def test_check_config_connection_override(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["check-config", str(CONFIG), "--connection", "udpin://0.0.0.0:14542"]) == 0
    assert "link udpin:0.0.0.0:14542" in capsys.readouterr().out


def test_check_config_says_when_the_serial_device_is_missing(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    missing = tmp_path / "ttyACM9"
    code = cli.main(["check-config", str(CONFIG), "--connection", f"serial://{missing}:57600"])
    out, err = capsys.readouterr()
    assert code == 0  # a USB autopilot may appear after boot: a warning, not an error
    assert f"link serial:{missing}:57600" in out
    assert f"serial device {missing}: No such file or directory" in err
    regular = tmp_path / "not-a-tty"
    regular.write_text("", encoding="utf-8")
    assert cli.main(["check-config", str(CONFIG), "--connection", f"serial:{regular}:57600"]) == 0
    assert "not a serial (character) device" in capsys.readouterr().err


def test_check_config_says_when_the_host_does_not_resolve(
    capsys: pytest.CaptureFixture[str],
) -> None:
    conn = "udpout:no-such-host.invalid:14550"
    assert cli.main(["check-config", str(CONFIG), "--connection", conn]) == 0
    assert "host 'no-such-host.invalid' does not resolve" in capsys.readouterr().err


def test_load_config_connection_override_keeps_the_rest() -> None:
    from companion.config import load_config

    base = load_config(CONFIG)
    over = load_config(CONFIG, connection="udpout:127.0.0.1:14580")
    assert over.link.connection == "udpout:127.0.0.1:14580"
    assert over.model_dump(exclude={"link"}) == base.model_dump(exclude={"link"})


@pytest.mark.timeout(300)
def test_simulate_json_prints_the_metrics_document(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenario = ROOT / "config" / "scenarios" / "smooth-hill.yaml"
    out = tmp_path / "out"
    assert cli.main(["simulate", str(scenario), "--out", str(out), "--no-plots", "--json"]) == 0
    stdout, stderr = capsys.readouterr()
    doc = json.loads(stdout)  # stdout holds the JSON document alone
    assert doc == json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert doc["scenario"] == "smooth-hill" and doc["reached_goal"] is True
    assert "scenario smooth-hill" in stderr  # the human table went to stderr
    assert not (out / "fig6.png").exists()


@pytest.mark.parametrize(
    ("extra", "quiet", "persist"),
    [([], False, False), (["--quiet"], True, False), (["--persist-params"], False, True)],
)
def test_run_passes_quiet_and_persist_params(
    extra: list[str], quiet: bool, persist: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    import companion.service

    seen: list[dict[str, object]] = []
    monkeypatch.setattr(companion.service, "main", lambda *a, **k: seen.append(k) or 0)
    assert cli.main(["run", "--config", str(CONFIG), *extra]) == 0
    assert seen == [{"quiet": quiet, "persist_params": persist}]
