"""Typed settings objects shared by code, command line and ROS parameters (no ROS import).

A settings class is a frozen dataclass whose fields are made with :func:`setting`. Each field
carries its help text, unit, bounds or choices, and how it appears as a ROS parameter (REP 103
SI units at that boundary: ``ros_scale`` multiplies the core value, e.g. 1e-3 for mm -> m;
``ros_none`` is the ROS value that stands for None, since ROS parameters have no null). A field
whose default is a tuple is a list of numbers (a ROS double or integer array; ``length`` items,
each checked against the bounds) or, with ``item_kind=str`` or a default of strings, a list of strings (a
ROS string array, any number of items); an optional list (default None) without ``ros_none`` is an empty
array on ROS (unset); an optional number, string or flag needs a ``ros_none``. The
nodes declare their parameters from these fields (:func:`robot_ct_ros.nodes.common.declare_settings`),
the CLI builds its options from them, and ``to_dict`` goes into report.json, so a new setting
reaches every front end at once, in the style of generate_parameter_library.

Validation lives here too: :func:`validate` checks every field against its bounds and
choices and raises one ``ValueError`` naming the field and what it accepts.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

__all__ = ["setting", "SettingSpec", "specs", "validate", "to_dict", "ros_defaults", "from_ros_values",
           "with_changes", "yaml_lines"]


SCALED_DIGITS = 12
"""Significant digits of a value converted between core and ROS units: the conversion's rounding noise
(0.3 deg is 0.005235987755982988 rad, back 0.30000000000000004 deg) is dropped, so that a config file,
a node's default and the library's default are the same value."""


def _unscaled(value, scale: float) -> float:
    """A ROS value in core units (``value / scale``, to :data:`SCALED_DIGITS` significant digits)."""
    x = float(value) / scale
    return x if scale == 1.0 or not math.isfinite(x) else float(f"{x:.{SCALED_DIGITS}g}")


def setting(default, help: str, *, unit: str = "", minimum=None, maximum=None, choices=None,
            ros_name: str | None = None, ros_scale: float = 1.0, ros_unit: str | None = None, ros_none=None,
            ros: bool = True, kind: type | None = None, length: int | None = None,
            item_kind: type | None = None) -> dataclasses.Field:
    """A dataclass field with what the front ends need to show, parse and check it.

    ``choices`` is a tuple or a zero-argument callable returning one (a registry filled later);
    ``minimum``/``maximum`` are inclusive bounds in core units; ``ros_unit`` the unit after
    ``ros_scale`` (default ``unit``); ``ros=False`` keeps a field off ROS; ``kind`` is the value
    type when the default is None (e.g. an optional int; ``tuple`` for an optional list).
    List fields (a tuple default, or ``kind=tuple``): ``length`` is the number of items (default:
    the length of a non-empty default of numbers, else any number), ``item_kind`` float, int or str (default:
    str when every item of a non-empty default is a string, int when every one is an int, else float); bounds and
    ``ros_scale`` apply to each number, and an optional list (default None) set to an empty list on ROS counts as
    unset."""
    return dataclasses.field(default=default, metadata={
        "help": help, "unit": unit, "minimum": minimum, "maximum": maximum, "choices": choices,
        "ros_name": ros_name, "ros_scale": float(ros_scale),
        "ros_unit": unit if ros_unit is None else ros_unit, "ros_none": ros_none, "ros": ros, "kind": kind,
        "length": length, "item_kind": item_kind})


@dataclass(frozen=True)
class SettingSpec:
    """What :func:`setting` recorded about one field, resolved."""

    name: str
    default: Any
    kind: type
    help: str
    unit: str
    minimum: Any
    maximum: Any
    choices: tuple | None
    ros_name: str
    ros_scale: float
    ros_unit: str
    ros_none: Any
    ros: bool
    length: int | None = None      # list fields: the number of items (None = any)
    item_kind: type | None = None  # list fields: float, int or str

    def to_ros(self, value):
        """The ROS parameter value of a core value (None -> ``ros_none``)."""
        if value is None:
            return self.ros_none
        if self.kind is tuple:
            if self.item_kind in (int, str):
                return [self.item_kind(x) for x in value]
            return [float(x) * self.ros_scale for x in value]
        if self.kind is float:
            return float(value) * self.ros_scale
        return self.kind(value)

    def from_ros(self, value):
        """The core value of a ROS parameter value (``ros_none`` -> None)."""
        if self.ros_none is not None and value == self.ros_none:
            return None
        if self.kind is tuple:
            if value is None or (self.default is None and len(value) == 0):
                return None  # an optional list left unset (or set to [])
            if self.item_kind in (int, str):
                return tuple(self.item_kind(x) for x in value)
            return tuple(_unscaled(x, self.ros_scale) for x in value)
        if self.kind is float:
            return _unscaled(value, self.ros_scale)
        if self.kind is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(f"{self.ros_name} must be a whole number, got {value!r}")
            return int(value)
        if self.kind is bool:
            return bool(value)
        return str(value)

    def coerce(self, value):
        """``value`` as this field stores it: a numpy scalar as the Python number it holds (a notebook's
        ``np.int64(3)``), a whole float as an int for an int field (``iterations=2.0``); unchecked."""
        if hasattr(value, "dtype") and hasattr(value, "item") and getattr(value, "ndim", None) == 0:
            value = value.item()
        if self.kind is tuple and isinstance(value, (list, tuple)):
            return tuple(x.item() if hasattr(x, "dtype") and hasattr(x, "item") else x for x in value)
        if self.kind is int and isinstance(value, float) and value.is_integer():
            return int(value)
        return value

    def check(self, value) -> None:
        """Raise ValueError unless ``value`` is acceptable for this field."""
        if value is None:
            if self.default is None:
                return
            raise ValueError(f"{self.name} must be given")
        if self.kind is tuple:
            self._check_items(value)
            return
        if self.kind is bool and not isinstance(value, bool):  # "false" or "off" would count as true
            raise ValueError(f"{self.name} must be True or False, got {value!r}")
        if self.kind in (int, float) and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise ValueError(f"{self.name} must be a number, got {value!r}")
        if self.kind is int and isinstance(value, float) and not value.is_integer():
            raise ValueError(f"{self.name} must be a whole number, got {value!r}")
        if self.kind is float and not math.isfinite(value):
            raise ValueError(f"{self.name} must be finite, got {value!r}")
        unit = f" {self.unit}" if self.unit else ""
        if self.minimum is not None and not value >= self.minimum:
            raise ValueError(f"{self.name} must be >= {self.minimum}{unit}, got {value!r}")
        if self.maximum is not None and not value <= self.maximum:
            raise ValueError(f"{self.name} must be <= {self.maximum}{unit}, got {value!r}")
        if self.choices is not None and value not in self.choices:
            shown = ", ".join('""' if c == "" else str(c) for c in self.choices)  # an empty choice shown, not blank
            raise ValueError(f"{self.name} must be one of {shown}; got {value!r}")

    def _check_items(self, value) -> None:
        unit = f" {self.unit}" if self.unit else ""
        what = {int: "whole numbers", str: "strings"}.get(self.item_kind, "numbers")
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
            raise ValueError(f"{self.name} must be a list of {what}{unit}, got {value!r}")
        if self.length is not None and len(value) != self.length:
            raise ValueError(f"{self.name} needs {self.length} {what}{unit}, got {list(value)!r}")
        if self.item_kind is str:
            if not all(isinstance(x, str) for x in value):
                raise ValueError(f"{self.name} must be a list of strings, got {list(value)!r}")
            return
        for x in value:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or (
                    self.item_kind is int and isinstance(x, float) and not x.is_integer()):
                raise ValueError(f"{self.name} must be a list of finite {what}{unit}, got {list(value)!r}")
            if self.minimum is not None and not x >= self.minimum:
                raise ValueError(f"{self.name}: every item must be >= {self.minimum}{unit}, got {list(value)!r}")
            if self.maximum is not None and not x <= self.maximum:
                raise ValueError(f"{self.name}: every item must be <= {self.maximum}{unit}, got {list(value)!r}")


def specs(cls_or_obj) -> tuple[SettingSpec, ...]:
    """The :class:`SettingSpec` of every field of a settings class (or instance), in order."""
    out = []
    for f in dataclasses.fields(cls_or_obj):
        m = f.metadata
        if "help" not in m:
            continue
        choices = m["choices"]() if callable(m["choices"]) else m["choices"]
        kind = m["kind"] or type(f.default)
        length, item_kind = m.get("length"), m.get("item_kind")
        if kind is tuple:
            items = f.default if isinstance(f.default, tuple) else ()
            if item_kind is None:
                item_kind = (str if items and all(isinstance(x, str) for x in items) else
                             int if items and all(type(x) is int for x in items) else float)
            if length is None and items and item_kind is not str:
                length = len(items)
        out.append(SettingSpec(f.name, f.default, kind, m["help"], m["unit"], m["minimum"], m["maximum"],
                               None if choices is None else tuple(choices), m["ros_name"] or f.name,
                               m["ros_scale"], m["ros_unit"], m["ros_none"], m["ros"], length, item_kind))
    return tuple(out)


def validate(obj) -> None:
    """Check every field of a settings instance (:meth:`SettingSpec.check`), each first stored as the field
    keeps it (:meth:`SettingSpec.coerce`; the instance may be frozen)."""
    for s in specs(obj):
        value = getattr(obj, s.name)
        coerced = s.coerce(value)
        s.check(coerced)
        if coerced is not value:
            object.__setattr__(obj, s.name, coerced)


def to_dict(obj) -> dict:
    """Field name -> value (tuples as lists): what report.json records."""
    return {s.name: (list(v) if isinstance(v := getattr(obj, s.name), tuple) else v) for s in specs(obj)}


def ros_defaults(cls) -> dict:
    """ROS parameter name -> ROS default value of every field shown on ROS."""
    return {s.ros_name: s.to_ros(s.default) for s in specs(cls) if s.ros}


def from_ros_values(cls, values: dict, **fixed):
    """A validated instance of ``cls`` from ROS parameter values (name -> value; missing ones take
    their defaults); ``fixed`` sets fields directly, in core units."""
    kwargs = dict(fixed)
    for s in specs(cls):
        if s.ros and s.ros_name in values and s.name not in kwargs:
            kwargs[s.name] = s.from_ros(values[s.ros_name])
    return cls(**kwargs)


def with_changes(obj, **changes):
    """``dataclasses.replace`` that also validates (settings classes validate in __post_init__)."""
    return dataclasses.replace(obj, **changes)


def yaml_lines(cls, indent: int = 4, exclude=()) -> list[str]:
    """The ROS parameters of ``cls`` with their defaults as YAML lines (``name: value  # help [unit]``),
    for a node's config/*.yaml: the files list every setting, and a test checks they do."""
    import json

    rows = []
    for s in specs(cls):
        if not s.ros or s.name in exclude:
            continue
        v = s.to_ros(s.default)
        text = ("true" if v else "false") if isinstance(v, bool) else json.dumps(v) if isinstance(v, (str, list, tuple)) \
            else (repr(float(f"{v:.{SCALED_DIGITS}g}")) if isinstance(v, float) else str(v))
        unit = f" [{s.ros_unit}]" if s.ros_unit else ""
        off = f"; {json.dumps(s.ros_none) if isinstance(s.ros_none, str) else s.ros_none} = off" if s.ros_none is not None \
            else ""
        rows.append((f"{' ' * indent}{s.ros_name}: {text}", f"# {s.help}{unit}{off}"))
    width = max(len(a) for a, _ in rows) + 1
    return [f"{a:<{width}} {b}" for a, b in rows]
