"""What ROS 2's test interface files hold, read off the files by hand.

The files are ROS 2's own test interfaces (``shared/ros_test_interfaces``, see
``support.ros_test_interfaces``), which ROS 2 ships as the package ``test_msgs``. Each fact is
written here once, keyed by the file's path inside that folder, so the parser's and the models'
tests check the same counts and values, and a parser or model that drops, adds or alters a
field, constant or default fails both.
"""

from __future__ import annotations

from srvwire.idl import Scalar, Value

# (fields, constants, fields with a default) for each part of each file, in file order.
COUNTS: dict[str, list[tuple[int, int, int]]] = {
    "msg/Arrays.msg": [(32, 0, 14)],
    "msg/BasicTypes.msg": [(13, 0, 0)],
    "msg/BoundedPlainSequences.msg": [(30, 0, 13)],
    "msg/BoundedSequences.msg": [(32, 0, 14)],
    "msg/Constants.msg": [(0, 13, 0)],
    "msg/Defaults.msg": [(13, 0, 13)],
    "msg/Empty.msg": [(0, 0, 0)],
    "msg/MultiNested.msg": [(9, 0, 0)],
    "msg/Nested.msg": [(1, 0, 0)],
    "msg/Strings.msg": [(12, 1, 10)],
    "msg/UnboundedSequences.msg": [(32, 0, 14)],
    "msg/WStrings.msg": [(7, 0, 3)],
    "srv/Arrays.srv": [(31, 0, 14), (31, 0, 14)],
    "srv/BasicTypes.srv": [(14, 0, 0), (14, 0, 0)],
    "srv/Empty.srv": [(0, 0, 0), (0, 0, 0)],
    "action/Fibonacci.action": [(1, 0, 0), (1, 0, 0), (1, 0, 0)],
}

# The defaults of the arrays and sequences of primitives (BoundedPlainSequences has no strings).
PLAIN_ARRAY_DEFAULTS: dict[str, Value] = {
    "bool_values_default": (False, True, False),
    "byte_values_default": (0, 1, 255),
    "char_values_default": (0, 1, 127),
    "float32_values_default": (1.125, 0.0, -1.125),
    "float64_values_default": (3.1415, 0.0, -3.1415),
    "int8_values_default": (0, 127, -128),
    "uint8_values_default": (0, 1, 255),
    "int16_values_default": (0, 32767, -32768),
    "uint16_values_default": (0, 1, 65535),
    "int32_values_default": (0, 2147483647, -2147483648),
    "uint32_values_default": (0, 1, 4294967295),
    "int64_values_default": (0, 9223372036854775807, -9223372036854775808),
    "uint64_values_default": (0, 1, 18446744073709551615),
}
ARRAY_DEFAULTS: dict[str, Value] = {
    **PLAIN_ARRAY_DEFAULTS,
    "string_values_default": ("", "max value", "min value"),
}
SCALAR_DEFAULTS: dict[str, Value] = {
    "bool_value": True,
    "byte_value": 50,
    "char_value": 100,
    "float32_value": 1.125,
    "float64_value": 1.125,
    "int8_value": -50,
    "uint8_value": 200,
    "int16_value": -1000,
    "uint16_value": 2000,
    "int32_value": -30000,
    "uint32_value": 60000,
    "int64_value": -40000000,
    "uint64_value": 50000000,
}
# Strings.msg gives ``string_value_<key>`` and ``bounded_string_value_<key>`` the same defaults.
_STRING_DEFAULTS = {
    "default1": "Hello world!",
    "default2": "Hello'world!",
    "default3": 'Hello"world!',
    "default4": "Hello'world!",
    "default5": 'Hello"world!',
}
STRING_DEFAULTS: dict[str, Value] = {
    **{f"string_value_{k}": v for k, v in _STRING_DEFAULTS.items()},
    **{f"bounded_string_value_{k}": v for k, v in _STRING_DEFAULTS.items()},
}
WSTRING_DEFAULTS: dict[str, Value] = {
    "wstring_value_default1": "Hello world!",
    "wstring_value_default2": "Hellö wörld!",
    "wstring_value_default3": "ハローワールド",
}

# The default of every field that has one, for each part of each file that has any.
DEFAULTS: dict[str, list[dict[str, Value]]] = {
    "msg/Arrays.msg": [ARRAY_DEFAULTS],
    "msg/BoundedPlainSequences.msg": [PLAIN_ARRAY_DEFAULTS],
    "msg/BoundedSequences.msg": [ARRAY_DEFAULTS],
    "msg/Defaults.msg": [SCALAR_DEFAULTS],
    "msg/Strings.msg": [STRING_DEFAULTS],
    "msg/UnboundedSequences.msg": [ARRAY_DEFAULTS],
    "msg/WStrings.msg": [WSTRING_DEFAULTS],
    "srv/Arrays.srv": [ARRAY_DEFAULTS, ARRAY_DEFAULTS],
}

# The value of every constant, for each file that has any (all of them are messages).
CONSTANTS: dict[str, dict[str, Scalar]] = {
    "msg/Constants.msg": {
        "BOOL_CONST": True,
        "BYTE_CONST": 50,
        "CHAR_CONST": 100,
        "FLOAT32_CONST": 1.125,
        "FLOAT64_CONST": 1.125,
        "INT8_CONST": -50,
        "UINT8_CONST": 200,
        "INT16_CONST": -1000,
        "UINT16_CONST": 2000,
        "INT32_CONST": -30000,
        "UINT32_CONST": 60000,
        "INT64_CONST": -40000000,
        "UINT64_CONST": 50000000,
    },
    "msg/Strings.msg": {"STRING_CONST": "Hello world!"},
}


def defaults_by_part(path: str) -> list[dict[str, Value]]:
    """The defaults written in each part of the file at ``path``; ``{}`` for a part with none."""
    return DEFAULTS.get(path, [{} for _ in COUNTS[path]])
