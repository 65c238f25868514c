"""Every `companion` subcommand refuses each kind of bad argument the same way: exit code 2,
one line on stderr naming the problem, no traceback, and before any work starts.

The good command line of each subcommand is built from its arguments' types (`ScenarioFile`,
`OutputDir`, ...), so a new subcommand built from the same types is covered without editing
this file; one with a required argument of another type is skipped with the reason.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from companion import cli

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "config" / "scenarios" / "smooth-hill.yaml"
CONFIG = ROOT / "config" / "paper.yaml"


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = cli._parser()
    sub = parser.get_default("_subparsers")
    return dict(sub.choices)


COMMANDS = sorted(_subcommands())


def _dests(command: str, kind: type) -> list[str]:
    return [a.dest for a in _subcommands()[command]._actions if isinstance(a.type, kind)]


def _taking(kind: type) -> list[str]:
    """The subcommands with an argument of this type."""
    return [c for c in COMMANDS if _dests(c, kind)]


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    """Good inputs of each kind, and the material for bad ones."""
    log = tmp_path / "flight.jsonl"
    log.write_text('{"type": "header", "planner": {"h_d_m": 3.0}}\n', encoding="utf-8")
    return {"scenario": SCENARIO, "config": CONFIG, "log": log, "out": tmp_path / "out"}


def _good_value(action: argparse.Action, files: dict[str, Path]) -> str | None:
    t = action.type
    if isinstance(t, cli.ScenarioFile):
        return str(files["scenario"])
    if isinstance(t, cli.FlightLogFile):
        return str(files["log"])
    if isinstance(t, cli.ConfigFile):
        return str(files["config"])
    if isinstance(t, cli.OutputDir):
        return str(files["out"])
    if isinstance(t, cli.Connection):
        return "udpin:127.0.0.1:14540"
    return None


def _argv(command: str, files: dict[str, Path], replace: dict[str, str] | None = None) -> list[str]:
    """A good command line for `command`, with `replace` (dest -> text) swapped in; the
    argument with a replaced dest is given even if optional."""
    replace = replace or {}
    argv: list[str] = [command]
    positionals: list[str] = []
    for action in _subcommands()[command]._actions:
        if isinstance(action, argparse._HelpAction) or action.dest in ("verbose", "log_level"):
            continue
        given = action.dest in replace
        if not (action.required or given):
            continue
        value = replace[action.dest] if given else _good_value(action, files)
        if value is None:
            pytest.skip(f"{command}: no known good value for required {action.dest}")
        if action.option_strings:
            argv += [action.option_strings[-1], value]
        else:
            positionals.append(value)
    return argv + positionals


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if a command's work starts."""

    def forbidden(*args: object, **kwargs: object) -> int:
        raise AssertionError("the command started its work on bad input")

    import companion.config
    import companion.harness.fly
    import companion.harness.runner
    import companion.service

    for module, name in [
        (companion.harness.runner, "simulate"),
        (companion.harness.fly, "fly"),
        (companion.harness.fly, "report"),
        (companion.service, "main"),
        (companion.config, "check_config"),
    ]:
        monkeypatch.setattr(module, name, forbidden)


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run in process; assert exit 2 and one stderr line without a traceback; return it."""
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code if isinstance(exc.code, int) else 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2, (argv, code, err)
    assert len(lines) == 1, (argv, err)
    assert "Traceback" not in err
    assert out == ""
    return lines[0]


def _bad_scenario(tmp_path: Path, kind: str) -> Path:
    """A scenario whose height map file is `kind`: missing, corrupt, 1-D or NaN."""
    npy = tmp_path / f"{kind}.npy"
    if kind == "corrupt":
        npy.write_bytes(b"\x93NUMPY garbage")
    elif kind == "empty":
        npy.write_bytes(b"")
    elif kind == "1-D":
        np.save(npy, np.zeros(10))
    elif kind == "NaN":
        grid = np.zeros((10, 10))
        grid[3, 4] = np.nan
        np.save(npy, grid)
    text = SCENARIO.read_text(encoding="utf-8").replace(
        "features:\n",
        f"features:\n    - {{type: heightmap, file: {npy.name}, resolution_m: 1.0}}\n",
    )
    text = text.replace("../sensors/", f"{SCENARIO.parent.parent / 'sensors'}/")
    path = tmp_path / f"scenario-{kind}.yaml"
    path.write_text(text, encoding="utf-8")
    return path


# --- input files ---------------------------------------------------------------------------


@pytest.mark.parametrize("command", _taking(cli.InputFile))
@pytest.mark.parametrize("kind", ["missing", "directory"])
def test_missing_input_file(
    command: str,
    kind: str,
    files: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    no_work: None,
) -> None:
    dests = _dests(command, cli.InputFile)
    bad = tmp_path / "nope.yaml" if kind == "missing" else tmp_path
    for dest in dests:
        line = _refused(_argv(command, files, {dest: str(bad)}), capsys)
        assert str(bad) in line
        assert ("no such file" if kind == "missing" else "not a file") in line


@pytest.mark.parametrize("command", _taking(cli.ScenarioFile))
@pytest.mark.parametrize("kind", ["missing", "corrupt", "empty", "1-D", "NaN", "bad key"])
def test_bad_scenario_or_height_map(
    command: str,
    kind: str,
    files: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    no_work: None,
) -> None:
    dests = _dests(command, cli.ScenarioFile)
    if kind == "bad key":
        bad = tmp_path / "bad-key.yaml"
        bad.write_text(
            SCENARIO.read_text(encoding="utf-8")
            .replace("duration_s:", "duraton_s:")
            .replace("../sensors/", f"{SCENARIO.parent.parent / 'sensors'}/"),
            encoding="utf-8",
        )
        expected = "duraton_s"
    else:
        bad = _bad_scenario(tmp_path, kind)
        expected = "heightmap"
    for dest in dests:
        line = _refused(_argv(command, files, {dest: str(bad)}), capsys)
        assert expected in line, line


@pytest.mark.parametrize("command", _taking(cli.FlightLogFile))
def test_not_a_flight_log(
    command: str,
    files: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    no_work: None,
) -> None:
    dests = _dests(command, cli.FlightLogFile)
    for content in [b"\xff\xfe binary", b"not json\n", b'{"type": "cycle"}\n', b""]:
        bad = tmp_path / "bad.jsonl"
        bad.write_bytes(content)
        line = _refused(_argv(command, files, {dests[0]: str(bad)}), capsys)
        assert "not a flight log" in line


# --- output directories --------------------------------------------------------------------


def _unwritable(kind: str, tmp_path: Path) -> Path:
    if kind == "existing file":
        f = tmp_path / "a-file"
        f.write_text("x", encoding="utf-8")
        return f
    if kind == "under a file":
        f = tmp_path / "a-file"
        f.write_text("x", encoding="utf-8")
        return f / "out"
    if kind == "/proc":
        return Path("/proc/companion-test-out")
    # read-only directory
    if os.geteuid() == 0:
        pytest.skip("running as root: permission bits do not stop root from writing")
    ro = tmp_path / "read-only"
    ro.mkdir()
    ro.chmod(0o555)
    return ro / "out"


@pytest.mark.parametrize("command", _taking(cli.OutputDir))
@pytest.mark.parametrize("kind", ["existing file", "under a file", "/proc", "read-only"])
def test_unwritable_out(
    command: str,
    kind: str,
    files: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    no_work: None,
) -> None:
    dests = _dests(command, cli.OutputDir)
    bad = _unwritable(kind, tmp_path)
    for dest in dests:
        line = _refused(_argv(command, files, {dest: str(bad)}), capsys)
        assert "output directory" in line


# --- other arguments -----------------------------------------------------------------------


@pytest.mark.parametrize("command", _taking(cli.Connection))
@pytest.mark.parametrize(
    "text", ["tcpin://:5760", "serial_flowcontrol:///dev/ttyACM0:57600", "udpin:14540", "x"]
)
def test_bad_connection(
    command: str,
    text: str,
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    no_work: None,
) -> None:
    dests = _dests(command, cli.Connection)
    line = _refused(_argv(command, files, {dests[0]: text}), capsys)
    assert "connection" in line or "udpin:HOST:PORT" in line or "tcp:HOST:PORT" in line


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", ["nothing", "unknown option", "bad log level"])
def test_usage_errors(
    command: str,
    kind: str,
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    no_work: None,
) -> None:
    if kind == "nothing":
        if not any(a.required for a in _subcommands()[command]._actions):
            pytest.skip(f"{command} has no required argument")
        argv = [command]
    elif kind == "unknown option":
        argv = [*_argv(command, files), "--no-such-option"]
    else:
        argv = [*_argv(command, files), "--log-level", "loud"]
    line = _refused(argv, capsys)
    assert line.startswith("companion") and ": error: " in line


@pytest.mark.parametrize(
    "command", [c for c in COMMANDS if "no_plots" in {a.dest for a in _subcommands()[c]._actions}]
)
def test_plots_without_matplotlib(
    command: str,
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    no_work: None,
) -> None:
    real: Callable[..., object] = cli.importlib.util.find_spec
    monkeypatch.setattr(
        cli.importlib.util,
        "find_spec",
        lambda name, *a: None if name == "matplotlib" else real(name, *a),
    )
    line = _refused(_argv(command, files), capsys)
    assert "--no-plots" in line and "matplotlib" in line


# --- the installed command, end to end -----------------------------------------------------


@pytest.mark.parametrize("command", COMMANDS)
def test_entry_point_one_line(command: str, files: dict[str, Path], tmp_path: Path) -> None:
    """The real process: a missing input file (or, without inputs, a bad option)."""
    dests = _dests(command, cli.InputFile)
    replace = {dests[0]: str(tmp_path / "missing.yaml")} if dests else {}
    argv = _argv(command, files, replace) + ([] if dests else ["--log-level", "loud"])
    proc = subprocess.run(
        [sys.executable, "-m", "companion.cli", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "Traceback" not in proc.stderr


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"companion {version('terrain-companion')}"
