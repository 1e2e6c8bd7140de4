"""The ROS 2 packages bundled with srvwire: the whole of each, loading and round-tripping.

The type names, fields, constants and defaults below are those of ROS 2 (rolling/jazzy): the
packages ``common_interfaces``, ``rcl_interfaces`` (``builtin_interfaces``, ``action_msgs``),
``unique_identifier_msgs`` and ``example_interfaces``. Every file on disk is loaded through the
public ``load_*`` functions and round-tripped through JSON; the exact list of names per package
makes a missing or an extra file fail.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, TypeAlias

import pytest

import srvwire
from srvwire.errors import InterfaceError, InterfaceNotFoundError
from srvwire.idl import ArrayKind, FieldSpec, InterfaceKind, MessageSpec, Scalar, TypeSpec, Value
from srvwire.loader import InterfaceLoader, bundled_interfaces
from srvwire.models import Action, Message, Service
from srvwire.typeregistry import TypeRegistry
from support import ROOT

BUNDLE = bundled_interfaces()
SEARCH_PATH = [BUNDLE]  # only the bundle, whatever SRVWIRE_INTERFACE_PATH holds

# Eighteen scalar wrappers and multi-arrays that std_msgs and example_interfaces both define.
_NUMBERS = ["Float32", "Float64", "Int16", "Int32", "Int64", "Int8"]
_NUMBERS += ["UInt16", "UInt32", "UInt64", "UInt8"]
_PLAIN = sorted(
    [
        "Bool",
        "Byte",
        "ByteMultiArray",
        "Char",
        "Empty",
        "MultiArrayDimension",
        "MultiArrayLayout",
        "String",
        *_NUMBERS,
        *(f"{number}MultiArray" for number in _NUMBERS),
    ]
)

EXPECTED: dict[str, dict[str, list[str]]] = {
    "action_msgs": {"msg": ["GoalInfo", "GoalStatus", "GoalStatusArray"], "srv": ["CancelGoal"]},
    "advanced_communication_tutorials": {
        "action": ["Calibrate"],
        "srv": ["RobotCommand", "RobotStateQuery"],
    },
    "builtin_interfaces": {"msg": ["Duration", "Time"]},
    "diagnostic_msgs": {
        "msg": ["DiagnosticArray", "DiagnosticStatus", "KeyValue"],
        "srv": ["AddDiagnostics", "SelfTest"],
    },
    "example_interfaces": {
        "msg": sorted([*_PLAIN, "WString"]),
        "srv": ["AddTwoInts", "SetBool", "Trigger"],
        "action": ["Fibonacci"],
    },
    "geometry_msgs": {
        "msg": [
            "Accel",
            "AccelStamped",
            "AccelWithCovariance",
            "AccelWithCovarianceStamped",
            "Inertia",
            "InertiaStamped",
            "Point",
            "Point32",
            "PointStamped",
            "Polygon",
            "PolygonInstance",
            "PolygonInstanceStamped",
            "PolygonStamped",
            "Pose",
            "Pose2D",
            "PoseArray",
            "PoseStamped",
            "PoseWithCovariance",
            "PoseWithCovarianceStamped",
            "Quaternion",
            "QuaternionStamped",
            "Transform",
            "TransformStamped",
            "Twist",
            "TwistStamped",
            "TwistWithCovariance",
            "TwistWithCovarianceStamped",
            "Vector3",
            "Vector3Stamped",
            "VelocityStamped",
            "Wrench",
            "WrenchStamped",
        ]
    },
    "nav_msgs": {
        "msg": ["GridCells", "MapMetaData", "OccupancyGrid", "Odometry", "Path"],
        "srv": ["GetMap", "GetPlan", "LoadMap", "SetMap"],
    },
    "sensor_msgs": {
        "msg": [
            "BatteryState",
            "CameraInfo",
            "ChannelFloat32",
            "CompressedImage",
            "FluidPressure",
            "Illuminance",
            "Image",
            "Imu",
            "JointState",
            "Joy",
            "JoyFeedback",
            "JoyFeedbackArray",
            "LaserEcho",
            "LaserScan",
            "MagneticField",
            "MultiDOFJointState",
            "MultiEchoLaserScan",
            "NavSatFix",
            "NavSatStatus",
            "PointCloud",
            "PointCloud2",
            "PointField",
            "Range",
            "RegionOfInterest",
            "RelativeHumidity",
            "Temperature",
            "TimeReference",
        ],
        "srv": ["SetCameraInfo"],
    },
    "std_msgs": {"msg": sorted([*_PLAIN, "ColorRGBA", "Header"])},
    "std_srvs": {"srv": ["Empty", "SetBool", "Trigger"]},
    "trajectory_msgs": {
        "msg": [
            "JointTrajectory",
            "JointTrajectoryPoint",
            "MultiDOFJointTrajectory",
            "MultiDOFJointTrajectoryPoint",
        ]
    },
    "unique_identifier_msgs": {"msg": ["UUID"]},
}
EXPECTED_NAMES = sorted(
    f"{package}/{kind}/{name}"
    for package, kinds in EXPECTED.items()
    for kind, names in kinds.items()
    for name in names
)


def names_on_disk() -> list[str]:
    """The full name of every interface file under the bundle folder, found by globbing."""
    return sorted(
        f"{path.parent.parent.name}/{kind.value}/{path.stem}"
        for kind in InterfaceKind
        for path in BUNDLE.glob(f"*/{kind.value}/*.{kind.value}")
    )


ON_DISK = names_on_disk()

Type: TypeAlias = type[Message] | type[Service] | type[Action]


def load(name: str) -> Type:
    """Load ``name`` through the public function for its kind."""
    kind = name.split("/")[1]
    if kind == "msg":
        return srvwire.load_message(name, SEARCH_PATH)
    if kind == "srv":
        return srvwire.load_service(name, SEARCH_PATH)
    return srvwire.load_action(name, SEARCH_PATH)


def parts_of(cls: Type) -> list[type[Message]]:
    if isinstance(cls, type) and issubclass(cls, Message):
        return [cls]
    if isinstance(cls, type) and issubclass(cls, Service):
        return [cls.Request, cls.Response]
    assert issubclass(cls, Action)
    return [cls.Goal, cls.Result, cls.Feedback]


# --- which types there are -----------------------------------------------------------------


def test_the_bundle_holds_exactly_these_packages() -> None:
    assert list(InterfaceLoader(SEARCH_PATH).packages()) == sorted(EXPECTED)
    assert "visualization_msgs" not in EXPECTED  # not bundled: nothing above should claim it


@pytest.mark.parametrize("package", sorted(EXPECTED))
def test_each_package_holds_exactly_its_ros_types(package: str) -> None:
    expected = [
        f"{package}/{kind}/{name}" for kind, names in EXPECTED[package].items() for name in names
    ]
    assert InterfaceLoader(SEARCH_PATH).types(package) == sorted(expected)


def test_the_files_on_disk_are_the_expected_ones() -> None:
    assert ON_DISK == EXPECTED_NAMES
    assert len(ON_DISK) == 154  # 151 from ROS 2, and the two services and action of the tutorial


# --- every file loads and round-trips --------------------------------------------------------


@pytest.mark.parametrize("name", ON_DISK)
def test_every_file_loads_through_the_public_functions(name: str) -> None:
    cls = load(name)
    assert cls.type_name == name
    assert load(name) is cls  # the shared loader builds each class once


def sample(cls: type[Message], loader: InterfaceLoader) -> dict[str, Any]:
    """Data for ``cls`` in which every field holds something other than its default.

    Scalars get a value that fits every type of their kind; arrays hold elements (the size of a
    fixed array, one for a bounded one, two for an unbounded one); nested messages are filled the
    same way, all the way down. Bytes are given as a list of integers, which every byte array
    accepts as input, whatever it is on the wire.
    """
    return {field.name: field_sample(field.type, loader) for field in cls.spec.fields}


def field_sample(type_: TypeSpec, loader: InterfaceLoader) -> Any:
    element: Any
    if type_.is_primitive:
        element = scalar_sample(type_.name)
    else:
        element = sample(loader.load_message(type_.qualified_name), loader)
    if type_.array is ArrayKind.NONE:
        return element
    count = {ArrayKind.FIXED: type_.size or 0, ArrayKind.BOUNDED: 1}.get(type_.array, 2)
    return [element] * count


def scalar_sample(type_name: str) -> Scalar:
    if type_name == "bool":
        return True
    if type_name in ("float32", "float64"):
        return 0.5
    if type_name in ("string", "wstring"):
        return "x"
    return 7  # every integer type, byte and char included, holds 7


@pytest.mark.parametrize("name", ON_DISK)
def test_every_part_round_trips_through_json(name: str) -> None:
    loader = InterfaceLoader(SEARCH_PATH)
    for part in parts_of(load(name)):
        for message in (part(), part.model_validate(sample(part, loader))):
            text = message.model_dump_json()
            back = part.model_validate_json(text)
            assert back == message
            assert back.model_dump_json() == text


@pytest.mark.parametrize("name", ON_DISK)
def test_every_part_has_its_constants_as_class_attributes(name: str) -> None:
    for part in parts_of(load(name)):
        for constant in part.spec.constants:
            assert getattr(part, constant.name) == constant.value


@pytest.mark.parametrize("name", ON_DISK)
def test_every_file_and_field_says_what_it_is_for(name: str) -> None:
    cls = load(name)
    text = InterfaceLoader(SEARCH_PATH).path_of(name).read_text(encoding="utf-8")
    assert text.startswith("# "), f"{name} does not open with a comment saying what it is"
    undocumented = [part.type_name for part in parts_of(cls) if not part.spec.doc]
    assert undocumented == []
    bare = [field.name for part in parts_of(cls) for field in part.spec.fields if not field.doc]
    assert bare == [], f"{name}: fields without a comment"


# --- well-known constants and defaults --------------------------------------------------------

CONSTANTS: list[tuple[str, str, str, Scalar]] = [
    # (type, part or "", constant, value)
    ("sensor_msgs/msg/NavSatStatus", "", "STATUS_UNKNOWN", -2),
    ("sensor_msgs/msg/NavSatStatus", "", "STATUS_NO_FIX", -1),
    ("sensor_msgs/msg/NavSatStatus", "", "STATUS_FIX", 0),
    ("sensor_msgs/msg/NavSatStatus", "", "STATUS_GBAS_FIX", 2),
    ("sensor_msgs/msg/NavSatStatus", "", "SERVICE_GALILEO", 8),
    ("sensor_msgs/msg/NavSatFix", "", "COVARIANCE_TYPE_KNOWN", 3),
    ("sensor_msgs/msg/BatteryState", "", "POWER_SUPPLY_STATUS_FULL", 4),
    ("sensor_msgs/msg/BatteryState", "", "POWER_SUPPLY_HEALTH_SAFETY_TIMER_EXPIRE", 8),
    ("sensor_msgs/msg/BatteryState", "", "POWER_SUPPLY_TECHNOLOGY_LION", 2),
    ("sensor_msgs/msg/PointField", "", "FLOAT32", 7),
    ("sensor_msgs/msg/PointField", "", "FLOAT64", 8),
    ("sensor_msgs/msg/Range", "", "INFRARED", 1),
    ("sensor_msgs/msg/JoyFeedback", "", "TYPE_BUZZER", 2),
    ("action_msgs/msg/GoalStatus", "", "STATUS_UNKNOWN", 0),
    ("action_msgs/msg/GoalStatus", "", "STATUS_ACCEPTED", 1),
    ("action_msgs/msg/GoalStatus", "", "STATUS_SUCCEEDED", 4),
    ("action_msgs/msg/GoalStatus", "", "STATUS_ABORTED", 6),
    ("action_msgs/srv/CancelGoal", "Response", "ERROR_UNKNOWN_GOAL_ID", 2),
    ("action_msgs/srv/CancelGoal", "Response", "ERROR_GOAL_TERMINATED", 3),
    ("diagnostic_msgs/msg/DiagnosticStatus", "", "WARN", 1),
    ("diagnostic_msgs/msg/DiagnosticStatus", "", "STALE", 3),
    ("nav_msgs/srv/LoadMap", "Response", "RESULT_INVALID_MAP_METADATA", 3),
    ("nav_msgs/srv/LoadMap", "Response", "RESULT_UNDEFINED_FAILURE", 255),
]


@pytest.mark.parametrize(("name", "part", "constant", "value"), CONSTANTS)
def test_well_known_constants(name: str, part: str, constant: str, value: Scalar) -> None:
    cls: Any = load(name)
    owner = getattr(cls, part) if part else cls
    assert getattr(owner, constant) == value
    assert type(getattr(owner, constant)) is int


def test_the_written_defaults() -> None:
    assert load_msg("sensor_msgs/msg/NavSatStatus")().model_dump()["status"] == -2
    quaternion = load_msg("geometry_msgs/msg/Quaternion")().model_dump()
    assert quaternion == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    # A pose is at the origin with no rotation; an odometry's covariance is 36 zeros.
    pose = load_msg("geometry_msgs/msg/PoseStamped")().model_dump()["pose"]
    assert pose["orientation"]["w"] == 1.0
    odometry = load_msg("nav_msgs/msg/Odometry")().model_dump()
    assert odometry["pose"]["covariance"] == [0.0] * 36
    assert len(load_msg("unique_identifier_msgs/msg/UUID")().model_dump()["uuid"]) == 16


def load_msg(name: str) -> type[Message]:
    return srvwire.load_message(name, SEARCH_PATH)


# --- key field lists, as ROS 2 defines them ---------------------------------------------------

# (type as written, field name, default or None)
Field: TypeAlias = tuple[str, str, Value | None]

HEADER: Field = ("std_msgs/Header", "header", None)
FIELDS: dict[str, list[Field]] = {
    "geometry_msgs/msg/Twist": [
        ("geometry_msgs/Vector3", "linear", None),
        ("geometry_msgs/Vector3", "angular", None),
    ],
    "geometry_msgs/msg/PoseStamped": [HEADER, ("geometry_msgs/Pose", "pose", None)],
    "nav_msgs/msg/Odometry": [
        HEADER,
        ("string", "child_frame_id", None),
        ("geometry_msgs/PoseWithCovariance", "pose", None),
        ("geometry_msgs/TwistWithCovariance", "twist", None),
    ],
    "geometry_msgs/msg/PoseWithCovariance": [
        ("geometry_msgs/Pose", "pose", None),
        ("float64[36]", "covariance", None),
    ],
    "sensor_msgs/msg/JointState": [
        HEADER,
        ("string[]", "name", None),
        ("float64[]", "position", None),
        ("float64[]", "velocity", None),
        ("float64[]", "effort", None),
    ],
    "sensor_msgs/msg/Image": [
        HEADER,
        ("uint32", "height", None),
        ("uint32", "width", None),
        ("string", "encoding", None),
        ("uint8", "is_bigendian", None),
        ("uint32", "step", None),
        ("uint8[]", "data", None),
    ],
    "sensor_msgs/msg/LaserScan": [
        HEADER,
        ("float32", "angle_min", None),
        ("float32", "angle_max", None),
        ("float32", "angle_increment", None),
        ("float32", "time_increment", None),
        ("float32", "scan_time", None),
        ("float32", "range_min", None),
        ("float32", "range_max", None),
        ("float32[]", "ranges", None),
        ("float32[]", "intensities", None),
    ],
    "nav_msgs/msg/OccupancyGrid": [
        HEADER,
        ("nav_msgs/MapMetaData", "info", None),
        ("int8[]", "data", None),
    ],
    "nav_msgs/msg/MapMetaData": [
        ("builtin_interfaces/Time", "map_load_time", None),
        ("float32", "resolution", None),
        ("uint32", "width", None),
        ("uint32", "height", None),
        ("geometry_msgs/Pose", "origin", None),
    ],
    "action_msgs/msg/GoalStatus": [
        ("action_msgs/GoalInfo", "goal_info", None),
        ("int8", "status", None),
    ],
    "action_msgs/msg/GoalInfo": [
        ("unique_identifier_msgs/UUID", "goal_id", None),
        ("builtin_interfaces/Time", "stamp", None),
    ],
    "unique_identifier_msgs/msg/UUID": [("uint8[16]", "uuid", None)],
    "diagnostic_msgs/msg/DiagnosticStatus": [
        ("byte", "level", None),
        ("string", "name", None),
        ("string", "message", None),
        ("string", "hardware_id", None),
        ("diagnostic_msgs/KeyValue[]", "values", None),
    ],
    "trajectory_msgs/msg/JointTrajectoryPoint": [
        ("float64[]", "positions", None),
        ("float64[]", "velocities", None),
        ("float64[]", "accelerations", None),
        ("float64[]", "effort", None),
        ("builtin_interfaces/Duration", "time_from_start", None),
    ],
    "sensor_msgs/msg/NavSatStatus": [("int8", "status", -2), ("uint16", "service", None)],
    "geometry_msgs/msg/Quaternion": [
        ("float64", "x", 0),
        ("float64", "y", 0),
        ("float64", "z", 0),
        ("float64", "w", 1),
    ],
}

# The parts of services and actions, in file order.
PART_FIELDS: dict[str, list[list[Field]]] = {
    "example_interfaces/action/Fibonacci": [
        [("int32", "order", None)],
        [("int32[]", "sequence", None)],
        [("int32[]", "sequence", None)],
    ],
    "std_srvs/srv/Trigger": [[], [("bool", "success", None), ("string", "message", None)]],
    "std_srvs/srv/SetBool": [
        [("bool", "data", None)],
        [("bool", "success", None), ("string", "message", None)],
    ],
    "example_interfaces/srv/AddTwoInts": [
        [("int64", "a", None), ("int64", "b", None)],
        [("int64", "sum", None)],
    ],
    "action_msgs/srv/CancelGoal": [
        [("action_msgs/GoalInfo", "goal_info", None)],
        [("int8", "return_code", None), ("action_msgs/GoalInfo[]", "goals_canceling", None)],
    ],
    "sensor_msgs/srv/SetCameraInfo": [
        [("sensor_msgs/CameraInfo", "camera_info", None)],
        [("bool", "success", None), ("string", "status_message", None)],
    ],
    "nav_msgs/srv/GetPlan": [
        [
            ("geometry_msgs/PoseStamped", "start", None),
            ("geometry_msgs/PoseStamped", "goal", None),
            ("float32", "tolerance", None),
        ],
        [("nav_msgs/Path", "plan", None)],
    ],
}


def described(fields: tuple[FieldSpec, ...]) -> list[Field]:
    return [(str(field.type), field.name, field.default) for field in fields]


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_key_messages_have_ros_fields(name: str) -> None:
    assert described(load_msg(name).spec.fields) == FIELDS[name]


@pytest.mark.parametrize("name", sorted(PART_FIELDS))
def test_key_services_and_actions_have_ros_fields(name: str) -> None:
    specs: list[MessageSpec] = [part.spec for part in parts_of(load(name))]
    assert [described(spec.fields) for spec in specs] == PART_FIELDS[name]


def test_a_fibonacci_goal_result_and_feedback_hold_what_they_are_given() -> None:
    fibonacci = srvwire.load_action("example_interfaces/action/Fibonacci", SEARCH_PATH)
    assert fibonacci.Goal(order=5).model_dump() == {"order": 5}
    assert fibonacci.Feedback(sequence=[0, 1, 1]).model_dump() == {"sequence": [0, 1, 1]}
    result = fibonacci.Result.model_validate_json('{"sequence": [0, 1, 1, 2, 3]}')
    assert result.model_dump() == {"sequence": [0, 1, 1, 2, 3]}


# --- what docs/interfaces.md says of the bundle -----------------------------------------------


def documented_packages() -> dict[str, dict[str, list[str]]]:
    """Read the list under "Bundled packages": each package's types, by kind."""
    page = (ROOT / "docs" / "interfaces.md").read_text(encoding="utf-8")
    section = page.split("\n## Bundled packages\n", 1)[1].split("\n### ", 1)[0]
    listed: dict[str, dict[str, list[str]]] = {}
    for item in re.findall(r"^\* `(\w+)`: (.*?)(?=^\* |\n\n)", section, re.M | re.S):
        package, text = item[0], " ".join(item[1].split())
        listed[package] = {
            kind: sorted(re.findall(r"\w+", found[0]))
            for kind, label in (("msg", "Messages"), ("srv", "Services"), ("action", "Actions"))
            if (found := re.findall(rf"{label}: ([\w, ]+)\.", text))
        }
    return listed


def test_the_docs_list_every_bundled_package_and_type() -> None:
    assert documented_packages() == EXPECTED


# --- a package of the same name hides the bundled one as a whole ------------------------------


def test_a_package_of_the_same_name_hides_the_whole_bundled_one(tmp_path: Path) -> None:
    twist = tmp_path / "geometry_msgs" / "msg" / "Twist.msg"
    twist.parent.mkdir(parents=True)
    twist.write_text("# Only a linear speed.\nfloat64 speed\n", encoding="utf-8")
    # A world of its own: this process already has the bundled Twist, a different definition.
    loader = InterfaceLoader([tmp_path, BUNDLE], use_default_path=False, types=TypeRegistry())
    assert loader.packages()["geometry_msgs"] == tmp_path / "geometry_msgs"
    assert loader.types("geometry_msgs") == ["geometry_msgs/msg/Twist"]
    assert list(loader.load_message("geometry_msgs/msg/Twist").model_fields) == ["speed"]
    with pytest.raises(InterfaceNotFoundError):
        loader.load_message("geometry_msgs/msg/Pose")
    with pytest.raises(InterfaceError):  # it nests a geometry_msgs type the overlay lacks
        loader.load_message("nav_msgs/msg/Odometry")
    # The other bundled packages are still there, whole.
    assert loader.load_message("std_msgs/msg/Header").type_name == "std_msgs/msg/Header"
    assert loader.types("sensor_msgs") == InterfaceLoader(SEARCH_PATH).types("sensor_msgs")
