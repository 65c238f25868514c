"""The Makefile finds a Python >= 3.11 or says what to install; it never installs anything."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

MAKEFILE = Path(__file__).resolve().parents[1] / "Makefile"

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def _fake(bin_dir: Path, name: str, script: str) -> None:
    path = bin_dir / name
    path.write_text("#!/bin/sh\n" + script, encoding="utf-8")
    path.chmod(0o755)


def _make(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """`make .venv/.installed` in an empty directory with only fake tools on PATH."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    # an old Python, and package managers that record being called
    _fake(bin_dir, "python3", 'case "$1" in -V) echo "Python 3.9.2";; *) exit 1;; esac\n')
    for tool in ("apt-get", "apt", "sudo"):
        _fake(bin_dir, tool, f'echo called >> "{tmp_path}/{tool}.called"\n')
    work = tmp_path / "work"
    work.mkdir(exist_ok=True)
    (work / "pyproject.toml").write_text("", encoding="utf-8")
    env = {"PATH": str(bin_dir), "HOME": str(tmp_path), "LANG": "C"}
    make = shutil.which("make")
    assert make is not None
    return subprocess.run(
        [make, "-f", str(MAKEFILE), "-C", str(work), *args, ".venv/.installed"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _nothing_installed(tmp_path: Path) -> None:
    assert not list(tmp_path.glob("*.called")), "make ran a package manager"
    assert not (tmp_path / "work" / ".venv").exists()


def test_no_suitable_python_says_what_to_install(tmp_path: Path) -> None:
    proc = _make(tmp_path)
    assert proc.returncode != 0
    assert "no Python >= 3.11 found" in proc.stdout
    assert "sudo apt install python3 python3-venv" in proc.stdout
    assert "make PY=" in proc.stdout
    _nothing_installed(tmp_path)


def test_a_named_old_python_is_refused(tmp_path: Path) -> None:
    proc = _make(tmp_path, f"PY={tmp_path / 'bin' / 'python3'}")
    assert proc.returncode != 0
    assert "is Python 3.9.2; the project needs Python >= 3.11" in proc.stdout
    _nothing_installed(tmp_path)


def test_a_python_without_venv_is_refused_without_installing(tmp_path: Path) -> None:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    # 3.11 by version, but `import ensurepip` fails (Debian without python3.11-venv)
    _fake(
        bin_dir,
        "python3.11",
        'case "$2" in *ensurepip*) exit 1;; *executable*) echo python3.11;; esac\n',
    )
    proc = _make(tmp_path)
    assert proc.returncode != 0, proc.stdout
    assert "cannot make a venv" in proc.stdout and "python3.11-venv" in proc.stdout
    _nothing_installed(tmp_path)
    assert os.access(bin_dir / "python3.11", os.X_OK)
