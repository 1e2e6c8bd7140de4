"""The annotation of each ROS primitive type: what one value of it is to pydantic.

:mod:`srvwire.models` composes these into field annotations and re-exports them; generated
modules import them from there (``from srvwire.models import Int32``), so that is their public
home, and this module is where they are defined.

* **Strict.** Every alias carries ``Strict()``: no ``"5"`` for an int, no ``5.0`` or ``True``
  for an int, no ``1`` for a bool; an int is still accepted for a float.
* **Checked in Rust, but for a few.** Integer ranges are ``Field(ge=, le=)``. The only checks
  that call Python are here: the ``float32`` range, which must let ``inf`` and ``nan`` through
  (no ``ge``/``le`` pair can say that); a non-finite float spelled as text or ``null``, which
  only the input that is not a number pays for; and byte arrays (:data:`AcceptBase64`), once
  per field.
* **Non-finite floats are read in every spelling.** A float field takes a number, the tokens
  ``NaN``/``Infinity``/``-Infinity``, the strings ``"NaN"``/``"Infinity"``/``"-Infinity"`` and
  ``null`` (read as ``nan``), whichever way the peer writes them; how they are *written* is the
  serializer's choice (:data:`InfNan`, set per server and per client).
* **Byte arrays are** ``bytes``. ``byte``/``uint8`` arrays are ``bytes`` in Python and base64
  text (RFC 4648, standard alphabet) in JSON; base64 text, ``bytes`` and lists of integers are
  read.
"""

from __future__ import annotations

import base64
import binascii
import math
from typing import Annotated, Any, Literal, TypeAlias

from pydantic import Field, GetCoreSchemaHandler, GetJsonSchemaHandler, Strict
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema, PydanticCustomError, SchemaValidator, core_schema

__all__ = [
    "FLOAT32_BOUND",
    "FLOAT32_MAX",
    "INF_NAN_MODES",
    "PRIMITIVE_ALIASES",
    "PRIMITIVE_ANNOTATIONS",
    "AcceptBase64",
    "Bool",
    "Byte",
    "Char",
    "Float32",
    "Float64",
    "InfNan",
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
"""The largest finite ``float32``."""
FLOAT32_BOUND = 2.0**128 - 2.0**103
"""3.4028235677973366e38, halfway from :data:`FLOAT32_MAX` to ``2**128``: a finite value of a
smaller magnitude rounds to a finite ``float32`` (``3.4028235e38``, as most languages write the
largest one, rounds to it), and one at the bound or beyond rounds to infinity. A finite
``float32`` value must lie strictly within ``±FLOAT32_BOUND``."""


def _check_float32(value: float) -> float:
    # abs() of nan is nan, and nan >= x is False, so nan and the two infinities pass.
    if abs(value) >= FLOAT32_BOUND and value not in (float("inf"), float("-inf")):
        raise PydanticCustomError(
            "float32_range",
            "Input should be a float32: of a magnitude below {limit} (what rounds to a finite "
            "float32), or inf, or nan",
            {"limit": FLOAT32_BOUND},
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
        json_schema.update(exclusiveMinimum=-FLOAT32_BOUND, exclusiveMaximum=FLOAT32_BOUND)
        return json_schema

    def __repr__(self) -> str:
        return "Float32Range()"


InfNan: TypeAlias = Literal["strings", "null", "constants"]
"""How JSON output writes ``inf``, ``-inf`` and ``nan``: pydantic's ``ser_json_inf_nan``.

``"strings"``: ``"Infinity"``, ``"-Infinity"``, ``"NaN"`` (standard JSON, and read back as the
same floats); ``"null"``: ``null`` (standard JSON; which value it was is lost);
``"constants"``: the bare tokens ``Infinity``, ``-Infinity``, ``NaN``, as Python's :mod:`json`
writes them (not standard JSON: a browser's ``JSON.parse`` refuses the whole message).
"""

INF_NAN_MODES: tuple[InfNan, ...] = ("strings", "null", "constants")
"""The values of :data:`InfNan`; the first is the default of servers, clients and messages."""

_NON_FINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}


def _non_finite(value: str | None) -> float:
    return math.nan if value is None else _NON_FINITE[value]


class _NonFiniteInput:
    """Annotation marker for float types: also read a non-finite value written as text or null.

    A union of the number and one of the strings ``"NaN"``, ``"Infinity"``, ``"-Infinity"`` or
    ``null``, which become floats (``null`` is ``nan``). A value that is none of these is one
    ``float_type`` error, as before. Output and the JSON schema are the number's. The union is
    pydantic-core's "smart" one: a float, which only the number takes, is taken at its first
    exact match, with less work per element than trying the choices in order (a sixth less
    for a 100 000-value array, read from JSON or built in Python); at most one choice takes
    any value, so what is read and what is refused are the same either way.
    """

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        number = handler(source)
        spelled = core_schema.no_info_after_validator_function(
            _non_finite,
            core_schema.nullable_schema(core_schema.literal_schema(list(_NON_FINITE))),
        )
        return core_schema.union_schema(
            [number, spelled],
            custom_error_type="float_type",
            serialization=core_schema.simple_ser_schema("float"),
        )

    def __get_pydantic_json_schema__(
        self, schema: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        return handler(core_schema.float_schema())

    def __repr__(self) -> str:
        return "NonFiniteInput()"


# Lists of integers are checked in Rust, element by element, so an error points at the element;
# as every array, it stops at the first invalid one (fail_fast).
_OCTETS = SchemaValidator(
    core_schema.list_schema(core_schema.int_schema(strict=True, ge=0, le=255), fail_fast=True)
)


_URL_SAFE = str.maketrans("-_", "+/")


def _bytes_input(value: Any) -> bytes:
    if type(value) is bytes:
        return value
    if isinstance(value, str):
        try:
            # The URL-safe alphabet too: pydantic's own base64 (ser_json_bytes) writes it.
            return base64.b64decode(value.translate(_URL_SAFE), validate=True)
        except (binascii.Error, ValueError) as exc:
            raise PydanticCustomError(
                "base64",
                "Input should be base64 text, bytes or a list of integers: {reason}",
                {"reason": str(exc)},
            ) from None
    if isinstance(value, bytes | bytearray | memoryview):
        return bytes(value)
    if isinstance(value, list | tuple):
        return bytes(_OCTETS.validate_python(value))  # its errors point into the list
    raise PydanticCustomError(
        "bytes_type", "Input should be base64 text, bytes or a list of integers"
    )


def _base64_text(value: bytes) -> str:
    return base64.b64encode(value).decode("ascii")


class _Base64Input:
    """Annotation marker for ``byte``/``uint8`` arrays: ``Annotated[bytes, ..., AcceptBase64]``.

    Reads base64 text (padded; the standard alphabet or the URL-safe one), ``bytes``,
    ``bytearray``, ``memoryview`` and lists of integers 0 … 255, into ``bytes``, before the
    length bounds of the ``bytes`` schema (``Field(min_length=, max_length=)``, counted in
    bytes) are checked. JSON output is base64 text, as rosbridge writes byte arrays; Python
    output (``model_dump()``) is the ``bytes``.
    """

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        return core_schema.no_info_before_validator_function(
            _bytes_input,
            handler(source),
            serialization=core_schema.plain_serializer_function_ser_schema(
                _base64_text, when_used="json"
            ),
        )

    def __get_pydantic_json_schema__(
        self, schema: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        text: JsonSchemaValue = {"type": "string", "contentEncoding": "base64"}
        if handler.mode == "serialization":
            return text
        inner = schema.get("schema", schema)
        array: JsonSchemaValue = {
            "type": "array",
            "items": {"type": "integer", "minimum": 0, "maximum": 255},
        }
        for bound, keyword in (("min_length", "minItems"), ("max_length", "maxItems")):
            if bound in inner:
                array[keyword] = inner[bound]
        return {"anyOf": [array, text]}

    def __repr__(self) -> str:
        return "AcceptBase64"


AcceptBase64 = _Base64Input()
"""Put in ``Annotated[bytes, ..., AcceptBase64]``: base64 in JSON; bytes or integers read too."""


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
Float32: TypeAlias = Annotated[float, Strict(), _NonFiniteInput(), _Float32Range()]
Float64: TypeAlias = Annotated[float, Strict(), _NonFiniteInput()]
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
