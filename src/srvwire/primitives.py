"""The annotation of each ROS primitive type: what one value of it is to pydantic.

:mod:`srvwire.models` composes these into field annotations and re-exports them; generated
modules import them from there (``from srvwire.models import Int32``), so that is their public
home, and this module is where they are defined.

* **Strict.** Every alias carries ``Strict()``: no ``"5"`` for an int, no ``5.0`` or ``True``
  for an int, no ``1`` for a bool; an int is still accepted for a float.
* **Checked in Rust, but for two.** Integer ranges are ``Field(ge=, le=)``. The only checks that
  call Python are here: the ``float32`` range, which must let ``inf`` and ``nan`` through (no
  ``ge``/``le`` pair can say that), and the base64 input of byte arrays (:data:`AcceptBase64`).
"""

from __future__ import annotations

import base64
import binascii
from typing import Annotated, Any, TypeAlias

from pydantic import Field, GetCoreSchemaHandler, GetJsonSchemaHandler, Strict
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema, PydanticCustomError, core_schema

__all__ = [
    "FLOAT32_MAX",
    "PRIMITIVE_ALIASES",
    "PRIMITIVE_ANNOTATIONS",
    "AcceptBase64",
    "Bool",
    "Byte",
    "Char",
    "Float32",
    "Float64",
    "Int8",
    "Int16",
    "Int32",
    "Int64",
    "String",
    "UInt8",
    "UInt16",
    "UInt32",
    "UInt64",
    "WString",
]

FLOAT32_MAX = 3.4028234663852886e38
"""The largest finite ``float32``; a finite ``float32`` value must lie within ``±FLOAT32_MAX``."""


def _check_float32(value: float) -> float:
    # abs() of nan is nan, and nan > x is False, so nan and the two infinities pass.
    if abs(value) > FLOAT32_MAX and value not in (float("inf"), float("-inf")):
        raise PydanticCustomError(
            "float32_range",
            "Input should be a float32: within ±{limit}, or inf, or nan",
            {"limit": FLOAT32_MAX},
        )
    return value


class _Float32Range:
    """Annotation marker: a finite value must fit a float32; ``inf`` and ``nan`` are allowed."""

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        return core_schema.no_info_after_validator_function(_check_float32, handler(source))

    def __get_pydantic_json_schema__(
        self, schema: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        json_schema = handler(schema)
        json_schema.update(minimum=-FLOAT32_MAX, maximum=FLOAT32_MAX)
        return json_schema

    def __repr__(self) -> str:
        return "Float32Range()"


def _bytes_input(value: Any) -> Any:
    if isinstance(value, str):
        try:
            return list(base64.b64decode(value, validate=True))
        except (binascii.Error, ValueError) as exc:
            raise PydanticCustomError(
                "base64",
                "Input should be a list of integers or base64 text: {reason}",
                {"reason": str(exc)},
            ) from None
    if isinstance(value, bytes | bytearray | memoryview):
        return list(value)
    return value


class _Base64Input:
    """Annotation marker for ``byte``/``uint8`` arrays: also accept base64 text and ``bytes``.

    The decoded bytes become a list of integers before the list's own checks (element range,
    length) run, so a fixed or bounded array keeps its bounds. Output is always the list.
    """

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        return core_schema.no_info_before_validator_function(_bytes_input, handler(source))

    def __get_pydantic_json_schema__(
        self, schema: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        json_schema = handler(schema)
        if handler.mode == "serialization":
            return json_schema
        return {"anyOf": [json_schema, {"type": "string", "contentEncoding": "base64"}]}

    def __repr__(self) -> str:
        return "AcceptBase64"


AcceptBase64 = _Base64Input()
"""Put in ``Annotated[list[UInt8], ..., AcceptBase64]`` to accept base64 text for the list."""


# Written out (not computed from INTEGER_RANGES) so that type checkers see ``int``; a test checks
# that each range matches the table in srvwire.idl.
Bool: TypeAlias = Annotated[bool, Strict()]
Byte: TypeAlias = Annotated[int, Strict(), Field(ge=0, le=255)]
Char: TypeAlias = Annotated[int, Strict(), Field(ge=0, le=255)]
Int8: TypeAlias = Annotated[int, Strict(), Field(ge=-128, le=127)]
UInt8: TypeAlias = Annotated[int, Strict(), Field(ge=0, le=255)]
Int16: TypeAlias = Annotated[int, Strict(), Field(ge=-32768, le=32767)]
UInt16: TypeAlias = Annotated[int, Strict(), Field(ge=0, le=65535)]
Int32: TypeAlias = Annotated[int, Strict(), Field(ge=-2147483648, le=2147483647)]
UInt32: TypeAlias = Annotated[int, Strict(), Field(ge=0, le=4294967295)]
Int64: TypeAlias = Annotated[int, Strict(), Field(ge=-9223372036854775808, le=9223372036854775807)]
UInt64: TypeAlias = Annotated[int, Strict(), Field(ge=0, le=18446744073709551615)]
Float32: TypeAlias = Annotated[float, Strict(), _Float32Range()]
Float64: TypeAlias = Annotated[float, Strict()]
String: TypeAlias = Annotated[str, Strict()]
WString: TypeAlias = Annotated[str, Strict()]

PRIMITIVE_ALIASES: dict[str, str] = {
    "bool": "Bool",
    "byte": "Byte",
    "char": "Char",
    "int8": "Int8",
    "uint8": "UInt8",
    "int16": "Int16",
    "uint16": "UInt16",
    "int32": "Int32",
    "uint32": "UInt32",
    "int64": "Int64",
    "uint64": "UInt64",
    "float32": "Float32",
    "float64": "Float64",
    "string": "String",
    "wstring": "WString",
}
"""Each ROS primitive type and the name of its annotated alias in this module."""

PRIMITIVE_ANNOTATIONS: dict[str, Any] = {
    ros: globals()[alias] for ros, alias in PRIMITIVE_ALIASES.items()
}
"""Each ROS primitive type and its annotated alias itself."""
