"""The nodes of a configuration file's table: each reads and validates one value of the parsed YAML.

A file's table is a tree: :class:`Section` (named fields, unknown keys refused), :class:`ListOf`,
:class:`Tuple`, :class:`MapOf`, :class:`Kinds` (one way of several to reach a device), :class:`Nullable`,
and the leaves :class:`Number`, :class:`Integer`, :class:`Text`, :class:`Id`, :class:`Flag`,
:class:`Choice`, :class:`Serial`, :class:`Note`. Reading checks a value's type before it is shown or
converted, shows it bounded (:func:`show`: a YAML alias bomb or a 400-digit number is described,
never expanded) and refuses it with the file's own error, built from (file, key path, problem), the
problem naming the allowed range or form. A field is optional when its node has a ``default``.
"""

from __future__ import annotations

import datetime
import math
import re
import reprlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from planner.picklable import PicklableError

MAX_STRING = 256
# Camera ids and sector names become file and folder names in a scan: letters, digits, '_', '-'
# and '.', starting with a letter or digit (so never '..', '/', or a hidden file).
ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,31}")


class ConfigError(PicklableError, ValueError):
    """A configuration file is unreadable or a key is missing, unknown or out of range."""

    def __init__(self, path: str, key: str, problem: str) -> None:
        self.path = str(path)
        self.key = key
        self.problem = problem
        super().__init__(f"{self.path}: {key}: {problem}")


ErrorFactory = Callable[[str, str, str], Exception]
"""Builds a file's error from (file, key path, problem)."""


class _ShortRepr(reprlib.Repr):
    """repr() bounded in length and depth; huge integers are described by their size."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict = 2, 4, 4, 4
        self.maxstring, self.maxother = 40, 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 64:  # str() of a huge int is slow, and refused past 4300 digits
            return f"<integer of about {int(x.bit_length() * math.log10(2)) + 1} digits>"
        return repr(x)


_SHORT = _ShortRepr()


def show(value: Any) -> str:
    """A short, bounded rendering of a value from a file, for error messages."""
    return _SHORT.repr(value)


def key_name(key: Any) -> str:
    """A mapping key as written in the file (bounded like :func:`show` when it is not a short string)."""
    return key if isinstance(key, str) and len(key) <= 40 else show(key)


def child(key: str, name: str) -> str:
    """The key path of ``name`` inside ``key`` ("" is the document)."""
    return f"{key}.{name}" if key else name


@dataclass(frozen=True)
class Reader:
    """One file being read: its path, and the error class its refusals raise."""

    path: str
    error: ErrorFactory

    def fail(self, key: str, problem: str) -> Exception:
        return self.error(self.path, key or "<top>", problem)


class _Required:
    def __repr__(self) -> str:
        return "required"


REQUIRED: Any = _Required()


@dataclass(frozen=True)
class Node:
    """One value's form. default: the value of an absent field (REQUIRED: absence is refused);
    doc: what the value means, for the reference page."""

    default: Any = field(default=REQUIRED, kw_only=True)
    doc: str = field(default="", kw_only=True)

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def form(self) -> str:
        """The allowed values in words ("an integer in [1, 127]")."""
        raise NotImplementedError

    def read(self, value: Any, key: str, reader: Reader) -> Any:
        """The validated value; raises the file's error naming ``key`` otherwise."""
        raise NotImplementedError

    def absent(self, key: str, reader: Reader) -> Any:
        """The value of this field when the file leaves it out (it is not required)."""
        return self.default

    def missing(self) -> str:
        """The problem of a required field the file leaves out."""
        return f"missing; expected {self.form()}"

    def refuse(self, value: Any, key: str, reader: Reader) -> Exception:
        return reader.fail(key, f"got {show(value)}; expected {self.form()}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and (
        not isinstance(value, float) or math.isfinite(value))


def _bound(x: float | None, none: str) -> str:
    if x is None:
        return none
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:.12g}"


@dataclass(frozen=True)
class Number(Node):
    """A finite number in [low, high] (None: unbounded), read as float."""

    low: float | None = None
    high: float | None = None

    def form(self) -> str:
        return f"a number in [{_bound(self.low, '-inf')}, {_bound(self.high, 'inf')}]"

    def within(self, value: Any) -> bool:
        # Compared before any conversion: an int and a float compare exactly, while float() of a
        # 400-digit integer overflows.
        return _is_number(value) and (self.low is None or value >= self.low) and (
            self.high is None or value <= self.high)

    def read(self, value: Any, key: str, reader: Reader) -> float:
        if not self.within(value):
            raise self.refuse(value, key, reader)
        return float(value)


@dataclass(frozen=True)
class Integer(Number):
    """A whole number in [low, high] (2.0 counts, 2.5 does not), read as int."""

    def form(self) -> str:
        return f"an integer in [{_bound(self.low, '-inf')}, {_bound(self.high, 'inf')}]"

    def read(self, value: Any, key: str, reader: Reader) -> int:
        if not self.within(value) or (isinstance(value, float) and not value.is_integer()):
            raise self.refuse(value, key, reader)
        return int(value)


@dataclass(frozen=True)
class Text(Node):
    """A string of min_len to max_len characters; with a pattern, matching it whole (``shape``
    says the pattern in words)."""

    pattern: re.Pattern[str] | None = None
    shape: str = ""
    min_len: int = 1
    max_len: int = MAX_STRING

    def form(self) -> str:
        if self.shape:
            return self.shape
        return f"a {'non-empty ' if self.min_len else ''}string of at most {self.max_len} characters"

    def read(self, value: Any, key: str, reader: Reader) -> str:
        if not isinstance(value, str) or not self.min_len <= len(value) <= self.max_len or (
                self.pattern is not None and not self.pattern.fullmatch(value)):
            raise self.refuse(value, key, reader)
        return value


@dataclass(frozen=True)
class Id(Text):
    """A name that becomes a file or folder name in a scan (:data:`ID_PATTERN`)."""

    pattern: re.Pattern[str] | None = ID_PATTERN
    shape: str = "an id of 1 to 32 letters, digits, '_', '-' or '.', starting with a letter or digit"


@dataclass(frozen=True)
class Flag(Node):
    def form(self) -> str:
        return "true or false"

    def read(self, value: Any, key: str, reader: Reader) -> bool:
        if not isinstance(value, bool):
            raise self.refuse(value, key, reader)
        return value


@dataclass(frozen=True)
class Choice(Node):
    """One of a few words."""

    options: tuple[str, ...]

    def form(self) -> str:
        return f"one of {', '.join(self.options)}" if len(self.options) > 1 else repr(self.options[0])

    def read(self, value: Any, key: str, reader: Reader) -> str:
        if not isinstance(value, str) or value not in self.options:
            raise self.refuse(value, key, reader)
        return value


@dataclass(frozen=True)
class Serial(Node):
    """A device's serial as text: a string, or a number YAML read from digits (RealSense serials
    are digits), checked before it is converted."""

    def form(self) -> str:
        return "the device's serial (text or digits)"

    def read(self, value: Any, key: str, reader: Reader) -> str:
        if isinstance(value, str) and len(value) <= MAX_STRING:
            return value
        if isinstance(value, int) and not isinstance(value, bool) and 0 <= value and value.bit_length() <= 64:
            return str(value)
        raise self.refuse(value, key, reader)


_SCALARS = (str, int, float, bool, datetime.date, type(None))


@dataclass(frozen=True)
class Note(Node):
    """A remark for people (a phone model, when a table was measured): any scalar, kept as written."""

    def form(self) -> str:
        return "any text, number or date (a note, not read)"

    def read(self, value: Any, key: str, reader: Reader) -> Any:
        if not isinstance(value, _SCALARS):
            raise self.refuse(value, key, reader)
        return value


def _mapping(value: Any, key: str, reader: Reader) -> dict[Any, Any]:
    if not isinstance(value, dict):
        raise reader.fail(key, f"expected a mapping, got {type(value).__name__} {show(value)}")
    return value


@dataclass(frozen=True)
class Section(Node):
    """A mapping of named fields, read as a dict of every field (absent ones at their default).
    optional: the whole section may be left out or null (every field at its default)."""

    fields: Mapping[str, Node]
    optional: bool = False

    @property
    def required(self) -> bool:
        return not self.optional

    def form(self) -> str:
        return "a section of the keys below"

    def missing(self) -> str:
        return "missing section"

    def absent(self, key: str, reader: Reader) -> dict[str, Any]:
        return self.read({}, key, reader)

    def read(self, value: Any, key: str, reader: Reader) -> dict[str, Any]:
        raw = _mapping({} if value is None and self.optional else value, key, reader)
        unknown = sorted((k for k in raw if k not in self.fields), key=key_name)
        if unknown:
            raise reader.fail(child(key, key_name(unknown[0])),
                              f"unknown key; allowed keys: {', '.join(sorted(self.fields))}")
        out: dict[str, Any] = {}
        for name, node in self.fields.items():
            full = child(key, name)
            if name in raw:
                out[name] = node.read(raw[name], full, reader)
            elif node.required:
                raise reader.fail(full, node.missing())
            else:
                out[name] = node.absent(full, reader)
        return out


@dataclass(frozen=True)
class ListOf(Node):
    """A list of min_len to max_len items of one form, read as a list."""

    item: Node
    min_len: int = 0
    max_len: int = 1024

    def form(self) -> str:
        what = "sections of the keys below" if isinstance(self.item, Section) else f"entries, each {self.item.form()}"
        return f"a list of {self.min_len} to {self.max_len} {what}"

    def read(self, value: Any, key: str, reader: Reader) -> list[Any]:
        if not isinstance(value, list):
            raise reader.fail(key, f"expected a list, got {type(value).__name__} {show(value)}")
        if not self.min_len <= len(value) <= self.max_len:
            raise reader.fail(key, f"has {len(value)} entries, allowed {self.min_len} to {self.max_len}")
        return [self.item.read(v, f"{key}[{i}]", reader) for i, v in enumerate(value)]


@dataclass(frozen=True)
class Tuple(Node):
    """A list of exactly len(items) values, the i-th of form items[i], read as a list."""

    items: tuple[Node, ...]

    @classmethod
    def of(cls, item: Node, n: int, **kw: Any) -> Tuple:
        """n values of one form (a 3-vector, an image size)."""
        return cls(items=(item,) * n, **kw)

    def form(self) -> str:
        n = len(self.items)
        if all(item == self.items[0] for item in self.items):
            return f"a list of {n} values, each {self.items[0].form()}"
        return f"a list of {n} values: " + ", then ".join(item.form() for item in self.items)

    def read(self, value: Any, key: str, reader: Reader) -> list[Any]:
        if not isinstance(value, list) or len(value) != len(self.items):
            raise self.refuse(value, key, reader)
        return [item.read(v, f"{key}[{i}]", reader) for i, (item, v) in enumerate(zip(self.items, value))]


@dataclass(frozen=True)
class MapOf(Node):
    """A mapping of keys of one form to values of one form (at most max_len), read as a dict."""

    keys: Node
    values: Node
    max_len: int = 1024

    def form(self) -> str:
        return f"a mapping of at most {self.max_len} keys, each {self.keys.form()}"

    def read(self, value: Any, key: str, reader: Reader) -> dict[Any, Any]:
        raw = _mapping(value, key, reader)
        if len(raw) > self.max_len:
            raise reader.fail(key, f"has {len(raw)} entries, allowed at most {self.max_len}")
        out = {}
        for k, v in raw.items():
            name = self.keys.read(k, child(key, key_name(k)), reader)
            out[name] = self.values.read(v, child(key, str(name)), reader)
        return out


@dataclass(frozen=True)
class Nullable(Node):
    """The inner form, or null (read as None)."""

    inner: Node

    def form(self) -> str:
        return f"{self.inner.form()}, or null"

    def missing(self) -> str:
        return f"{self.inner.missing()} (write null for none)"

    def read(self, value: Any, key: str, reader: Reader) -> Any:
        return None if value is None else self.inner.read(value, key, reader)


@dataclass(frozen=True)
class Kind:
    """One way of reaching a device, written ``{name: value}`` in the file, or ``name`` alone when
    bare (the rig file says the rest). value: the form of the value; doc: what it means."""

    value: Node
    bare: bool = False
    doc: str = ""


@dataclass(frozen=True)
class Kinds(Node):
    """One of several kinds (a phone over USB or TCP, a depth camera live or recorded), read as
    (kind name, value or None when written bare)."""

    kinds: Mapping[str, Kind]

    def form(self) -> str:
        bare = " or ".join(repr(name) for name, kind in self.kinds.items() if kind.bare)
        return f"{bare + ' or ' if bare else ''}a mapping with one of {', '.join(self.kinds)}"

    def read(self, value: Any, key: str, reader: Reader) -> tuple[str, Any]:
        if isinstance(value, str) and value in self.kinds and self.kinds[value].bare:
            return value, None
        if not isinstance(value, dict) or len(value) != 1 or next(iter(value)) not in self.kinds:
            raise self.refuse(value, key, reader)
        name, inner = next(iter(value.items()))
        return name, self.kinds[name].value.read(inner, f"{key}.{name}", reader)
