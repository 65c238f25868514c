"""Which way the doors go between `companion.sim`, `companion.harness` and the rest.

Every import counts, also the ones inside functions (a lazy import hides a cycle, it does not
break it). `sim` is the simulated world and autopilot: it may use the planner's pure modules
and `companion.geo`/`companion.tuning`, never the service nor the harness that drives flights.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("companion",)
SIM = "companion.sim"
HARNESS = "companion.harness"

SIM_UPWARD_ALLOWED: set[str] = set()
"""Modules under sim allowed to import upward: none."""
SIM_FORBIDDEN = ("companion.service", "companion.config", "companion.cli", HARNESS)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {
        _module_name(p): p
        for pkg in PACKAGES
        for p in sorted((ROOT / pkg).rglob("*.py"))
        if "__pycache__" not in p.parts
    }


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Project modules `name` imports anywhere in its source (module names, not symbols)."""
    is_pkg = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_pkg else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for t in targets:
            # the longest known module the dotted name starts with
            parts = t.split(".")
            for k in range(len(parts), 0, -1):
                candidate = ".".join(parts[:k])
                if candidate in known:
                    if candidate != name:
                        found.add(candidate)
                    break
    return found


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {name: _imports(name, path, known) for name, path in mods.items()}


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_the_graph_sees_the_imports_it_checks() -> None:
    graph = _graph()
    assert f"{SIM}.mavlink.telemetry" in graph[f"{SIM}.mavlink.server"]
    assert f"{HARNESS}.closed_loop" in graph[f"{HARNESS}.runner"]
    assert "companion.service" in graph[f"{HARNESS}.fly"]


def test_sim_never_imports_the_service_or_the_harness() -> None:
    graph = _graph()
    wrong = sorted(
        (m, t)
        for m, targets in graph.items()
        if _under(m, SIM) and m not in SIM_UPWARD_ALLOWED
        for t in targets
        if any(_under(t, f) for f in SIM_FORBIDDEN)
    )
    assert not wrong, f"sim imports upward: {wrong}"


def test_the_companion_never_imports_the_simulator_or_the_harness() -> None:
    """Only the command line (`companion.cli`) reaches into the harness and sim."""
    graph = _graph()
    wrong = sorted(
        (m, t)
        for m, targets in graph.items()
        if not (_under(m, SIM) or _under(m, HARNESS)) and m != "companion.cli"
        for t in targets
        if _under(t, SIM) or _under(t, HARNESS)
    )
    assert not wrong, f"companion imports its sim/harness: {wrong}"


def _cycles(graph: dict[str, set[str]], scope: tuple[str, ...]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), within scope."""
    nodes = [m for m in graph if any(_under(m, s) for s in scope)]
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in graph or not any(_under(w, s) for s in scope):
                continue
            # a package's __init__ re-exporting its own modules is not a cycle between rooms
            if _under(w, v) or _under(v, w):
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for n in nodes:
        if n not in index:
            visit(n)
    return out


def test_no_import_cycles_in_sim_or_the_harness() -> None:
    cycles = _cycles(_graph(), (SIM, HARNESS))
    assert not cycles, f"import cycles: {cycles}"


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"sim.a": {"sim.b"}, "sim.b": {"sim.c"}, "sim.c": {"sim.a"}, "sim.d": {"sim.a"}}
    assert _cycles(graph, ("sim",)) == [["sim.a", "sim.b", "sim.c"]]
