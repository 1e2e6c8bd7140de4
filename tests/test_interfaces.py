"""The tutorial's services and the first bundled ROS 2 types: their fields, every one documented."""

from __future__ import annotations

from typing import Any, TypeAlias

import pytest

from srvwire.idl import FieldSpec, Value
from srvwire.loader import InterfaceLoader, bundled_interfaces

# (type as written in full, field name, default or None)
Field: TypeAlias = tuple[str, str, Value | None]

TUTORIAL_SERVICES: dict[str, tuple[list[Field], list[Field]]] = {
    "advanced_communication_tutorials/srv/RobotStateQuery": (
        [("string", "query_type", None), ("string", "target_frame", None)],
        [
            ("bool", "success", None),
            ("string", "message", None),
            ("float64[]", "values", None),
            ("string[]", "names", None),
        ],
    ),
    "advanced_communication_tutorials/srv/RobotCommand": (
        [
            ("string", "command_type", None),
            ("float64[]", "parameters", None),
            ("string", "target_frame", None),
        ],
        [
            ("bool", "success", None),
            ("string", "message", None),
            ("float64", "execution_time", None),
        ],
    ),
}

# The same fields, types and defaults as ROS 2's own definitions of these types.
STANDARD_SERVICES: dict[str, tuple[list[Field], list[Field]]] = {
    "std_srvs/srv/Empty": ([], []),
    "std_srvs/srv/Trigger": ([], [("bool", "success", None), ("string", "message", None)]),
    "std_srvs/srv/SetBool": (
        [("bool", "data", None)],
        [("bool", "success", None), ("string", "message", None)],
    ),
    "example_interfaces/srv/AddTwoInts": (
        [("int64", "a", None), ("int64", "b", None)],
        [("int64", "sum", None)],
    ),
}
STANDARD_MESSAGES: dict[str, list[Field]] = {
    "builtin_interfaces/msg/Time": [("int32", "sec", None), ("uint32", "nanosec", None)],
    "builtin_interfaces/msg/Duration": [("int32", "sec", None), ("uint32", "nanosec", None)],
    "std_msgs/msg/Header": [
        ("builtin_interfaces/Time", "stamp", None),
        ("string", "frame_id", None),
    ],
    "sensor_msgs/msg/JointState": [
        ("std_msgs/Header", "header", None),
        ("string[]", "name", None),
        ("float64[]", "position", None),
        ("float64[]", "velocity", None),
        ("float64[]", "effort", None),
    ],
    "geometry_msgs/msg/Point": [
        ("float64", "x", None),
        ("float64", "y", None),
        ("float64", "z", None),
    ],
    "geometry_msgs/msg/Quaternion": [
        ("float64", "x", 0.0),
        ("float64", "y", 0.0),
        ("float64", "z", 0.0),
        ("float64", "w", 1.0),
    ],
    "geometry_msgs/msg/Pose": [
        ("geometry_msgs/Point", "position", None),
        ("geometry_msgs/Quaternion", "orientation", None),
    ],
}
SERVICES = {**TUTORIAL_SERVICES, **STANDARD_SERVICES}

# What a message built with no arguments holds.
DEFAULT_INSTANCES: dict[str, dict[str, Any]] = {
    "builtin_interfaces/msg/Time": {"sec": 0, "nanosec": 0},
    "builtin_interfaces/msg/Duration": {"sec": 0, "nanosec": 0},
    "std_msgs/msg/Header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
    "sensor_msgs/msg/JointState": {
        "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
        "name": [],
        "position": [],
        "velocity": [],
        "effort": [],
    },
    "geometry_msgs/msg/Point": {"x": 0.0, "y": 0.0, "z": 0.0},
    "geometry_msgs/msg/Quaternion": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
    "geometry_msgs/msg/Pose": {
        "position": {"x": 0.0, "y": 0.0, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
    },
}


@pytest.fixture(scope="module")
def loader() -> InterfaceLoader:
    return InterfaceLoader([bundled_interfaces()], use_default_path=False)


def described(fields: tuple[FieldSpec, ...]) -> list[Field]:
    return [(str(field.type), field.name, field.default) for field in fields]


def test_the_bundle_holds_these_types(loader: InterfaceLoader) -> None:
    # The exact list of every bundled package and type is in test_bundled_interfaces.py.
    assert set([*SERVICES, *STANDARD_MESSAGES]) <= set(loader.types())


@pytest.mark.parametrize("name", sorted([*SERVICES, *STANDARD_MESSAGES]))
def test_every_bundled_interface_loads(loader: InterfaceLoader, name: str) -> None:
    cls = loader.load(name)
    assert cls.type_name == name


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_services_have_their_fields(loader: InterfaceLoader, name: str) -> None:
    spec = loader.service_spec(name)
    request, response = SERVICES[name]
    assert described(spec.request.fields) == request
    assert described(spec.response.fields) == response
    assert spec.request.constants == spec.response.constants == ()


@pytest.mark.parametrize("name", sorted(STANDARD_MESSAGES))
def test_messages_have_their_fields(loader: InterfaceLoader, name: str) -> None:
    spec = loader.message_spec(name)
    assert described(spec.fields) == STANDARD_MESSAGES[name]
    assert spec.constants == ()


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_every_service_builds_a_request_and_a_response_with_no_arguments(
    loader: InterfaceLoader, name: str
) -> None:
    service = loader.load_service(name)
    request, response = SERVICES[name]
    assert list(service.Request().model_dump()) == [field[1] for field in request]
    assert list(service.Response().model_dump()) == [field[1] for field in response]


@pytest.mark.parametrize("name", sorted(DEFAULT_INSTANCES))
def test_default_messages(loader: InterfaceLoader, name: str) -> None:
    assert loader.load_message(name)().model_dump() == DEFAULT_INSTANCES[name]


def test_the_tutorial_services_hold_what_they_are_given(loader: InterfaceLoader) -> None:
    query = loader.load_service("advanced_communication_tutorials/RobotStateQuery")
    reply = query.Response.model_validate(
        {"success": True, "message": "ok", "values": [1.5, -2.0], "names": ["a", "b"]}
    )
    assert reply.model_dump() == {
        "success": True,
        "message": "ok",
        "values": [1.5, -2.0],
        "names": ["a", "b"],
    }
    command = loader.load_service("advanced_communication_tutorials/RobotCommand")
    request = command.Request.model_validate(
        {"command_type": "move_to", "parameters": [0.5, 0.25], "target_frame": "map"}
    )
    assert request.model_dump() == {
        "command_type": "move_to",
        "parameters": [0.5, 0.25],
        "target_frame": "map",
    }


@pytest.mark.parametrize("name", sorted([*SERVICES, *STANDARD_MESSAGES]))
def test_every_field_and_message_is_documented(loader: InterfaceLoader, name: str) -> None:
    if name in SERVICES:
        spec = loader.service_spec(name)
        assert spec.request.doc, f"{name} has no leading comment"
        assert spec.response.doc, f"{name} has no comment below its '---'"
        fields = spec.request.fields + spec.response.fields
    else:
        message = loader.message_spec(name)
        assert message.doc, f"{name} has no leading comment"
        fields = message.fields
    undocumented = [field.name for field in fields if not field.doc]
    assert undocumented == [], f"{name}: fields without a comment"
    text = loader.path_of(name).read_text(encoding="utf-8")
    assert text.startswith("# "), f"{name} does not open with a comment saying what it is"
