"""ROS 2's own test interfaces load as the package ``test_msgs``, meaning what they mean in ROS 2.

The corpus (``shared/ros_test_interfaces``, see ``support.ros_test_interfaces``) is copied into
a temporary search-path folder as ``test_msgs``, the package ROS 2 ships these files in. The
counts and values checked here were read off the files by hand and are kept in ``ros_corpus``,
so a parser or model that drops, adds or alters a field, constant or default fails here. Random
valid instances of every message, and of every part of every service and action, must also
survive JSON unchanged.
"""

from __future__ import annotations

import json
import math
import shutil
from typing import Any

import pytest
from hypothesis import given, settings, strategies as st
from pydantic import BaseModel

import ros_corpus
from srvwire.idl import INTEGER_RANGES, STRING_TYPES, ArrayKind, MessageSpec, TypeSpec
from srvwire.loader import InterfaceLoader
from srvwire.models import FLOAT32_MAX, Message
from support import ros_test_interfaces


def type_name(path: str) -> str:
    """The type in the file at ``path``: ``msg/Arrays.msg`` holds ``test_msgs/msg/Arrays``."""
    return "test_msgs/" + path.rsplit(".", 1)[0]


# ros_corpus's facts, keyed by the type each file holds rather than by the file's path.
COUNTS = {type_name(path): counts for path, counts in ros_corpus.COUNTS.items()}
DEFAULTS = {type_name(path): ros_corpus.defaults_by_part(path) for path in ros_corpus.COUNTS}
CONSTANTS = {type_name(path): values for path, values in ros_corpus.CONSTANTS.items()}
TYPES = sorted(COUNTS)


@pytest.fixture(scope="module")
def loader(tmp_path_factory: pytest.TempPathFactory) -> InterfaceLoader:
    # A copy rather than a symlink: it works wherever the tests run, Windows included.
    root = tmp_path_factory.mktemp("ros_corpus")
    shutil.copytree(ros_test_interfaces(), root / "test_msgs")
    return InterfaceLoader([root], use_default_path=False)


def spec_parts(loader: InterfaceLoader, name: str) -> list[MessageSpec]:
    if "/msg/" in name:
        return [loader.message_spec(name)]
    if "/srv/" in name:
        service = loader.service_spec(name)
        return [service.request, service.response]
    action = loader.action_spec(name)
    return [action.goal, action.result, action.feedback]


def class_parts(loader: InterfaceLoader, name: str) -> list[type[Message]]:
    if "/msg/" in name:
        return [loader.load_message(name)]
    if "/srv/" in name:
        service = loader.load_service(name)
        return [service.Request, service.Response]
    action = loader.load_action(name)
    return [action.Goal, action.Result, action.Feedback]


def typed(value: Any) -> Any:
    """``value`` with the type of every scalar, so ``1 == 1.0 == True`` no longer holds."""
    if isinstance(value, list | tuple | bytes):
        return [typed(item) for item in value]
    return (type(value).__name__, value)


def test_the_corpus_holds_exactly_these_files(loader: InterfaceLoader) -> None:
    assert loader.types() == TYPES
    assert list(loader.packages()) == ["test_msgs"]


@pytest.mark.parametrize("name", TYPES)
def test_fields_constants_and_defaults_are_counted_as_in_ros(
    loader: InterfaceLoader, name: str
) -> None:
    parts = spec_parts(loader, name)
    counted = [
        (
            len(part.fields),
            len(part.constants),
            sum(field.default is not None for field in part.fields),
        )
        for part in parts
    ]
    assert counted == COUNTS[name]
    classes = class_parts(loader, name)
    assert [len(cls.model_fields) for cls in classes] == [count[0] for count in COUNTS[name]]


@pytest.mark.parametrize("name", TYPES)
def test_defaults_are_the_values_written(loader: InterfaceLoader, name: str) -> None:
    expected = DEFAULTS[name]
    specs = spec_parts(loader, name)
    instances = [cls() for cls in class_parts(loader, name)]
    for spec, instance, defaults in zip(specs, instances, expected, strict=True):
        written = {field.name: field.default for field in spec.fields if field.default is not None}
        assert {key: typed(value) for key, value in written.items()} == {
            key: typed(value) for key, value in defaults.items()
        }
        held = {key: typed(getattr(instance, key)) for key in defaults}
        assert held == {key: typed(value) for key, value in defaults.items()}


@pytest.mark.parametrize("name", sorted(CONSTANTS))
def test_constants_are_class_attributes(loader: InterfaceLoader, name: str) -> None:
    cls = loader.load_message(name)
    expected = CONSTANTS[name]
    spec = loader.message_spec(name)
    assert {constant.name: typed(constant.value) for constant in spec.constants} == {
        key: typed(value) for key, value in expected.items()
    }
    assert {key: typed(getattr(cls, key)) for key in expected} == {
        key: typed(value) for key, value in expected.items()
    }


@pytest.mark.parametrize("name", TYPES)
def test_a_default_instance_survives_json(loader: InterfaceLoader, name: str) -> None:
    for cls in class_parts(loader, name):
        instance = cls()
        text = instance.model_dump_json()
        again = cls.model_validate_json(text)
        assert again == instance
        assert again.model_dump_json() == text


# --- random valid instances ----------------------------------------------------------------------

# Each part of each file, named as ROS 2 names it: ("test_msgs/srv/Arrays", 1) is Arrays_Response.
PART_NAMES = {
    "msg": [""],
    "srv": ["_Request", "_Response"],
    "action": ["_Goal", "_Result", "_Feedback"],
}
PARTS = [(name, index) for name in TYPES for index in range(len(COUNTS[name]))]
PART_IDS = [name + PART_NAMES[name.split("/")[1]][index] for name, index in PARTS]

# Unbounded arrays get at most this many elements: MultiNested nests them three levels deep.
UNBOUNDED_MAX = 2
NON_FINITE = st.sampled_from([math.inf, -math.inf, math.nan])


def scalar_values(type_: TypeSpec) -> st.SearchStrategy[Any]:
    """Every value a primitive scalar field accepts, non-finite floats included."""
    if type_.name == "bool":
        return st.booleans()
    if type_.name in INTEGER_RANGES:
        low, high = INTEGER_RANGES[type_.name]
        return st.integers(low, high)
    if type_.name == "float32":
        # Any double within the float32 range (models check the range, they do not round), inf,
        # -inf and nan.
        return st.floats(-FLOAT32_MAX, FLOAT32_MAX) | NON_FINITE
    if type_.name == "float64":
        return st.floats()  # every double, inf, -inf and nan included
    assert type_.name in STRING_TYPES, type_
    bound = type_.string_bound  # bounds and max_size both count code points
    # Hypothesis leaves out lone surrogates: they are text Python holds but UTF-8 cannot encode.
    if bound is None:
        return st.text()
    # Text exactly at the bound is rare among short texts, and it is where a bound check errs.
    return st.text(max_size=bound) | st.text(min_size=bound, max_size=bound)


def field_values(loader: InterfaceLoader, type_: TypeSpec) -> st.SearchStrategy[Any]:
    """Every value a field of type ``type_`` accepts, as plain Python data (dicts for messages)."""
    if type_.is_primitive:
        element = scalar_values(type_.element)
    else:
        element = payloads(loader, loader.message_spec(type_.qualified_name))
    if type_.array is ArrayKind.FIXED:
        return st.lists(element, min_size=type_.size or 0, max_size=type_.size)
    if type_.array is ArrayKind.BOUNDED:
        return st.lists(element, max_size=type_.size)
    if type_.array is ArrayKind.UNBOUNDED:
        return st.lists(element, max_size=UNBOUNDED_MAX)
    return element


def payloads(loader: InterfaceLoader, spec: MessageSpec) -> st.SearchStrategy[dict[str, Any]]:
    """Valid payloads of ``spec``, derived from the spec alone and keyed by .srv names.

    Every field is optional (a missing one takes its default), which also keeps MultiNested's
    payloads, a dozen messages of dozens of values each, within Hypothesis's size budget.
    """
    return st.fixed_dictionaries(
        {}, optional={field.name: field_values(loader, field.type) for field in spec.fields}
    )


def same(a: Any, b: Any) -> bool:
    """``a == b`` for messages and their values, but NaN equals NaN, and types and signs count.

    ``1``, ``1.0`` and ``True`` differ, and so do ``0.0`` and ``-0.0``.
    """
    if type(a) is not type(b):
        return False
    if isinstance(a, BaseModel):
        return all(same(getattr(a, key), getattr(b, key)) for key in type(a).model_fields)
    if isinstance(a, list):
        return len(a) == len(b) and all(map(same, a, b))
    if isinstance(a, float):
        if math.isnan(a):
            return math.isnan(b)
        return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)
    return bool(a == b)


@pytest.mark.parametrize(("name", "index"), PARTS, ids=PART_IDS)
def test_random_valid_instances_survive_json(
    loader: InterfaceLoader, name: str, index: int
) -> None:
    cls = class_parts(loader, name)[index]

    @settings(max_examples=30, deadline=None)
    @given(payloads(loader, cls.spec))
    def round_trip(payload: dict[str, Any]) -> None:
        instance = cls.model_validate(payload)
        text = instance.model_dump_json()
        again = cls.model_validate_json(text)
        assert same(again, instance)
        assert again.model_dump_json() == text
        # The other way to JSON: plain data, written and read by Python's own json module.
        data = json.loads(json.dumps(instance.model_dump(mode="json")))
        assert same(cls.model_validate(data), instance)

    round_trip()
