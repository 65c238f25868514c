"""Packaging: the licence file, the metadata, and an sdist that carries what the tests read."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_metadata_and_license() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert project["license"] == "MIT"
    assert project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text(encoding="utf-8").startswith("MIT License")
    assert project["authors"] and project["keywords"]
    assert "License :: OSI Approved :: MIT License" not in project["classifiers"]  # PEP 639
    assert any(
        c.startswith("Programming Language :: Python :: 3.11") for c in project["classifiers"]
    )


def test_sdist_carries_what_the_tests_and_docs_use() -> None:
    """Every top-level directory the tests, docs and Makefile read is grafted."""
    manifest = (ROOT / "MANIFEST.in").read_text(encoding="utf-8")
    grafted = set(re.findall(r"^graft (\S+)$", manifest, flags=re.M))
    assert {"config", "docs", "systemd", "tests", "bench"} <= grafted
    included = set(re.findall(r"^include (.+)$", manifest, flags=re.M)[0].split())
    assert {"LICENSE", "README.md", "Makefile"} <= included
    # the tests read these directories: if a new one appears, graft it too
    used = set(
        re.findall(
            r'ROOT / "(\w+)"',
            "".join(p.read_text(encoding="utf-8") for p in (ROOT / "tests").glob("*.py")),
        )
    )
    assert used <= grafted | included | {"companion"}, used - grafted
