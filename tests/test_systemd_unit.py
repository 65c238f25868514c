"""systemd/companion.service: a bad config is not restarted, and systemd finds nothing to say."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "companion.service"
INSTALLED = "/opt/companion/.venv/bin/companion"


def _service_section() -> dict[str, list[str]]:
    keys: dict[str, list[str]] = {}
    section = ""
    for raw in UNIT.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line
        elif section == "[Service]" and "=" in line and not line.startswith("#"):
            key, _, value = line.partition("=")
            keys.setdefault(key, []).append(value)
    return keys


def test_bad_config_exit_is_not_restarted() -> None:
    keys = _service_section()
    assert keys["Restart"] == ["on-failure"]
    assert "2" in keys["RestartPreventExitStatus"][0].split()
    # RestartPreventExitStatus= covers the main process only: a validating ExecStartPre that
    # exits 2 would still be restarted
    assert "ExecStartPre" not in keys
    assert keys["ExecStart"] == [f"{INSTALLED} run --config /etc/companion/companion.yaml"]


def test_cheap_hardening_is_on() -> None:
    keys = _service_section()
    for key, value in {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "ProtectProc": "invisible",
        "RestrictSUIDSGID": "yes",
        "LockPersonality": "yes",
        "CapabilityBoundingSet": "",
    }.items():
        assert keys.get(key) == [value], key


def test_systemd_analyze_verify_is_clean(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed on this machine")
    companion = shutil.which("companion") or str(Path(sys.executable).parent / "companion")
    if not Path(companion).exists():
        pytest.skip("the companion command is not installed next to this Python")
    unit = tmp_path / "companion.service"  # verify checks that ExecStart= exists
    unit.write_text(UNIT.read_text(encoding="utf-8").replace(INSTALLED, companion), "utf-8")
    proc = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip() == "" and proc.stdout.strip() == "", proc.stderr + proc.stdout
