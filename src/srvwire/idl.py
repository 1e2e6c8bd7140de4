"""What interface files mean: types, fields, constants, messages, services and actions.

These are plain frozen dataclasses with no behaviour beyond naming. The parser builds them from
text; the models module builds pydantic classes from them; nothing here knows about either.

Conventions:

* A primitive type has ``package is None``. A nested type always has its package filled in: the
  parser resolves a same-package reference (``Point``) to the file's own package.
* ``array is ArrayKind.NONE`` for a scalar; ``size`` is the exact length of a fixed array or the
  upper bound of a bounded one, and ``None`` otherwise.
* Default and constant values are Python values: ``bool``, ``int``, ``float``, ``str``, or a tuple
  of those for arrays.
* A service's request and response, and an action's three parts, are :class:`MessageSpec` values
  named as ROS 2 names them: ``AddTwoInts_Request``, ``Fibonacci_Goal`` and so on.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TypeAlias

__all__ = [
    "ARRAY_PRIMITIVES_AS_BYTES",
    "FLOAT_TYPES",
    "INTEGER_RANGES",
    "PRIMITIVE_TYPES",
    "STRING_TYPES",
    "ActionSpec",
    "ArrayKind",
    "ConstantSpec",
    "FieldSpec",
    "InterfaceKind",
    "MessageSpec",
    "Scalar",
    "ServiceSpec",
    "TypeSpec",
    "Value",
]

Scalar: TypeAlias = bool | int | float | str
Value: TypeAlias = Scalar | tuple[Scalar, ...]

INTEGER_RANGES: dict[str, tuple[int, int]] = {
    "byte": (0, 255),
    "char": (0, 255),
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
FLOAT_TYPES = frozenset({"float32", "float64"})
STRING_TYPES = frozenset({"string", "wstring"})
PRIMITIVE_TYPES = frozenset({"bool", *INTEGER_RANGES, *FLOAT_TYPES, *STRING_TYPES})
# Arrays of these element types may also be written as base64 text.
ARRAY_PRIMITIVES_AS_BYTES = frozenset({"byte", "uint8"})


class ArrayKind(enum.Enum):
    """Whether a field is a scalar, or which of the three kinds of array it is."""

    NONE = "none"
    FIXED = "fixed"  # T[N]
    UNBOUNDED = "unbounded"  # T[]
    BOUNDED = "bounded"  # T[<=N]


class InterfaceKind(enum.Enum):
    """The three kinds of interface file."""

    MSG = "msg"
    SRV = "srv"
    ACTION = "action"


@dataclass(frozen=True, slots=True)
class TypeSpec:
    """The type of a field or constant, as written in an interface file."""

    name: str  # "int32", "string", "Point"
    package: str | None = None  # None for primitives; always set for nested types
    string_bound: int | None = None  # N of string<=N / wstring<=N
    array: ArrayKind = ArrayKind.NONE
    size: int | None = None  # N of T[N] and T[<=N]

    @property
    def is_primitive(self) -> bool:
        return self.package is None

    @property
    def is_array(self) -> bool:
        return self.array is not ArrayKind.NONE

    @property
    def element(self) -> TypeSpec:
        """The type of one element: this type with the array part removed."""
        return TypeSpec(self.name, self.package, self.string_bound)

    @property
    def qualified_name(self) -> str:
        """``pkg/msg/Name`` for a nested type, the primitive's name otherwise."""
        return self.name if self.package is None else f"{self.package}/msg/{self.name}"

    def __str__(self) -> str:
        text = self.name if self.package is None else f"{self.package}/{self.name}"
        if self.string_bound is not None:
            text += f"<={self.string_bound}"
        if self.array is ArrayKind.FIXED:
            text += f"[{self.size}]"
        elif self.array is ArrayKind.UNBOUNDED:
            text += "[]"
        elif self.array is ArrayKind.BOUNDED:
            text += f"[<={self.size}]"
        return text


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One field: its type, name, optional default, and the comment that documents it."""

    type: TypeSpec
    name: str
    default: Value | None = None
    doc: str = ""
    line: int = 0


@dataclass(frozen=True, slots=True)
class ConstantSpec:
    """One constant (``TYPE NAME=value``); its type is always a primitive scalar."""

    type: TypeSpec
    name: str
    value: Scalar
    doc: str = ""
    line: int = 0


@dataclass(frozen=True, slots=True)
class MessageSpec:
    """A message: a ``.msg`` file, or one part of a ``.srv`` or ``.action`` file."""

    package: str
    name: str
    fields: tuple[FieldSpec, ...] = ()
    constants: tuple[ConstantSpec, ...] = ()
    doc: str = ""
    path: str | None = None
    text: str = field(default="", repr=False, compare=False)  # a .msg file's text; "" for a part

    @property
    def type_name(self) -> str:
        return f"{self.package}/msg/{self.name}"


@dataclass(frozen=True, slots=True)
class ServiceSpec:
    """A service: a request message and a response message, and the file's text."""

    package: str
    name: str
    request: MessageSpec
    response: MessageSpec
    text: str = field(default="", repr=False)
    path: str | None = None

    @property
    def type_name(self) -> str:
        return f"{self.package}/srv/{self.name}"


@dataclass(frozen=True, slots=True)
class ActionSpec:
    """An action: goal, result and feedback messages, and the file's text."""

    package: str
    name: str
    goal: MessageSpec
    result: MessageSpec
    feedback: MessageSpec
    text: str = field(default="", repr=False)
    path: str | None = None

    @property
    def type_name(self) -> str:
        return f"{self.package}/action/{self.name}"
