"""Config files that go wrong, generated from the schema: each refused, naming the key.

The cases are not listed by hand: they come from walking `ServiceConfig`'s pydantic fields
(nested sections, and the first entry of list-of-model fields such as `sensors`):
- every required key removed in turn;
- every key given a value of the wrong type (a mapping for a scalar or a list, a string for a
  section);
- every numeric bound (gt/ge/lt/le) crossed, NaN/inf where they are refused, a word that is
  not one of a Literal's choices;
- an unknown key added to every section;
and files that cannot be used: missing, a directory, unreadable, not UTF-8, not YAML, empty,
a list at the top. Each must give ConfigError with a line naming the key path (and
`check-config` exit code 2 with that line), never another exception.
"""

from __future__ import annotations

import io
import math
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import annotated_types as at
import pytest
import yaml
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from companion.config import ConfigError, ServiceConfig, check_config, load_config, parse_config
from tests.service_fakes import SENSORS

BASE: dict[str, Any] = {
    "route": {"source": "config", "points": [[10.0, 0.0]]},
    "sensors": SENSORS,
}
FULL: dict[str, Any] = parse_config(BASE).model_dump(mode="json")
"""Every key spelt out (defaults filled in), as config/default.yaml does."""
FULL["route"] = {"source": "config", "points": [[10.0, 0.0]]}  # not both points kinds


def _models(annotation: Any) -> list[type[BaseModel]]:
    """Pydantic models inside an annotation (X, X | None, list[X])."""
    out = []
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        out.append(annotation)
    for arg in typing.get_args(annotation):
        out += _models(arg)
    return out


def _is_list(annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    if origin in (list, tuple):
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_is_list(a) for a in typing.get_args(annotation) if a is not type(None))
    return False


def walk(
    model: type[BaseModel], path: tuple[str | int, ...] = ()
) -> Iterator[tuple[tuple[str | int, ...], FieldInfo, type[BaseModel] | None]]:
    """(path, field, nested model or None) for every field, depth first."""
    for name, info in model.model_fields.items():
        p = (*path, name)
        nested = _models(info.annotation)
        yield p, info, nested[0] if nested else None
        for sub in nested:
            inner = (*p, 0) if _is_list(info.annotation) else p
            yield from walk(sub, inner)


FIELDS = list(walk(ServiceConfig))
SECTIONS = [()] + [
    (*p, 0) if _is_list(info.annotation) else p for p, info, m in FIELDS if m is not None
]


def dotted(path: tuple[str | int, ...]) -> str:
    return ".".join(str(p) for p in path)


def get(doc: Any, path: tuple[str | int, ...]) -> Any:
    for p in path:
        doc = doc[p]
    return doc


def exists(doc: Any, path: tuple[str | int, ...]) -> bool:
    try:
        get(doc, path)
    except (KeyError, IndexError, TypeError):
        return False
    return True


def with_value(path: tuple[str | int, ...], value: Any, delete: bool = False) -> dict[str, Any]:
    doc = yaml.safe_load(yaml.safe_dump(FULL))  # a deep copy through YAML, as a file would be
    parent = get(doc, path[:-1])
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return doc


def refused(doc: Any, path: tuple[str | int, ...], tmp_path: Path) -> list[str]:
    """The error lines for `doc` written to a file; asserts the key path is named."""
    f = tmp_path / "companion.yaml"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError) as err:
        load_config(f)
    lines = err.value.errors
    key = dotted(path)
    assert any(key in line for line in lines), (key, lines)
    out = io.StringIO()
    assert check_config(f, out=out) == 2
    assert key in out.getvalue()
    return lines


# --- the generated cases -------------------------------------------------------------------

REQUIRED = [p for p, info, _ in FIELDS if info.is_required() and exists(FULL, p)]


def _bounds(info: FieldInfo) -> list[Any]:
    """Values just outside every numeric bound of a field (including inside unions)."""
    metas = list(info.metadata)
    stack = [info.annotation]
    while stack:
        a = stack.pop()
        if typing.get_origin(a) is typing.Annotated:
            metas += list(a.__metadata__)
        stack += list(typing.get_args(a))
    values: list[Any] = []
    for m in metas:
        inner = getattr(m, "metadata", [m])  # FieldInfo inside Annotated
        for c in inner if isinstance(inner, list) else [inner]:
            if isinstance(c, at.Gt):
                values.append(c.gt)
            elif isinstance(c, at.Ge):
                values.append(c.ge - (1 if isinstance(c.ge, int) else 1e-6))
            elif isinstance(c, at.Lt):
                values.append(c.lt)
            elif isinstance(c, at.Le):
                values.append(c.le + (1 if isinstance(c.le, int) else 1e-6))
            elif getattr(c, "allow_inf_nan", None) is False:
                values += [math.inf, math.nan]
    return values


def _literal_choices(annotation: Any) -> bool:
    return typing.get_origin(annotation) is typing.Literal or any(
        _literal_choices(a) for a in typing.get_args(annotation)
    )


def _scalar_leaf(p: tuple[str | int, ...], info: FieldInfo, model: Any) -> bool:
    return model is None and exists(FULL, p)


OUT_OF_RANGE = [
    (p, v)
    for p, info, model in FIELDS
    if _scalar_leaf(p, info, model)
    for v in _bounds(info)
    if not isinstance(get(FULL, p), list)
] + [
    (p, "no-such-choice")
    for p, info, model in FIELDS
    if _scalar_leaf(p, info, model) and _literal_choices(info.annotation)
]
WRONG_TYPE = [
    (p, "a section as text" if model is not None else {"unexpected": ["mapping"]})
    for p, _info, model in FIELDS
    if exists(FULL, p)
]


def test_the_schema_walk_finds_every_section_and_key() -> None:
    keys = {dotted(p) for p, _, _ in FIELDS}
    for section in ("link", "identity", "autopilot", "control", "route", "planner", "sensors"):
        assert section in keys
    assert {"failsafe.max_position_jump_m", "autopilot.streams_hz.ATTITUDE"} <= keys
    assert "sensors.0.id" in keys and "control.auto_start.enabled" in keys
    assert len(REQUIRED) >= 4 and len(OUT_OF_RANGE) >= 50 and len(WRONG_TYPE) >= 60


@pytest.mark.parametrize("path", REQUIRED, ids=dotted)
def test_required_key_missing(path: tuple[str | int, ...], tmp_path: Path) -> None:
    lines = refused(with_value(path, None, delete=True), path, tmp_path)
    assert any("required" in line for line in lines)


@pytest.mark.parametrize(
    ("path", "value"), WRONG_TYPE, ids=lambda v: dotted(v) if isinstance(v, tuple) else ""
)
def test_wrong_type(path: tuple[str | int, ...], value: Any, tmp_path: Path) -> None:
    refused(with_value(path, value), path, tmp_path)


@pytest.mark.parametrize(
    ("path", "value"),
    OUT_OF_RANGE,
    ids=[f"{dotted(p)}={v}" for p, v in OUT_OF_RANGE],
)
def test_out_of_range(path: tuple[str | int, ...], value: Any, tmp_path: Path) -> None:
    lines = refused(with_value(path, value), path, tmp_path)
    assert any("found" in line for line in lines)


@pytest.mark.parametrize("section", SECTIONS, ids=lambda p: dotted(p) or "(top level)")
def test_unknown_key(section: tuple[str | int, ...], tmp_path: Path) -> None:
    path = (*section, "no_such_key")
    lines = refused(with_value(path, 1), path, tmp_path)
    assert any("no such key" in line for line in lines)


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (lambda d: d / "missing.yaml", "cannot read the file"),
        (lambda d: d, "cannot read the file"),  # a directory
        (lambda d: _write(d, b"\xff\xfe\x00garbage\x80"), "not UTF-8"),
        (lambda d: _write(d, b"link: [unclosed\n"), "(YAML) line"),
        (lambda d: _write(d, b""), "(top level)"),
        (lambda d: _write(d, b"- a\n- b\n"), "(top level)"),
        (lambda d: _write(d, b"sensors: 12\n"), "sensors"),
    ],
    ids=["missing", "directory", "not-utf8", "not-yaml", "empty", "a-list", "scalar-sensors"],
)
def test_unusable_files(make: Any, expected: str, tmp_path: Path) -> None:
    path = make(tmp_path)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert any(expected in line for line in err.value.errors), err.value.errors
    out = io.StringIO()
    assert check_config(path, out=out) == 2
    assert expected in out.getvalue()


def test_unreadable_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Permission denied (faked: the tests may run as root, who can read anything)."""
    f = _write(tmp_path, yaml.safe_dump(FULL).encode())
    real = Path.read_text

    def denied(self: Path, *a: Any, **k: Any) -> str:
        if self == f:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *a, **k)

    monkeypatch.setattr(Path, "read_text", denied)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    assert "Permission denied" in err.value.errors[0]


def test_the_full_document_is_valid(tmp_path: Path) -> None:
    f = _write(tmp_path, yaml.safe_dump(FULL).encode())
    assert load_config(f).sensors[0].id == SENSORS[0]["id"]


def _write(d: Path, data: bytes) -> Path:
    f = d / "companion.yaml"
    f.write_bytes(data)
    return f
