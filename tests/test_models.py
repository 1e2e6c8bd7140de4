"""Spec -> pydantic classes: every ROS type's mapping, defaults, names, errors (srvwire.models)."""

from __future__ import annotations

import base64
import json
import math
import struct
import typing
import warnings
from typing import Any

import pydantic
import pydantic_core
import pytest
from hypothesis import given, settings, strategies as st

from srvwire import scanner
from srvwire.errors import InterfaceError
from srvwire.idl import (
    INTEGER_RANGES,
    ActionSpec,
    ArrayKind,
    ConstantSpec,
    FieldSpec,
    MessageSpec,
    ServiceSpec,
    TypeSpec,
)
from srvwire.models import (
    FLOAT32_BOUND,
    FLOAT32_MAX,
    MAX_LISTED_ERRORS,
    PRIMITIVE_ALIASES,
    Action,
    InfNan,
    Message,
    Service,
    ServiceRequest,
    TypedService,
    build_action,
    build_message,
    build_service,
    error_data,
    json_writer,
    python_name,
    summarize_errors,
    unencodable_strings,
    validation_errors,
)
from srvwire.parser import parse_file
from support import ros_test_interfaces

# --- helpers -------------------------------------------------------------------------------------


def t(
    name: str,
    *,
    package: str | None = None,
    bound: int | None = None,
    array: ArrayKind = ArrayKind.NONE,
    size: int | None = None,
) -> TypeSpec:
    return TypeSpec(name, package, bound, array, size)


def fixed(name: str, size: int, **kwargs: Any) -> TypeSpec:
    return t(name, array=ArrayKind.FIXED, size=size, **kwargs)


def bounded(name: str, size: int, **kwargs: Any) -> TypeSpec:
    return t(name, array=ArrayKind.BOUNDED, size=size, **kwargs)


def unbounded(name: str, **kwargs: Any) -> TypeSpec:
    return t(name, array=ArrayKind.UNBOUNDED, **kwargs)


def msg(name: str, *fields: FieldSpec, package: str = "pkg", **kwargs: Any) -> MessageSpec:
    return MessageSpec(package, name, fields, **kwargs)


def one(type_: TypeSpec, default: Any = None) -> Any:
    """A message with the single field ``v`` (typed ``Any``: its attributes are dynamic)."""
    return build_message(msg("One", FieldSpec(type_, "v", default)))


def errors_of(cls: type[Message], data: Any, *, as_json: bool = False) -> list[dict[str, str]]:
    with pytest.raises(pydantic.ValidationError) as info:
        if as_json:
            cls.model_validate_json(data)
        else:
            cls.model_validate(data)
    return validation_errors(info.value)


def error_types(cls: type[Message], data: Any, *, as_json: bool = False) -> list[str]:
    return [e["type"] for e in errors_of(cls, data, as_json=as_json)]


POINT = msg("Point", FieldSpec(t("float64"), "x"), FieldSpec(t("float64"), "y"), package="geo")
POSE = msg(
    "Pose",
    FieldSpec(t("Point", package="geo"), "position"),
    FieldSpec(unbounded("Point", package="geo"), "points"),
    package="geo",
)


def geo_resolver() -> Any:
    built: dict[str, type[Message]] = {}

    def resolve(type_: TypeSpec) -> type[Message]:
        assert type_.package == "geo"
        assert not type_.is_array
        if type_.name not in built:
            spec = {"Point": POINT, "Pose": POSE}[type_.name]
            built[type_.name] = build_message(spec, resolve)
        return built[type_.name]

    return resolve


# --- integers ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(INTEGER_RANGES))
def test_integer_bounds_are_inclusive(name: str) -> None:
    low, high = INTEGER_RANGES[name]
    cls = one(t(name))
    assert cls(v=low).v == low
    assert cls(v=high).v == high
    assert error_types(cls, {"v": low - 1}) == ["greater_than_equal"]
    assert error_types(cls, {"v": high + 1}) == ["less_than_equal"]


@pytest.mark.parametrize("name", sorted(INTEGER_RANGES))
@pytest.mark.parametrize("bad", [True, False, 1.0, 1.5, "1", None, [1]])
def test_integers_are_strict(name: str, bad: Any) -> None:
    assert error_types(one(t(name)), {"v": bad}) == ["int_type"]


@pytest.mark.parametrize("text", ['{"v": 1.0}', '{"v": "1"}', '{"v": true}', '{"v": null}'])
def test_integers_are_strict_in_json(text: str) -> None:
    assert error_types(one(t("int32")), text, as_json=True) == ["int_type"]


@pytest.mark.parametrize("name", sorted(INTEGER_RANGES))
def test_integer_json_schema_carries_the_range(name: str) -> None:
    low, high = INTEGER_RANGES[name]
    schema = one(t(name)).model_json_schema()["properties"]["v"]
    assert (schema["type"], schema["minimum"], schema["maximum"]) == ("integer", low, high)


@pytest.mark.parametrize("name", ["int64", "uint64"])
def test_64_bit_integers_are_exact_in_json(name: str) -> None:
    low, high = INTEGER_RANGES[name]
    cls = one(fixed(name, 2))
    text = cls(v=[low, high]).model_dump_json()
    assert text == f'{{"v":[{low},{high}]}}'
    assert json.loads(text)["v"] == [low, high]
    assert cls.model_validate_json(text).v == [low, high]


def test_assignment_is_validated() -> None:
    m = one(t("int8"))()
    m.v = 127
    with pytest.raises(pydantic.ValidationError):
        m.v = 128
    assert m.v == 127


# --- floats --------------------------------------------------------------------------------------


def test_float32_range_is_what_rounds_to_a_finite_float32() -> None:
    cls = one(t("float32"))
    assert cls(v=FLOAT32_MAX).v == FLOAT32_MAX
    assert cls(v=-FLOAT32_MAX).v == -FLOAT32_MAX
    # The bound is halfway from the largest float32 to 2**128: below it a value rounds to the
    # largest float32 (3.4028235e38, as most languages write it, does), from it on to infinity.
    assert struct.unpack("f", struct.pack("f", 3.4028235e38))[0] == FLOAT32_MAX
    below = math.nextafter(FLOAT32_BOUND, 0)
    assert struct.unpack("f", struct.pack("f", below))[0] == FLOAT32_MAX
    assert struct.unpack("f", struct.pack("f", FLOAT32_BOUND))[0] == math.inf
    # The scanner checks constants and defaults against its own copy (both are layer 1, and
    # neither may import the other): the two must be the same bound.
    assert scanner.FLOAT32_BOUND == FLOAT32_BOUND
    for value in (3.4028235e38, 3.40282347e38, below):
        assert cls(v=value).v == value
        assert cls(v=-value).v == -value
    assert error_types(cls, {"v": FLOAT32_BOUND}) == ["float32_range"]
    assert error_types(cls, {"v": -FLOAT32_BOUND}) == ["float32_range"]
    assert error_types(cls, {"v": 1e39}) == ["float32_range"]
    schema = cls.model_json_schema()["properties"]["v"]
    assert (schema["exclusiveMinimum"], schema["exclusiveMaximum"]) == (
        -FLOAT32_BOUND,
        FLOAT32_BOUND,
    )


@pytest.mark.parametrize("name", ["float32", "float64"])
def test_floats_allow_inf_and_nan_and_write_them_as_strings(name: str) -> None:
    cls = one(fixed(name, 3))
    m = cls(v=[math.inf, -math.inf, math.nan])
    text = m.model_dump_json()
    assert text == '{"v":["Infinity","-Infinity","NaN"]}'
    back = cls.model_validate_json(text).v
    assert back[:2] == [math.inf, -math.inf]
    assert math.isnan(back[2])
    json.loads(text, parse_constant=pytest.fail)  # standard JSON: no bare NaN token


@pytest.mark.parametrize("name", ["float32", "float64"])
@pytest.mark.parametrize(
    ("mode", "written"),
    [
        ("strings", '{"v":["Infinity","-Infinity","NaN",1.5]}'),
        ("null", '{"v":[null,null,null,1.5]}'),
        ("constants", '{"v":[Infinity,-Infinity,NaN,1.5]}'),
    ],
)
def test_a_json_writer_writes_non_finite_floats_in_its_mode(
    name: str, mode: InfNan, written: str
) -> None:
    cls = one(fixed(name, 4))
    m = cls(v=[math.inf, -math.inf, math.nan, 1.5])
    assert json_writer(cls, mode)(m).decode() == written
    assert json_writer(cls, mode, strict=True)(m).decode() == written
    back = cls.model_validate_json(written).v  # every mode's output is read back
    assert math.isnan(back[2])
    assert back[3] == 1.5
    if mode == "null":  # which value it was is lost
        assert math.isnan(back[0]) and math.isnan(back[1])
    else:
        assert back[:2] == [math.inf, -math.inf]


def test_a_json_writer_reaches_nested_messages_and_leaves_the_class_alone() -> None:
    point = build_message(msg("Point", FieldSpec(t("float64"), "x")))
    path = build_message(
        msg(
            "Path",
            FieldSpec(t("Point", package="geo"), "first"),
            FieldSpec(unbounded("Point", package="geo"), "rest"),
        ),
        lambda type_: point,
    )
    value = path(first={"x": math.nan}, rest=[{"x": math.inf}])
    assert json_writer(path, "null")(value) == b'{"first":{"x":null},"rest":[{"x":null}]}'
    assert json_writer(path, "constants")(value) == b'{"first":{"x":NaN},"rest":[{"x":Infinity}]}'
    assert value.model_dump_json() == '{"first":{"x":"NaN"},"rest":[{"x":"Infinity"}]}'
    assert point(x=math.inf).model_dump_json() == '{"x":"Infinity"}'
    with pytest.raises(ValueError, match="inf_nan must be one of strings, null, constants"):
        json_writer(path, "none")  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["float32", "float64"])
def test_floats_read_every_spelling_of_non_finite_values(name: str) -> None:
    cls = one(unbounded(name))
    spelled = '{"v": ["NaN", "Infinity", "-Infinity", null, NaN, Infinity, -Infinity, 2]}'
    for value in (cls.model_validate_json(spelled), cls.model_validate(json.loads(spelled))):
        v = value.v
        assert [v[1], v[2], v[5], v[6], v[7]] == [math.inf, -math.inf, math.inf, -math.inf, 2.0]
        assert all(math.isnan(v[i]) for i in (0, 3, 4))
    for bad in ("nan", "inf", "Inf", "+Infinity", "1.5", ""):
        assert errors_of(cls, {"v": [bad]}) == [
            {"path": "v[0]", "message": "Input should be a valid number", "type": "float_type"}
        ]


@pytest.mark.parametrize("name", ["float32", "float64"])
def test_floats_accept_ints_as_floats(name: str) -> None:
    cls = one(t(name))
    value = cls(v=3).v
    assert value == 3.0
    assert type(value) is float
    assert type(cls.model_validate_json('{"v": 3}').v) is float
    assert cls(v=3).model_dump_json() == '{"v":3.0}'


@pytest.mark.parametrize("name", ["float32", "float64"])
@pytest.mark.parametrize("bad", [True, "1.5", "nan", [1.0], {}])
def test_floats_are_strict(name: str, bad: Any) -> None:
    assert error_types(one(t(name)), {"v": bad}) == ["float_type"]


def test_float64_takes_any_double() -> None:
    cls = one(t("float64"))
    assert cls(v=1.7976931348623157e308).v == 1.7976931348623157e308
    assert cls(v=2**64).v == float(2**64)
    assert cls(v=5e-324).v == 5e-324


# --- bool, strings -------------------------------------------------------------------------------


def test_bool_is_strict() -> None:
    cls = one(t("bool"))
    assert cls(v=True).v is True
    assert cls.model_validate_json('{"v": false}').v is False
    for bad in (1, 0, "true", None):
        assert error_types(cls, {"v": bad}) == ["bool_type"]


@pytest.mark.parametrize("name", ["string", "wstring"])
def test_strings_are_strict(name: str) -> None:
    cls = one(t(name))
    assert cls(v="hi").v == "hi"
    for bad in (5, b"hi", None, ["a"]):
        assert error_types(cls, {"v": bad}) == ["string_type"]


@pytest.mark.parametrize("name", ["string", "wstring"])
def test_bounded_strings_count_characters(name: str) -> None:
    cls = one(t(name, bound=3))
    assert cls(v="abc").v == "abc"
    assert cls(v="ハロー").v == "ハロー"  # 3 characters, 9 UTF-8 bytes
    assert error_types(cls, {"v": "abcd"}) == ["string_too_long"]
    assert cls.model_json_schema()["properties"]["v"]["maxLength"] == 3


def test_bounded_strings_in_a_bounded_array() -> None:
    cls = one(bounded("string", 2, bound=3))
    assert cls(v=["abc", ""]).v == ["abc", ""]
    assert [e["path"] for e in errors_of(cls, {"v": ["abc", "abcd"]})] == ["v[1]"]
    assert error_types(cls, {"v": ["a", "b", "c"]}) == ["too_long"]
    schema = cls.model_json_schema()["properties"]["v"]
    assert (schema["maxItems"], schema["items"]["maxLength"]) == (2, 3)


# --- arrays --------------------------------------------------------------------------------------


def test_fixed_arrays_take_exactly_n_elements() -> None:
    cls = one(fixed("int32", 3))
    assert cls(v=[1, 2, 3]).v == [1, 2, 3]
    assert error_types(cls, {"v": [1, 2]}) == ["too_short"]
    assert error_types(cls, {"v": [1, 2, 3, 4]}) == ["too_long"]
    schema = cls.model_json_schema()["properties"]["v"]
    assert (schema["minItems"], schema["maxItems"]) == (3, 3)


def test_bounded_arrays_take_at_most_n_elements() -> None:
    cls = one(bounded("float64", 2))
    assert cls(v=[]).v == []
    assert cls(v=[1.0, 2.0]).v == [1.0, 2.0]
    assert error_types(cls, {"v": [1.0, 2.0, 3.0]}) == ["too_long"]
    schema = cls.model_json_schema()["properties"]["v"]
    assert schema["maxItems"] == 2
    assert "minItems" not in schema


def test_unbounded_arrays_take_any_length_and_tuples() -> None:
    cls = one(unbounded("int16"))
    assert cls(v=list(range(10_000))).v == list(range(10_000))
    assert cls(v=(1, 2)).v == [1, 2]
    assert [e["path"] for e in errors_of(cls, {"v": [1, 2, 3, 40_000]})] == ["v[3]"]
    assert error_types(cls, {"v": "abc"}) == ["list_type"]


# --- byte arrays and base64 ------------------------------------------------------------------


@pytest.mark.parametrize("name", ["byte", "uint8"])
def test_byte_arrays_are_bytes_written_as_base64(name: str) -> None:
    cls = one(unbounded(name))
    assert cls(v="AQID/w==").v == b"\x01\x02\x03\xff"
    assert cls.model_validate_json('{"v": "AQID/w=="}').v == b"\x01\x02\x03\xff"
    assert cls.model_validate_json('{"v": [1, 2, 3, 255]}').v == b"\x01\x02\x03\xff"
    assert cls(v=[0, 255]).v == b"\x00\xff"
    assert cls(v=(0, 255)).v == b"\x00\xff"
    assert cls(v=bytearray(b"ab")).v == b"ab"
    assert cls(v=memoryview(b"ab")).v == b"ab"
    assert cls(v="").v == b""
    assert cls().v == b""
    assert cls(v="-_8=").v == b"\xfb\xff"  # the URL-safe alphabet, which pydantic writes
    assert cls(v=[251, 255]).model_dump_json() == '{"v":"+/8="}'  # the standard alphabet
    assert cls(v=b"ab").model_dump() == {"v": b"ab"}


def test_a_list_for_a_byte_array_is_checked_element_by_element() -> None:
    cls = one(unbounded("uint8"))
    # Up to the first invalid element: as every array, it stops there.
    assert errors_of(cls, {"v": [1, 256, True, "a"]}) == [
        {
            "path": "v[1]",
            "message": "Input should be less than or equal to 255",
            "type": "less_than_equal",
        },
    ]
    assert errors_of(cls, {"v": [1, 2, True]}) == [
        {"path": "v[2]", "message": "Input should be a valid integer", "type": "int_type"},
    ]
    assert errors_of(cls, {"v": 5}) == [
        {
            "path": "v",
            "message": "Input should be base64 text, bytes or a list of integers",
            "type": "bytes_type",
        }
    ]


@pytest.mark.parametrize("bad", ["AQI", "AQ!D", "AQ ID", "é"])
def test_invalid_base64_is_a_validation_error(bad: str) -> None:
    errors = errors_of(one(unbounded("uint8")), {"v": bad})
    assert [(e["path"], e["type"]) for e in errors] == [("v", "base64")]
    assert errors[0]["message"].startswith("Input should be base64 text, bytes or a list of ")


def test_base64_obeys_the_array_bounds() -> None:
    exact = one(fixed("uint8", 3))
    assert exact(v=base64.b64encode(b"abc").decode()).v == b"abc"
    assert error_types(exact, {"v": base64.b64encode(b"ab").decode()}) == ["bytes_too_short"]
    assert error_types(exact, {"v": base64.b64encode(b"abcd").decode()}) == ["bytes_too_long"]
    assert error_types(exact, {"v": [1, 2]}) == ["bytes_too_short"]
    assert errors_of(one(bounded("byte", 2)), {"v": "AQID"}) == [
        {"path": "v", "message": "Data should have at most 2 bytes", "type": "bytes_too_long"}
    ]
    assert exact().v == b"\x00\x00\x00"


def test_base64_is_only_for_byte_arrays() -> None:
    assert error_types(one(unbounded("int8")), {"v": "AQID"}) == ["list_type"]
    assert error_types(one(unbounded("char")), {"v": "AQID"}) == ["list_type"]
    assert error_types(one(t("uint8")), {"v": "AQ=="}) == ["int_type"]


@given(st.binary(max_size=64))
def test_base64_round_trip_is_exact(data: bytes) -> None:
    cls = one(unbounded("byte"))
    m = cls.model_validate_json(json.dumps({"v": base64.b64encode(data).decode()}))
    assert m.v == data
    assert cls.model_validate_json(m.model_dump_json()) == m


def test_byte_array_schema_offers_base64_only_for_input() -> None:
    cls = one(bounded("uint8", 4))
    field = cls.model_json_schema()["properties"]["v"]
    array, text = field["anyOf"]
    assert array == {
        "type": "array",
        "items": {"type": "integer", "minimum": 0, "maximum": 255},
        "maxItems": 4,
    }
    assert text == {"type": "string", "contentEncoding": "base64"}
    written = cls.model_json_schema(mode="serialization")["properties"]["v"]
    assert written == {"type": "string", "contentEncoding": "base64", "default": "", "title": "V"}


# --- defaults ------------------------------------------------------------------------------------

ZEROS = msg(
    "Zeros",
    *(FieldSpec(t(name), f"{name}_value") for name in sorted(PRIMITIVE_ALIASES)),
    FieldSpec(fixed("int32", 3), "fixed_ints"),
    FieldSpec(fixed("string", 2), "fixed_strings"),
    FieldSpec(bounded("float32", 3), "bounded_floats"),
    FieldSpec(unbounded("bool"), "bools"),
    FieldSpec(t("Point", package="geo"), "point"),
    FieldSpec(fixed("Point", 2, package="geo"), "fixed_points"),
    FieldSpec(unbounded("Point", package="geo"), "points"),
)


def test_every_field_has_the_ros_zero_value_by_default() -> None:
    m: Any = build_message(ZEROS, geo_resolver())()
    assert m.model_dump() == {
        "bool_value": False,
        "byte_value": 0,
        "char_value": 0,
        "float32_value": 0.0,
        "float64_value": 0.0,
        "int16_value": 0,
        "int32_value": 0,
        "int64_value": 0,
        "int8_value": 0,
        "string_value": "",
        "uint16_value": 0,
        "uint32_value": 0,
        "uint64_value": 0,
        "uint8_value": 0,
        "wstring_value": "",
        "fixed_ints": [0, 0, 0],
        "fixed_strings": ["", ""],
        "bounded_floats": [],
        "bools": [],
        "point": {"x": 0.0, "y": 0.0},
        "fixed_points": [{"x": 0.0, "y": 0.0}, {"x": 0.0, "y": 0.0}],
        "points": [],
    }
    assert type(m.float64_value) is float


def test_mutable_defaults_are_never_shared() -> None:
    cls: Any = build_message(ZEROS, geo_resolver())
    first, second = cls(), cls()
    first.fixed_ints[0] = 7
    first.bools.append(True)
    first.point.x = 1.5
    first.fixed_points[1].y = 2.5
    assert second.fixed_ints == [0, 0, 0]
    assert second.bools == []
    assert second.point.x == 0.0
    assert second.fixed_points[1].y == 0.0
    assert cls().model_dump() == second.model_dump()


def test_written_defaults_become_field_defaults() -> None:
    cls: Any = build_message(
        msg(
            "Defaults",
            FieldSpec(t("int8"), "i", -50),
            FieldSpec(t("float32"), "f", 1),  # an int written for a float becomes a float
            FieldSpec(t("string", bound=5), "s", "hi"),
            FieldSpec(fixed("uint64", 2), "u", (0, 2**64 - 1)),
            FieldSpec(bounded("float64", 3), "b", (1.5,)),
            FieldSpec(t("bool"), "flag", True),
        )
    )
    m = cls()
    assert m.model_dump() == {
        "i": -50,
        "f": 1.0,
        "s": "hi",
        "u": [0, 2**64 - 1],
        "b": [1.5],
        "flag": True,
    }
    assert type(m.f) is float
    m.u[0] = 5
    assert cls().u == [0, 2**64 - 1]
    assert cls.model_json_schema()["properties"]["i"]["default"] == -50


@pytest.mark.parametrize(
    ("field", "problem"),
    [
        (FieldSpec(t("int8"), "x", 300), "x: Input should be less than or equal to 127"),
        (FieldSpec(t("string", bound=2), "x", "abc"), "x: String should have at most 2 char"),
        (FieldSpec(fixed("int32", 2), "x", (1, 2, 3)), "x: List should have at most 2 items"),
    ],
)
def test_invalid_written_defaults_are_refused(field: FieldSpec, problem: str) -> None:
    with pytest.raises(InterfaceError, match=r"^pkg/msg/Bad: invalid default value") as info:
        build_message(msg("Bad", field))
    assert problem in str(info.value)


# --- constants -----------------------------------------------------------------------------------

CONSTANTS = msg(
    "Limits",
    FieldSpec(t("int32"), "value"),
    constants=(
        ConstantSpec(t("int32"), "MAX", 10),
        ConstantSpec(t("float64"), "RATIO", 2),
        ConstantSpec(t("string"), "NAME", "limits"),
        ConstantSpec(t("bool"), "ON", True),
        ConstantSpec(t("uint64"), "BIG", 2**64 - 1),
    ),
)


def test_constants_are_class_attributes() -> None:
    cls: Any = build_message(CONSTANTS)
    assert (cls.MAX, cls.RATIO, cls.NAME, cls.ON, cls.BIG) == (10, 2.0, "limits", True, 2**64 - 1)
    assert type(cls.RATIO) is float
    assert cls().MAX == 10
    assert cls.spec.constants == CONSTANTS.constants
    assert list(cls.model_fields) == ["value"]
    assert cls().model_dump() == {"value": 0}


def test_constants_cannot_be_set_on_an_instance() -> None:
    m: Any = build_message(CONSTANTS)()
    with pytest.raises(AttributeError, match="ClassVar"):
        m.MAX = 3


# --- names ---------------------------------------------------------------------------------------

CLASHING = [
    "from",
    "class",
    "import",
    "lambda",
    "copy",
    "json",
    "dict",
    "schema",
    "validate",
    "construct",
    "model_config",
    "model_fields",
    "model_dump",
    "type_name",
    "spec",
    "register",  # the class's metaclass (an ABCMeta) has these two
    "mro",
]


def test_python_name_adds_an_underscore_only_where_needed() -> None:
    assert [python_name(n) for n in CLASHING] == [f"{n}_" for n in CLASHING]
    for name in ["fields", "type", "id", "list", "model_name", "data", "text", "value"]:
        assert python_name(name) == name


def test_clashing_field_names_work_without_warnings() -> None:
    spec = msg("Clash", *(FieldSpec(t("int32"), name, i) for i, name in enumerate(CLASHING)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cls: Any = build_message(spec)
    assert [str(w.message) for w in caught] == []
    assert list(cls.model_fields) == [f"{n}_" for n in CLASHING]
    m = cls.model_validate({"from": 100, "class": 101})
    assert (m.from_, m.class_, m.copy_) == (100, 101, 4)
    assert cls(from_=7).from_ == 7  # the Python name works for input too
    dumped = m.model_dump()
    assert list(dumped) == CLASHING
    assert json.loads(m.model_dump_json())["from"] == 100
    assert list(cls.model_json_schema()["properties"]) == CLASHING
    assert cls.type_name == "pkg/msg/Clash"
    assert cls.spec is spec
    assert callable(m.model_dump)
    assert errors_of(cls, {"from": "x"})[0]["path"] == "from"


def test_unknown_fields_are_refused() -> None:
    cls = one(t("int32"))
    assert errors_of(cls, {"v": 1, "w": 2}) == [
        {"path": "w", "message": "Extra inputs are not permitted", "type": "extra_forbidden"}
    ]
    assert cls.model_json_schema()["additionalProperties"] is False


def test_class_names_modules_and_type_names() -> None:
    point: Any = build_message(POINT)
    assert (point.__name__, point.__qualname__, point.__module__) == ("Point", "Point", "geo.msg")
    assert point.type_name == "geo/msg/Point"
    assert repr(point(x=1)) == "Point(x=1.0, y=0.0)"
    srv = build_service(SERVICE)
    assert (srv.__name__, srv.__qualname__, srv.__module__) == ("Add", "Add", "calc.srv")
    assert issubclass(srv, Service)
    assert srv.Request.__name__ == "Add_Request"
    assert srv.Request.__module__ == "calc.srv"
    assert (srv.Request.type_name, srv.Response.type_name) == (
        "calc/srv/Add_Request",
        "calc/srv/Add_Response",
    )
    assert srv.type_name == "calc/srv/Add"
    assert srv.spec is SERVICE
    assert srv.text == SERVICE.text
    assert srv.Request.spec is SERVICE.request


def test_a_service_names_its_parts_in_generic_bases_and_nothing_else() -> None:
    srv = build_service(SERVICE)
    assert issubclass(srv, TypedService)
    assert typing.get_args(srv.__orig_bases__[0]) == (srv.Request, srv.Response)
    assert issubclass(srv.Request, ServiceRequest)
    assert typing.get_args(srv.Request.__orig_bases__[1]) == (srv.Response,)
    assert not issubclass(srv.Response, ServiceRequest)
    # The generic base adds no field, config or state: the request is the plain message.
    assert srv.Request.model_fields.keys() == {f.name for f in SERVICE.request.fields}
    assert srv.Request.model_config == Message.model_config
    assert not hasattr(srv.Request(), "__dict__") or srv.Request().__dict__.keys() == (
        srv.Request.model_fields.keys()
    )


# --- documentation ---------------------------------------------------------------------------


def test_comments_become_schema_descriptions() -> None:
    spec = msg(
        "Documented",
        FieldSpec(t("int32"), "speed", doc="Speed in m/s.\nNever negative."),
        FieldSpec(t("int32"), "from", doc="Where it starts."),
        FieldSpec(t("int32"), "plain"),
        doc="A documented message.",
    )
    cls = build_message(spec)
    schema = cls.model_json_schema()
    assert schema["description"] == "A documented message."
    assert schema["title"] == "Documented"
    assert schema["properties"]["speed"]["description"] == "Speed in m/s.\nNever negative."
    assert schema["properties"]["from"]["description"] == "Where it starts."
    assert "description" not in schema["properties"]["plain"]
    assert cls.__doc__ == "A documented message."


# --- nested messages and error paths ---------------------------------------------------------


def test_nested_types_need_a_resolver() -> None:
    with pytest.raises(InterfaceError) as info:
        build_message(POSE)
    assert str(info.value) == (
        "geo/msg/Pose: field 'position' has the nested type geo/msg/Point, "
        "and no resolver was given to find its class"
    )


def test_the_resolver_must_return_a_message_class() -> None:
    with pytest.raises(InterfaceError, match="the resolver returned <class 'int'>"):
        build_message(POSE, lambda _: int)  # type: ignore[arg-type, return-value]


def test_nested_messages_validate_from_dicts_and_instances() -> None:
    resolve = geo_resolver()
    pose_cls, point_cls = resolve(t("Pose", package="geo")), resolve(t("Point", package="geo"))
    pose = pose_cls.model_validate({"position": {"x": 1}, "points": [{"y": 2}, point_cls(x=3)]})
    assert pose.model_dump() == {
        "position": {"x": 1.0, "y": 0.0},
        "points": [{"x": 0.0, "y": 2.0}, {"x": 3.0, "y": 0.0}],
    }
    assert pose.model_json_schema()["$defs"]["Point"]["properties"]["x"]["type"] == "number"


def test_validation_errors_point_into_the_payload() -> None:
    pose_cls = geo_resolver()(t("Pose", package="geo"))
    bad = {"position": {"x": "far", "z": 1}, "points": [{}, {"y": True}], "extra": 1}
    assert errors_of(pose_cls, bad) == [
        {"path": "position.x", "message": "Input should be a valid number", "type": "float_type"},
        {
            "path": "position.z",
            "message": "Extra inputs are not permitted",
            "type": "extra_forbidden",
        },
        {"path": "points[1].y", "message": "Input should be a valid number", "type": "float_type"},
        {"path": "extra", "message": "Extra inputs are not permitted", "type": "extra_forbidden"},
    ]
    values = one(unbounded("uint8"))
    assert errors_of(values, {"v": [0, 1, 2, 256]}) == [
        {
            "path": "v[3]",
            "message": "Input should be less than or equal to 255",
            "type": "less_than_equal",
        }
    ]
    assert errors_of(values, [1, 2]) == [
        {
            "path": "",
            "message": "Input should be a valid dictionary or instance of One",
            "type": "model_type",
        }
    ]


def test_summarize_errors_says_the_first_and_counts_the_rest() -> None:
    three = build_message(
        msg(
            "Three",
            FieldSpec(t("uint8"), "a"),
            FieldSpec(t("int32"), "b"),
            FieldSpec(t("string"), "c"),
        )
    )
    errors = errors_of(three, {"a": 256, "b": "x", "c": 1})
    assert summarize_errors(errors) == "a: Input should be less than or equal to 255 (and 2 more)"
    assert summarize_errors(errors[:1]) == "a: Input should be less than or equal to 255"
    whole = errors_of(three, [1, 2])  # no path: the payload as a whole is wrong
    assert summarize_errors(whole) == "Input should be a valid dictionary or instance of Three"


@pytest.mark.parametrize(
    ("element", "good", "bad", "path"),
    [
        (t("int32"), 1, {}, "v[1]"),
        (t("uint8"), 0, 256, "v[1]"),  # a byte array given as a list of integers
        (t("string"), "s", 5, "v[1]"),
        (t("Point", package="geo"), {"x": 1.0}, {"x": "no"}, "v[1].x"),
    ],
)
def test_an_array_stops_at_its_first_invalid_element(
    element: TypeSpec, good: Any, bad: Any, path: str
) -> None:
    # 100 000 bad elements cost one error, not 100 000: the work and the reply of a bad
    # request do not grow with the number of elements it holds. Every kind of array.
    for type_ in (
        unbounded(element.name, package=element.package),
        bounded(element.name, 200_000, package=element.package),
        fixed(element.name, 100_001, package=element.package),
    ):
        cls = build_message(msg("Many", FieldSpec(type_, "v")), geo_resolver())
        with pytest.raises(pydantic.ValidationError) as caught:
            cls.model_validate({"v": [good, *[bad] * 100_000]})
        assert caught.value.error_count() == 1
        assert [e["path"] for e in error_data(caught.value)["errors"]] == [path]


def test_an_error_lists_the_first_problems_and_counts_them_all() -> None:
    # A reply must not be much larger than the request that caused it: of 30 bad fields, the
    # first MAX_LISTED_ERRORS are listed, and error_count says how many were found.
    wide = build_message(msg("Wide", *(FieldSpec(t("uint8"), f"f{i}") for i in range(30))))
    with pytest.raises(pydantic.ValidationError) as caught:
        wide.model_validate({f"f{i}": 256 for i in range(30)})
    data = error_data(caught.value)
    assert len(data["errors"]) == MAX_LISTED_ERRORS == 10
    assert [e["path"] for e in data["errors"]] == [f"f{i}" for i in range(10)]
    assert data["error_count"] == 30
    assert summarize_errors(data["errors"], data["error_count"]) == (
        "f0: Input should be less than or equal to 255 (and 29 more)"
    )
    with pytest.raises(pydantic.ValidationError) as few:
        wide.model_validate({"f0": 256, "f1": 257})
    assert "error_count" not in error_data(few.value)  # all of them are listed


def test_a_lone_surrogate_validates_but_unencodable_strings_finds_it() -> None:
    # Refusing lone surrogates during validation would cost 10-15 % of a string-heavy
    # validation, so they pass; writing JSON fails, and this names the field for the error.
    pose_cls = geo_resolver()(t("Pose", package="geo"))
    names = one(unbounded("string"))
    message = names(v=["ok", "caf\u00e9", "a\udc80", "\ud800"])
    assert message.v[3] == "\ud800"
    with pytest.raises(pydantic_core.PydanticSerializationError):
        message.model_dump_json()
    assert unencodable_strings(message) == [
        {
            "path": "v[2]",
            "message": "String should not contain the lone surrogate '\\udc80' (at index 1): "
            "it cannot be written as UTF-8",
            "type": "string_unicode",
        },
        {
            "path": "v[3]",
            "message": "String should not contain the lone surrogate '\\ud800' (at index 0): "
            "it cannot be written as UTF-8",
            "type": "string_unicode",
        },
    ]
    assert unencodable_strings({"a": {"b": ["\ud800"]}})[0]["path"] == "a.b[0]"
    assert unencodable_strings(pose_cls()) == []
    assert unencodable_strings(names(v=["caf\u00e9", "\U0001f600"])) == []


# --- services and actions ----------------------------------------------------------------------

SERVICE = ServiceSpec(
    "calc",
    "Add",
    msg("Add_Request", FieldSpec(t("int64"), "a"), FieldSpec(t("int64"), "b"), package="calc"),
    msg("Add_Response", FieldSpec(t("int64"), "sum"), package="calc"),
    text="int64 a\nint64 b\n---\nint64 sum\n",
)


def test_services_take_defaults_like_ros() -> None:
    srv: Any = build_service(SERVICE)
    assert srv.Request().model_dump() == {"a": 0, "b": 0}
    assert srv.Response(sum=3).sum == 3
    assert srv.Request.model_validate_json('{"a": 1}') == srv.Request(a=1, b=0)


def test_actions_group_goal_result_and_feedback() -> None:
    spec = ActionSpec(
        "demo",
        "Count",
        msg("Count_Goal", FieldSpec(t("int32"), "order"), package="demo"),
        msg("Count_Result", FieldSpec(unbounded("int32"), "sequence"), package="demo"),
        msg("Count_Feedback", FieldSpec(unbounded("int32"), "partial"), package="demo"),
        text="int32 order\n---\nint32[] sequence\n---\nint32[] partial\n",
    )
    action: Any = build_action(spec)
    assert issubclass(action, Action)
    assert action.type_name == "demo/action/Count"
    assert action.text == spec.text
    assert action.spec is spec
    assert [action.Goal.__name__, action.Result.__name__, action.Feedback.__name__] == [
        "Count_Goal",
        "Count_Result",
        "Count_Feedback",
    ]
    assert action.Feedback.type_name == "demo/action/Count_Feedback"
    assert action.Result(sequence=[1, 1, 2]).sequence == [1, 1, 2]


def test_each_build_makes_a_new_class() -> None:
    assert build_message(POINT) is not build_message(POINT)


# --- the ROS 2 test corpus -----------------------------------------------------------------------


def corpus_classes() -> tuple[dict[str, Any], dict[str, Any]]:
    root = ros_test_interfaces()
    specs: dict[str, Any] = {
        p.stem: parse_file(p, "test_msgs") for p in sorted((root / "msg").glob("*.msg"))
    }
    built: dict[str, type[Message]] = {}

    def resolve(type_: TypeSpec) -> type[Message]:
        if type_.name not in built:
            built[type_.name] = build_message(specs[type_.name], resolve)
        return built[type_.name]

    for name in specs:
        resolve(t(name, package="test_msgs"))
    others = {
        p.name: parse_file(p, "test_msgs")
        for kind in ("srv", "action")
        for p in sorted((root / kind).iterdir())
    }
    groups: dict[str, Any] = {}
    for name, spec in others.items():
        if isinstance(spec, ServiceSpec):
            groups[name] = build_service(spec, resolve)
        else:
            assert isinstance(spec, ActionSpec)
            groups[name] = build_action(spec, resolve)
    return built, groups


def test_the_whole_ros_corpus_builds_and_round_trips() -> None:
    messages, groups = corpus_classes()
    assert sorted(messages) == sorted(p.stem for p in (ros_test_interfaces() / "msg").iterdir())
    parts = [*messages.values()]
    for group in groups.values():
        parts += [
            getattr(group, a)
            for a in ("Request", "Response", "Goal", "Result", "Feedback")
            if hasattr(group, a)
        ]
    for cls in parts:
        m = cls()
        assert cls.model_validate_json(m.model_dump_json()) == m
        assert cls.model_validate(m.model_dump()) == m
        assert set(cls.model_json_schema()["properties"]) == {f.name for f in cls.spec.fields}


def test_corpus_defaults_and_constants_match_the_files() -> None:
    messages, _ = corpus_classes()
    arrays = messages["Arrays"]()
    assert arrays.int64_values_default == [0, 2**63 - 1, -(2**63)]
    assert arrays.uint64_values_default == [0, 1, 2**64 - 1]
    assert arrays.string_values_default == ["", "max value", "min value"]
    assert arrays.float32_values_default == [1.125, 0.0, -1.125]
    assert arrays.basic_types_values == [messages["BasicTypes"]()] * 3
    assert arrays.defaults_values[0].int8_value == -50
    assert len(arrays.bool_values) == 3
    strings = messages["Strings"]()
    assert strings.string_value_default4 == "Hello'world!"
    assert messages["Strings"].STRING_CONST == "Hello world!"
    assert messages["Constants"].UINT64_CONST == 50000000
    assert messages["WStrings"]().wstring_value_default3 == "ハローワールド"
    assert messages["Empty"]().model_dump() == {}
    error = errors_of(messages["BoundedSequences"], {"uint8_values": [1, 2, 3, 4]})
    assert error == [
        {
            "path": "uint8_values",
            "message": "Data should have at most 3 bytes",
            "type": "bytes_too_long",
        }
    ]


# --- property: random valid instances survive JSON ---------------------------------------------


def element_strategy(type_: TypeSpec, nested: dict[str, type[Message]]) -> st.SearchStrategy[Any]:
    name = type_.name
    if not type_.is_primitive:
        return instances(nested[name], nested)
    if name == "bool":
        return st.booleans()
    if name in INTEGER_RANGES:
        low, high = INTEGER_RANGES[name]
        return st.integers(low, high)
    if name == "float32":
        return st.floats(width=32, allow_nan=False)
    if name == "float64":
        return st.floats(allow_nan=False)
    return st.text(max_size=type_.string_bound if type_.string_bound is not None else 20)


def value_strategy(type_: TypeSpec, nested: dict[str, type[Message]]) -> st.SearchStrategy[Any]:
    element = element_strategy(type_, nested)
    if type_.array is ArrayKind.FIXED:
        return st.lists(element, min_size=type_.size or 0, max_size=type_.size)
    if type_.array is ArrayKind.BOUNDED:
        return st.lists(element, max_size=type_.size)
    if type_.array is ArrayKind.UNBOUNDED:
        return st.lists(element, max_size=4)
    return element


def instances(cls: type[Message], nested: dict[str, type[Message]]) -> st.SearchStrategy[Any]:
    fields = {f.name: value_strategy(f.type, nested) for f in cls.spec.fields}
    return st.fixed_dictionaries({}, optional=fields).map(cls.model_validate)


EVERYTHING = msg(
    "Everything",
    *(FieldSpec(t(name), f"{name}_value") for name in sorted(PRIMITIVE_ALIASES)),
    *(FieldSpec(unbounded(name), f"{name}_list") for name in sorted(PRIMITIVE_ALIASES)),
    FieldSpec(t("string", bound=4), "short"),
    FieldSpec(bounded("wstring", 2, bound=3), "shorts"),
    FieldSpec(fixed("uint8", 4), "four_bytes"),
    FieldSpec(fixed("float32", 2), "pair"),
    FieldSpec(t("Pose", package="geo"), "pose"),
    FieldSpec(bounded("Point", 2, package="geo"), "corners"),
    FieldSpec(t("int32"), "from"),
    FieldSpec(t("int32"), "model_dump"),
)


def everything_classes() -> dict[str, type[Message]]:
    resolve = geo_resolver()
    return {
        "Everything": build_message(EVERYTHING, resolve),
        "Pose": resolve(t("Pose", package="geo")),
        "Point": resolve(t("Point", package="geo")),
    }


EVERYTHING_CLASSES = everything_classes()


@settings(max_examples=60, deadline=None)
@given(instances(EVERYTHING_CLASSES["Everything"], EVERYTHING_CLASSES))
def test_random_valid_instances_round_trip_through_json(instance: Message) -> None:
    cls = type(instance)
    text = instance.model_dump_json()
    assert cls.model_validate_json(text) == instance
    assert cls.model_validate(instance.model_dump()) == instance
    assert cls.model_validate_json(text).model_dump_json() == text


def test_every_primitive_has_an_alias() -> None:
    import srvwire.models as models

    assert set(PRIMITIVE_ALIASES) == {"bool", "string", "wstring", "float32", "float64"} | set(
        INTEGER_RANGES
    )
    for alias in PRIMITIVE_ALIASES.values():
        assert hasattr(models, alias)


class _Floats(pydantic.BaseModel):
    values: list[float]


def test_a_strict_writer_refuses_a_value_that_does_not_fit_even_with_warnings_ignored() -> None:
    import warnings

    from pydantic_core import PydanticSerializationError

    from srvwire.models import dump_json, json_writer

    value = _Floats(values=[1.0])
    value.values.append("x")  # type: ignore[arg-type]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # goes in front of srvwire's filter: put back behind it
        with pytest.raises(PydanticSerializationError, match="Expected `float`"):
            json_writer(_Floats, strict=True)(value)
        with pytest.raises(PydanticSerializationError, match="Expected `float`"):
            dump_json(value, strict=True)
    assert json_writer(_Floats, strict=True)(_Floats(values=[1.0])) == b'{"values":[1.0]}'


def test_only_strict_writers_turn_the_serializer_warning_into_an_error() -> None:
    import warnings

    from srvwire.models import json_writer

    value = _Floats(values=[1.0])
    value.values.append("x")  # type: ignore[arg-type]
    json_writer(_Floats, strict=True)(_Floats(values=[1.0]))  # the filter is in place
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        json_writer(_Floats, strict=True)(_Floats(values=[2.0]))
        assert value.model_dump_json() == '{"values":[1.0,"x"]}'  # pydantic's own: a warning
        assert json_writer(_Floats)(value) == b'{"values":[1.0,"x"]}'  # not strict: a warning
    assert [str(w.message).splitlines()[0] for w in caught] == ["Pydantic serializer warnings:"] * 2
