"""Typed settings schemas for backends and profile sections.

A schema is a ``dict[str, Setting]``. :func:`validate_settings` checks a TOML table against it
and returns a complete dict (defaults filled in). Every error names the file, the dotted key
path, the bad value and what would be valid, so the user can fix the profile in one go.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from dotshell.errors import ProfileError

_KINDS = {"bool", "int", "float", "str", "list[float]", "list[int]", "list[str]", "table",
          "matrix"}
REQUIRED = object()


@dataclass(frozen=True)
class Setting:
    """One setting.

    Attributes:
        kind: ``bool``, ``int``, ``float``, ``str``, ``list[float]``, ``list[int]``,
            ``list[str]``, ``matrix`` (list of lists of numbers) or ``table`` (free-form).
        default: value used when the key is absent; :data:`REQUIRED` makes it mandatory.
        help: one line for users; say the unit.
        unit: unit of the value (``mm``, ``deg``, ``px``, ``ms`` ...) for documentation.
        choices: allowed values, when the set is closed.
        min, max: inclusive bounds for numbers (and for each list item).
        length: exact length for lists, ``(rows, cols)`` for matrices.
        schema: nested schema for ``table`` settings with a fixed shape.
    """

    kind: str
    default: Any = REQUIRED
    help: str = ""
    unit: str = ""
    choices: tuple | None = None
    min: float | None = None
    max: float | None = None
    length: int | tuple[int, int] | None = None
    schema: Mapping[str, Setting] | None = field(default=None)

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"unknown setting kind {self.kind!r}; use one of {sorted(_KINDS)}")

    @property
    def required(self) -> bool:
        return self.default is REQUIRED


def _fail(where: str, key: str, value: Any, expected: str) -> ProfileError:
    return ProfileError(f"{where}: [{key}] = {value!r} is invalid: expected {expected}.")


def _check_number(where: str, key: str, value: Any, s: Setting, integer: bool) -> float | int:
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok:
        raise _fail(where, key, value, "an integer" if integer else "a number"
                    + (f" in {s.unit}" if s.unit else ""))
    if not math.isfinite(value):  # comparisons with NaN are all false: refuse it first
        raise _fail(where, key, value, "a finite number" + (f" in {s.unit}" if s.unit else "")
                    + " (nan and inf are not values a device or a step can use)")
    if (s.min is not None and value < s.min) or (s.max is not None and value > s.max):
        lo = "-inf" if s.min is None else s.min
        hi = "+inf" if s.max is None else s.max
        raise _fail(where, key, value, f"a value in [{lo}, {hi}]" + (f" {s.unit}" if s.unit else ""))
    return value if integer else float(value)


def _check_value(where: str, key: str, value: Any, s: Setting) -> Any:
    k = s.kind
    if k == "bool":
        if not isinstance(value, bool):
            raise _fail(where, key, value, "true or false")
    elif k in ("int", "float"):
        value = _check_number(where, key, value, s, k == "int")
    elif k == "str":
        if not isinstance(value, str):
            raise _fail(where, key, value, "a string")
    elif k.startswith("list["):
        if not isinstance(value, list):
            raise _fail(where, key, value, f"a list ({k})")
        if isinstance(s.length, int) and len(value) != s.length:
            raise _fail(where, key, value, f"a list of exactly {s.length} items")
        item = Setting(k[5:-1], min=s.min, max=s.max, unit=s.unit)
        value = [_check_value(where, f"{key}[{i}]", v, item) for i, v in enumerate(value)]
        return value
    elif k == "matrix":
        rows, cols = s.length if isinstance(s.length, tuple) else (None, None)
        if not isinstance(value, list) or not all(isinstance(r, list) for r in value):
            raise _fail(where, key, value, "a list of rows (a matrix)")
        if rows is not None and (len(value) != rows or any(len(r) != cols for r in value)):
            raise _fail(where, key, value, f"a {rows}x{cols} matrix")
        num = Setting("float")
        return [[_check_value(where, f"{key}[{i}][{j}]", v, num) for j, v in enumerate(r)]
                for i, r in enumerate(value)]
    elif k == "table":
        if not isinstance(value, dict):
            raise _fail(where, key, value, "a table")
        if s.schema is not None:
            return validate_settings(s.schema, value, where, key)
        return dict(value)
    if s.choices is not None and value not in s.choices:
        raise ProfileError(f"{where}: [{key}] = {value!r} is not a valid choice. "
                           f"Valid choices: {', '.join(map(repr, s.choices))}.")
    return value


def validate_settings(schema: Mapping[str, Setting], data: Mapping[str, Any] | None,
                      where: str, prefix: str = "") -> dict[str, Any]:
    """Check ``data`` against ``schema``; return a new dict with defaults filled in.

    Args:
        schema: the settings schema.
        data: the table read from TOML (``None`` means empty).
        where: the file (or other origin) named in errors.
        prefix: dotted key path of ``data`` inside the file, for errors.

    Raises:
        ProfileError: on an unknown key, a missing required key, a wrong type or a bad value.
    """
    data = dict(data or {})
    dot = f"{prefix}." if prefix else ""
    unknown = sorted(set(data) - set(schema))
    if unknown:
        raise ProfileError(
            f"{where}: unknown key [{dot}{unknown[0]}]. Valid keys here: "
            f"{', '.join(sorted(schema)) or '(none)'}.")
    out: dict[str, Any] = {}
    for name, s in schema.items():
        key = f"{dot}{name}"
        if data.get(name) is None:  # absent (TOML has no null; None is our own default)
            if s.required:
                raise ProfileError(f"{where}: missing required key [{key}] ({s.kind}"
                                   + (f", {s.unit}" if s.unit else "") + f"): {s.help}")
            fill = s.kind == "table" and s.schema is not None and s.default == {}
            out[name] = validate_settings(s.schema, {}, where, key) if fill and s.schema else s.default
            continue
        out[name] = _check_value(where, key, data[name], s)
    return out


def describe(schema: Mapping[str, Setting]) -> list[tuple[str, str, str, str]]:
    """Rows of (key, kind, default, help) for docs and ``dotshell plugins --settings``: the
    kind with its unit and limits (``float [deg] 0..360``), the help with the choices."""
    rows = []
    for name, s in schema.items():
        default = "(required)" if s.required else repr(s.default)
        kind = s.kind + (f" [{s.unit}]" if s.unit else "")
        if s.min is not None and s.max is not None:
            kind += f" {s.min:g}..{s.max:g}"
        elif s.min is not None or s.max is not None:
            kind += f" ≥ {s.min:g}" if s.min is not None else f" ≤ {s.max:g}"
        text = s.help
        if s.choices is not None:
            text += f" (choices: {', '.join(map(str, s.choices))})"
        rows.append((name, kind, default, text))
    return rows
