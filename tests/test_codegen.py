"""Static generation (srvwire.codegen): generated classes behave exactly like built ones."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pydantic
import pytest

from srvwire.codegen import generate_module, generate_modules, write_module
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
from srvwire.loader import InterfaceLoader, bundled_interfaces
from srvwire.models import (
    FLOAT32_MAX,
    Action,
    Message,
    Service,
    build_action,
    build_message,
    build_service,
    validation_errors,
)
from srvwire.parser import parse_file, parse_message, parse_service
from support import ROOT, import_each_first, ros_test_interfaces, write_package

Spec = MessageSpec | ServiceSpec | ActionSpec

# --- a hand-built interface set that exercises every corner of the writer -------------------------


def t(name: str, package: str | None = None, **kwargs: Any) -> TypeSpec:
    return TypeSpec(name, package, **kwargs)


def arr(name: str, kind: ArrayKind, size: int | None = None, **kwargs: Any) -> TypeSpec:
    return TypeSpec(name, kwargs.pop("package", None), array=kind, size=size, **kwargs)


FIXED, BOUNDED, UNBOUNDED = ArrayKind.FIXED, ArrayKind.BOUNDED, ArrayKind.UNBOUNDED

POINT = MessageSpec(
    "geo",
    "Point",
    (
        FieldSpec(t("float64"), "x", doc="Metres east."),
        FieldSpec(t("float64"), "y", doc="Metres north."),
    ),
    doc="A point on the map.\n\n  Indented detail, kept as written.",
    path="/somewhere/geo/msg/Point.msg",
)
POSE = MessageSpec(
    "geo",
    "Pose",
    (FieldSpec(t("Point", "geo"), "position"), FieldSpec(t("float32"), "heading")),
)
STRING = MessageSpec("std", "String", (FieldSpec(t("string"), "data"),))  # named like a helper
INT32 = MessageSpec("std", "Int32", (FieldSpec(t("int32"), "data", 7),))
ODD = MessageSpec(
    "demo",
    "Odd",
    (
        FieldSpec(t("int32"), "from", doc='Where it "starts".'),
        FieldSpec(arr("int32", UNBOUNDED), "list"),
        FieldSpec(t("string"), "str"),
        FieldSpec(t("bool"), "bool", True),
        FieldSpec(t("int64"), "copy", -(2**63)),
        FieldSpec(t("uint64"), "model_config", 2**64 - 1),
        FieldSpec(arr("uint8", BOUNDED, 4), "bytes", (1, 2)),
        FieldSpec(arr("byte", FIXED, 2), "pair_of_bytes"),
        FieldSpec(arr("float32", FIXED, 2), "gains", (1.5, -0.25)),
        FieldSpec(arr("string", BOUNDED, 2, string_bound=3), "tags", ("a", "bc")),
        FieldSpec(t("wstring", string_bound=5), "label", "ハロー"),
        FieldSpec(arr("Point", FIXED, 2, package="geo"), "corners"),
        FieldSpec(arr("Point", BOUNDED, 3, package="geo"), "route"),
        FieldSpec(t("Pose", "geo"), "pose", doc="Back\\slash and\ttab."),
        FieldSpec(arr("float64", UNBOUNDED), "samples", (0.5,)),
        FieldSpec(t("String", "std"), "note"),
        FieldSpec(t("char"), "char", 65),
    ),
    (
        ConstantSpec(t("float64"), "INF", math.inf),
        ConstantSpec(t("float32"), "LIMIT", FLOAT32_MAX),
        ConstantSpec(t("int8"), "LOW", -128),
        ConstantSpec(t("string"), "GREETING", 'say "hi"\n'),
        ConstantSpec(t("bool"), "ON", False),
        ConstantSpec(t("float64"), "WHOLE", 2),
    ),
    doc='Odd names, "quotes", and a backslash \\ in the doc.',
)
MOVE = ServiceSpec(
    "demo",
    "Move",
    MessageSpec(
        "demo",
        "Move_Request",
        (FieldSpec(t("Pose", "geo"), "target"), FieldSpec(t("float32"), "speed", 0.5)),
        doc="Where to go.",
    ),
    MessageSpec(
        "demo", "Move_Response", (FieldSpec(t("bool"), "ok"), FieldSpec(t("string"), "message"))
    ),
    text="# Where to go.\ngeo/Pose target\nfloat32 speed 0.5\n---\nbool ok\nstring message\n",
    path="/somewhere/demo/srv/Move.srv",
)
WALK = ActionSpec(
    "demo",
    "Walk",
    MessageSpec("demo", "Walk_Goal", (FieldSpec(t("uint16"), "steps"),)),
    MessageSpec(
        "demo", "Walk_Result", (FieldSpec(arr("Point", UNBOUNDED, package="geo"), "path"),)
    ),
    MessageSpec("demo", "Walk_Feedback", (FieldSpec(t("uint16"), "done"),)),
    text="uint16 steps\n---\ngeo/Point[] path\n---\nuint16 done\n",
)
SENTENCE = "The quick brown fox jumps over the lazy dog, again and again, until it tires. "
AWKWARD = MessageSpec(  # text too long for a line, and quotes, everywhere a string can go
    "demo",
    "Awkward",
    (
        FieldSpec(t("string"), "long_default", SENTENCE * 2, doc=SENTENCE * 2),
        FieldSpec(t("string"), "unbroken", "x" * 120, doc="y" * 130),
        FieldSpec(t("string"), "quoted", "He said \"hi\" and 'bye'. " * 5),
        FieldSpec(t("string"), "escaped", "tab\there, bell\x07, line\u2028separator " * 3),
        FieldSpec(arr("string", BOUNDED, 5, string_bound=200), "words", ("x" * 95, "", SENTENCE)),
        FieldSpec(arr("float64", UNBOUNDED), "sevenths", tuple(i / 7 for i in range(20))),
        FieldSpec(
            arr("uint8", FIXED, 3), "a_field_name_long_enough_to_push_the_annotation", (1, 2, 3)
        ),
        FieldSpec(t("float64"), "large", 1e16, doc="Written 1e16, as ruff spells it."),
    ),
    (
        ConstantSpec(t("string"), "LONG_TEXT", SENTENCE * 3),
        ConstantSpec(t("string"), "QUOTE", '"'),
        ConstantSpec(t("string"), "APOSTROPHE", "it's"),
    ),
    doc=f'{SENTENCE * 2}\n\n  An indented line.\nA quote at the end: "',
)
SPECS: dict[str, MessageSpec] = {s.type_name: s for s in (POINT, POSE, STRING, INT32, ODD, AWKWARD)}


def resolve_spec(type_: TypeSpec) -> MessageSpec:
    assert not type_.is_array
    return SPECS[type_.qualified_name]


def built_classes(specs: list[Spec]) -> dict[str, Any]:
    """Build ``specs`` with srvwire.models; key each class by the name it gets in the module."""
    messages: dict[str, type[Message]] = {}

    def resolve(type_: TypeSpec) -> type[Message]:
        name = type_.qualified_name
        if name not in messages:
            messages[name] = build_message(resolve_spec(type_), resolve)
        return messages[name]

    out: dict[str, Any] = {}
    for spec in specs:
        if isinstance(spec, MessageSpec):
            out[spec.name] = resolve(t(spec.name, spec.package))
        elif isinstance(spec, ServiceSpec):
            out[spec.name] = build_service(spec, resolve)
        else:
            out[spec.name] = build_action(spec, resolve)
    for cls in messages.values():
        out.setdefault(cls.__name__, cls)
    return out


def load(path: Path, name: str, monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    module_spec = importlib.util.spec_from_file_location(name, path)
    assert module_spec is not None and module_spec.loader is not None
    module = importlib.util.module_from_spec(module_spec)
    monkeypatch.setitem(sys.modules, name, module)
    module_spec.loader.exec_module(module)
    return module


def generated(
    specs: list[Spec], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> ModuleType:
    path = write_module(tmp_path / f"{name}.py", specs, resolve_spec=resolve_spec)
    return load(path, name, monkeypatch)


# --- comparing a generated class with a built one -----------------------------------------------


def without_paths(spec: Any) -> Any:
    changes = {"path": None}
    for part in ("request", "response", "goal", "result", "feedback"):
        if hasattr(spec, part):
            changes[part] = without_paths(getattr(spec, part))
    return dataclasses.replace(spec, **changes)


def probes(spec: MessageSpec) -> Iterator[Any]:
    """Inputs to validate: good and bad values for every field, and some whole-object mistakes."""
    yield {}
    yield []
    yield "text"
    yield {"no_such_field": 1}
    for field in spec.fields:
        type_ = field.type
        element: list[Any]
        if type_.name in INTEGER_RANGES:
            low, high = INTEGER_RANGES[type_.name]
            element = [low, high, low - 1, high + 1, True, 1.0, "1"]
        elif type_.name == "float32":
            element = [FLOAT32_MAX, 3, math.inf, 1e39, "1.0", None]
        elif type_.name == "float64":
            element = [1e308, -3, False, "x"]
        elif type_.name == "bool":
            element = [True, 1, "true"]
        elif type_.name in ("string", "wstring"):
            element = ["", "abc", "abcdef", "ハローハロー", 5]
        else:
            element = [{}, {"x": 1}, {"x": "far"}, {"bogus": 1}, 5, {"position": {"y": None}}]
        if not type_.is_array:
            values = element
        else:
            values = [[], element[:1], element[:1] * 2, element[:1] * 3, element[:1] * 5, "AQID"]
            values += [[e] for e in element] + [element[:1] * ((type_.size or 1) - 1)]
        for value in values:
            yield {field.name: value}


def outcome(cls: type[Message], data: Any) -> Any:
    try:
        return cls.model_validate(data).model_dump_json()
    except pydantic.ValidationError as exc:
        return validation_errors(exc)


def outcome_json(cls: type[Message], text: str) -> Any:
    try:
        return cls.model_validate_json(text).model_dump_json()
    except pydantic.ValidationError as exc:
        return validation_errors(exc)


def assert_same_message(
    made: type[Message], built: type[Message], *, same_name: bool = True
) -> None:
    assert issubclass(made, Message)
    if same_name:
        assert made.__name__ == built.__name__
    assert made.type_name == built.type_name
    assert without_paths(made.spec) == without_paths(built.spec)
    assert made.__doc__ is not None or built.__doc__ is None
    made_fields, built_fields = made.model_fields, built.model_fields
    assert list(made_fields) == list(built_fields)
    for name, info in made_fields.items():
        other = built_fields[name]
        assert (info.alias, info.description) == (other.alias, other.description), name
    for constant in built.spec.constants:
        made_value, built_value = getattr(made, constant.name), getattr(built, constant.name)
        assert (type(made_value), made_value) == (type(built_value), built_value), constant.name
    assert made().model_dump_json() == built().model_dump_json()
    for mode in ("validation", "serialization"):
        made_schema = made.model_json_schema(mode=mode)
        assert made_schema == built.model_json_schema(mode=mode)

    def same(made_outcome: Any, built_outcome: Any) -> bool:
        # A renamed class names itself in "instance of ..." errors; nothing else may differ.
        renamed = json.dumps(made_outcome).replace(made.__name__, built.__name__)
        return renamed == json.dumps(built_outcome)

    for data in probes(built.spec):
        assert same(outcome(made, data), outcome(built, data)), data
        text = json.dumps(data)
        assert same(outcome_json(made, text), outcome_json(built, text)), text
    written = built().model_dump_json()
    assert made.model_validate_json(written).model_dump_json() == written


def assert_same(made: Any, built: Any, *, same_name: bool = True) -> None:
    if isinstance(built, type) and issubclass(built, Service):
        assert issubclass(made, Service)
        assert (made.type_name, made.text) == (built.type_name, built.text)
        assert without_paths(made.spec) == without_paths(built.spec)
        assert made.Request.spec is made.spec.request
        assert_same_message(made.Request, built.Request, same_name=same_name)
        assert_same_message(made.Response, built.Response, same_name=same_name)
    elif isinstance(built, type) and issubclass(built, Action):
        assert issubclass(made, Action)
        assert (made.type_name, made.text) == (built.type_name, built.text)
        assert without_paths(made.spec) == without_paths(built.spec)
        for part in ("Goal", "Result", "Feedback"):
            assert_same_message(getattr(made, part), getattr(built, part), same_name=same_name)
    else:
        assert_same_message(made, built, same_name=same_name)


# --- tests -------------------------------------------------------------------------------------


def test_generated_classes_match_built_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    specs: list[Spec] = [ODD, MOVE, WALK, INT32]
    module = generated(specs, tmp_path, monkeypatch, "demo_types")
    built = built_classes(specs)
    assert sorted(module.__all__) == sorted(
        [
            "Int32",
            "Move",
            "Move_Request",
            "Move_Response",
            "Odd",
            "Point",
            "Pose",
            "String",
            "Walk",
            "Walk_Feedback",
            "Walk_Goal",
            "Walk_Result",
        ]
    )
    for name, cls in built.items():
        assert_same(getattr(module, name), cls)


def test_generated_source_reads_like_hand_written_code(tmp_path: Path) -> None:
    source = generate_module([ODD, MOVE], resolve_spec=resolve_spec)
    assert "from srvwire.models import (" in source
    assert "import srvwire.models as _models\n" in source  # std/String is a class here
    assert 'class String(Message):\n    type_name: ClassVar[str] = "std/msg/String"\n' in source
    assert '    data: _models.String = ""\n' in source
    # Quotes as ruff format chooses them: double, unless that would need more escapes.
    assert (
        '    from_: Int32 = Field(default=0, alias="from", description=\'Where it "starts".\')\n'
        in source
    )
    assert (
        "    list: _builtins.list[Int32] = Field(default_factory=_builtins.list, fail_fast=True)\n"
        in source
    )
    assert (
        "    samples: _builtins.list[Float64] = Field("
        "default_factory=lambda: [0.5], fail_fast=True)" in source
    )
    assert "import builtins as _builtins\n" in source
    assert (
        '    bytes: Annotated[_builtins.bytes, Field(max_length=4), AcceptBase64] = b"\\x01\\x02"\n'
        in source
    )
    assert "= (\n        Field(default_factory=lambda: _builtins.bytes(2))\n    )\n" in source
    assert "    INF: ClassVar[float] = 1e999\n" in source
    assert "    WHOLE: ClassVar[float] = 2.0\n" in source
    assert "    Request: TypeAlias = Move_Request\n" in source
    assert (  # one literal, as ruff format joins the lines of a text that fits on one
        '    text: ClassVar[str] = (\n        "# Where to go.\\ngeo/Pose target\\nfloat32 speed 0.5'
        in source
    )
    assert "Move_Request.spec = Move.spec.request\n" in source
    assert "/somewhere" not in source
    assert source == generate_module([ODD, MOVE], resolve_spec=resolve_spec)
    assert not any(line.endswith(" ") for line in source.splitlines())
    compile(source, "generated.py", "exec")


def test_nested_types_come_from_the_interfaces_given_or_resolve_spec() -> None:
    with pytest.raises(InterfaceError) as info:
        generate_module([POSE])
    assert str(info.value) == (
        "Pose nests geo/msg/Point, which is not among the interfaces given, "
        "and no resolve_spec was given to find it"
    )
    asked: list[TypeSpec] = []

    def spy(type_: TypeSpec) -> MessageSpec:
        asked.append(type_)
        return resolve_spec(type_)

    with_point = generate_module([POINT, POSE], resolve_spec=spy)
    assert asked == []
    assert with_point.index("class Point(") < with_point.index("class Pose(")
    assert generate_module([POSE], resolve_spec=spy) == with_point.replace(
        "* ``geo/msg/Point``\n", ""
    )
    assert asked == [t("Point", "geo")]


def test_classes_can_be_given_instead_of_specs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    built = built_classes([MOVE, WALK])
    path = write_module(tmp_path / "from_classes.py", [built["Move"], built["Walk"]])
    module = load(path, "from_classes", monkeypatch)
    assert_same(module.Move, built["Move"])
    assert_same(module.Walk, built["Walk"])
    assert_same(module.Pose, built["Pose"])
    with pytest.raises(TypeError, match="generate_module takes specs or srvwire classes"):
        generate_module([42])  # type: ignore[list-item]


def test_a_message_that_contains_itself_is_refused() -> None:
    a = MessageSpec("x", "A", (FieldSpec(t("B", "x"), "b"),))
    b = MessageSpec("x", "B", (FieldSpec(arr("A", UNBOUNDED, package="x"), "a"),))
    with pytest.raises(InterfaceError) as info:
        generate_module([a, b])
    assert str(info.value) == "a message cannot contain itself: x/msg/A -> x/msg/B -> x/msg/A"


def test_a_constant_named_like_a_nested_class_is_refused() -> None:
    pi = MessageSpec("x", "PI", (FieldSpec(t("float64"), "value"),))
    holder = MessageSpec(
        "x",
        "Holder",
        (FieldSpec(t("PI", "x"), "pi"),),
        (ConstantSpec(t("int32"), "PI", 3),),
    )
    with pytest.raises(InterfaceError) as info:
        generate_module([pi, holder])
    assert str(info.value) == (
        "x/msg/Holder: constant PI has the name of the class of one of its fields, "
        "so the module cannot name both; rename one"
    )


def test_interfaces_sharing_a_name_are_prefixed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    other = MessageSpec("other", "Point", (FieldSpec(t("int8"), "q"),))
    uses_both = MessageSpec(
        "other", "Both", (FieldSpec(t("Point", "geo"), "a"), FieldSpec(t("Point", "other"), "b"))
    )
    SPECS[other.type_name] = other
    try:
        path = write_module(tmp_path / "clash.py", [uses_both, POINT], resolve_spec=resolve_spec)
        module = load(path, "clash", monkeypatch)
    finally:
        del SPECS[other.type_name]
    assert module.__all__ == ["Both", "geo_msg_Point", "other_msg_Point"]
    assert_same(module.geo_msg_Point, build_message(POINT), same_name=False)
    assert_same(module.other_msg_Point, build_message(other), same_name=False)
    assert module.other_msg_Point.model_json_schema()["title"] == "Point"
    assert module.Both().model_dump() == {"a": {"x": 0.0, "y": 0.0}, "b": {"q": 0}}


def test_write_module_writes_utf8(tmp_path: Path) -> None:
    path = write_module(tmp_path / "odd.py", [ODD], resolve_spec=resolve_spec, docstring="Odd.")
    assert path == tmp_path / "odd.py"
    text = path.read_text(encoding="utf-8")
    assert text.startswith('"""Odd."""\n\n')
    assert '"ハロー"' in text
    assert text == generate_module([ODD], resolve_spec=resolve_spec, docstring="Odd.")


def corpus_specs() -> list[Spec]:
    root = ros_test_interfaces()
    return [
        parse_file(path, "test_msgs")
        for kind in ("msg", "srv", "action")
        for path in sorted((root / kind).iterdir())
    ]


def test_the_ros_corpus_generates_the_same_classes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    specs = corpus_specs()
    messages = {s.type_name: s for s in specs if isinstance(s, MessageSpec)}
    built: dict[str, type[Message]] = {}

    def resolve(type_: TypeSpec) -> type[Message]:
        if type_.qualified_name not in built:
            built[type_.qualified_name] = build_message(messages[type_.qualified_name], resolve)
        return built[type_.qualified_name]

    def spec_of(type_: TypeSpec) -> MessageSpec:
        return messages[type_.qualified_name]

    # msg/Arrays and srv/Arrays share a name, so messages and each service go in separate modules.
    module = load(
        write_module(tmp_path / "corpus_msg.py", list(messages.values())), "corpus_msg", monkeypatch
    )
    for spec in messages.values():
        assert_same(getattr(module, spec.name), resolve(t(spec.name, "test_msgs")))
    for group in specs:
        if isinstance(group, MessageSpec):
            continue
        name = f"corpus_{group.name.lower()}"
        path = write_module(tmp_path / f"{name}.py", [group], resolve_spec=spec_of)
        made = load(path, name, monkeypatch)
        if isinstance(group, ServiceSpec):
            assert_same(getattr(made, group.name), build_service(group, resolve))
        else:
            assert_same(getattr(made, group.name), build_action(group, resolve))


def test_long_and_quoted_text_is_wrapped_without_changing_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    module = generated([AWKWARD], tmp_path, monkeypatch, "awkward")
    built = build_message(AWKWARD)
    assert_same(module.Awkward, built)
    assert module.Awkward.__doc__ == AWKWARD.doc  # too long for a docstring: assigned
    source = (tmp_path / "awkward.py").read_text(encoding="utf-8")
    assert max(len(line) for line in source.splitlines()) <= 100
    assert "    QUOTE: ClassVar[str] = '\"'\n" in source
    assert "    large: Float64 = Field(default=1e16, " in source


def ruff(tmp_path: Path, *arguments: str) -> subprocess.CompletedProcess[str]:
    # Run inside tmp_path: with --isolated, ruff takes the working directory as the project,
    # so srvwire is a third-party package there, as in a project that uses srvwire.
    return subprocess.run(
        [sys.executable, "-m", "ruff", *arguments, "--isolated", "."],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_generated_modules_are_ruff_clean_and_formatted(tmp_path: Path) -> None:
    loader = InterfaceLoader([bundled_interfaces()], use_default_path=False)
    kinds = {"msg": loader.message_spec, "srv": loader.service_spec, "action": loader.action_spec}

    def bundled_spec(type_: TypeSpec) -> MessageSpec:
        return loader.message_spec(type_.qualified_name)

    for package in loader.packages():
        specs = [kinds[name.split("/")[1]](name) for name in loader.types(package)]
        write_module(tmp_path / f"{package}.py", specs, resolve_spec=bundled_spec)
    corpus = corpus_specs()
    messages = {s.type_name: s for s in corpus if isinstance(s, MessageSpec)}
    write_module(tmp_path / "corpus_msg.py", list(messages.values()))
    for group in corpus:
        if not isinstance(group, MessageSpec):
            path = tmp_path / f"corpus_{group.type_name.replace('/', '_').lower()}.py"
            write_module(path, [group], resolve_spec=lambda type_: messages[type_.qualified_name])
    write_module(tmp_path / "demo_types.py", [ODD, MOVE, WALK, INT32], resolve_spec=resolve_spec)
    write_module(tmp_path / "awkward.py", [AWKWARD])
    # Class lines too long for one line: the Request's bases, the service's TypedService[...].
    long_names = [
        parse_service("int32 a\n---\nint32 b\n", "pkg", name)
        for name in ("SetSpeed", "A" * 30 + "Long", "B" * 38)
    ]
    write_module(tmp_path / "long_names.py", long_names)
    assert len(list(tmp_path.glob("*.py"))) >= len(loader.packages()) + 7

    strict = ruff(tmp_path, "check", "--select", "E,F,W,I,B,UP,ASYNC,RUF", "--line-length", "100")
    assert (strict.returncode, strict.stderr) == (0, ""), strict.stdout
    default_rules = ruff(tmp_path, "check")
    assert (default_rules.returncode, default_rules.stderr) == (0, ""), default_rules.stdout
    formatted = ruff(tmp_path, "format", "--check", "--line-length", "100")
    assert (formatted.returncode, formatted.stderr) == (0, ""), formatted.stdout


def test_a_generated_class_and_a_built_one_do_not_mix_but_their_dicts_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # docs/types.md, "Generated modules": two classes of one type; a dict of its fields goes
    # into either.
    module = generated([POINT, POSE], tmp_path, monkeypatch, "geo_mixed")
    built = built_classes([POINT, POSE])
    point = module.Point(x=1.0)
    with pytest.raises(pydantic.ValidationError) as caught:
        built["Pose"](position=point)
    assert [error["type"] for error in caught.value.errors()] == ["model_type"]
    assert "instance of Point" in str(caught.value)
    assert built["Pose"](position=point.model_dump()).position.x == 1.0
    assert module.Pose(position=built["Point"](y=2.0).model_dump()).position.y == 2.0


def test_all_is_ordered_as_ruffs_ruf022_orders_it(tmp_path: Path) -> None:
    # RUF022 sorts __all__ case-sensitively within each kind (isort sorts imports ignoring
    # case): IMUStatus before Imu ('M' < 'm'), DoThing before Do_Request ('T' < '_').
    specs = [
        parse_message("float64 x\n", "robot", "Imu"),
        parse_message("float64 x\n", "robot", "IMUStatus"),
        parse_message("int32 x\n", "robot", "DoThing"),
        parse_message("int32 x\n", "robot", "Int16"),
        parse_message("int32 x\n", "robot", "Int8"),
        parse_service("int32 a\n---\nint32 b\n", "robot", "Do"),
    ]
    write_module(tmp_path / "robot.py", specs)
    source = (tmp_path / "robot.py").read_text(encoding="utf-8")
    assert (
        '__all__ = ["Do", "DoThing", "Do_Request", "Do_Response", "IMUStatus", "Imu", "Int8", '
        '"Int16"]\n'
    ) in source
    strict = ruff(tmp_path, "check", "--select", "E,F,W,I,B,UP,ASYNC,RUF", "--line-length", "100")
    assert (strict.returncode, strict.stderr) == (0, ""), strict.stdout


def test_mypy_strict_sees_the_real_field_types(tmp_path: Path) -> None:
    write_module(tmp_path / "demo_types.py", [ODD, MOVE, WALK, INT32], resolve_spec=resolve_spec)
    (tmp_path / "good.py").write_text(
        "from demo_types import Int32, Move, Odd, Point, Pose, String, Walk\n"
        "\n"
        "\n"
        "def handle(request: Move.Request) -> Move.Response:\n"
        "    target: Pose = request.target\n"
        "    x: float = target.position.x\n"
        "    return Move.Response(ok=x > 0, message=str(x))\n"
        "\n"
        "\n"
        "odd = Odd(from_=3)\n"
        "values: list[int] = odd.list\n"
        "text: str = odd.str\n"
        "first: int = odd.from_\n"
        "flag: bool = odd.bool\n"
        "raw: bytes = odd.bytes\n"
        "corners: list[Point] = odd.corners\n"
        "gains: list[float] = odd.gains\n"
        "note: str = odd.note.data + String(data='hi').data\n"
        "number: int = Int32().data + Odd.LOW\n"
        "limit: float = Odd.INF\n"
        "steps: int = Walk.Goal(steps=3).steps\n"
        "path: list[Point] = Walk.Result().path\n"
        "name: str = Move.type_name + Odd.type_name + Move.text + Move.spec.name\n"
        "response: Move.Response = handle(Move.Request())\n",
        encoding="utf-8",
    )
    (tmp_path / "bad.py").write_text(
        "from demo_types import Move, Odd\n"
        "\n"
        "speed: str = Move.Request().speed\n"
        "missing = Odd().nonexistent\n",
        encoding="utf-8",
    )
    mypy = Path(sys.executable).parent / "mypy"
    result = subprocess.run(
        [
            str(mypy),
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--strict",
            "--cache-dir",
            str(tmp_path / ".mypy_cache"),
            "--no-error-summary",
            "--hide-error-context",
            "demo_types.py",
            "good.py",
            "bad.py",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.stderr == ""
    assert result.stdout.splitlines() == [
        'bad.py:3: error: Incompatible types in assignment (expression has type "float", '
        'variable has type "str")  [assignment]',
        'bad.py:4: error: "Odd" has no attribute "nonexistent"  [attr-defined]',
    ]


def test_generated_modules_import_without_warnings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = generated([ODD, MOVE, WALK], tmp_path, monkeypatch, "quiet_types")
    assert [str(w.message) for w in caught] == []
    odd = module.Odd.model_validate({"from": 1, "list": [1, 2], "bytes": "AQID"})
    assert (odd.from_, odd.list, odd.bytes) == (1, [1, 2], b"\x01\x02\x03")
    assert json.loads(odd.model_dump_json())["from"] == 1


def test_a_fixed_array_of_any_size_is_written_as_a_factory_of_its_zeros(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Neither writing the module nor importing it makes the 4294967295 values of a default.
    most = 2**32 - 1
    huge = MessageSpec(
        "big",
        "Huge",
        (
            FieldSpec(arr("int32", FIXED, most), "a"),
            FieldSpec(arr("uint8", FIXED, most), "b"),
            FieldSpec(arr("bool", FIXED, 2), "c"),
        ),
    )
    module = generated([huge], tmp_path, monkeypatch, "huge_types")
    source = (tmp_path / "huge_types.py").read_text(encoding="utf-8")
    assert f"default_factory=lambda: [0] * {most}," in source
    assert f"default_factory=lambda: bytes({most})," in source
    assert module.Huge.model_fields["c"].default_factory() == [False, False]
    built = build_message(huge)
    assert module.Huge.model_json_schema() == built.model_json_schema()


def test_without_pydantics_plugin_mypy_knows_a_renamed_field_by_its_file_name(
    tmp_path: Path,
) -> None:
    # What docs/types.md says: pydantic's dataclass_transform gives mypy the fields by alias,
    # so keywords and their types are checked, and `from_` is not a keyword mypy knows.
    write_module(tmp_path / "demo_types.py", [ODD], resolve_spec=resolve_spec)
    (tmp_path / "use.py").write_text(
        "from demo_types import Odd\n"
        "\n"
        "renamed = Odd(from_=3)\n"
        "wrong = Odd(char='A')\n"
        "read: Odd = Odd.model_validate({'from': 3})\n"
        "first: int = read.from_\n",
        encoding="utf-8",
    )
    (tmp_path / "mypy.ini").write_text("[mypy]\nstrict = True\n", encoding="utf-8")
    result = subprocess.run(
        [
            *(sys.executable, "-m", "mypy", "--config-file", "mypy.ini", "--cache-dir"),
            *(str(tmp_path / ".mypy_cache"), "--no-error-summary", "--hide-error-context"),
            "use.py",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.stderr == ""
    assert result.stdout.splitlines() == [
        'use.py:3: error: Unexpected keyword argument "from_" for "Odd"; did you mean "from"?  '
        "[call-arg]",
        'use.py:4: error: Argument "char" to "Odd" has incompatible type "str"; expected "int"  '
        "[arg-type]",
    ]


def test_packages_that_nest_each_other_share_one_module_and_import_in_any_order(
    tmp_path: Path,
) -> None:
    # a nests b, b nests c, c nests a (no message contains itself); d, outside the cycle,
    # nests a. a and c also both have a message named Point.
    a_point = MessageSpec("a", "Point", (FieldSpec(t("int8"), "x"),))
    a_outer = MessageSpec("a", "Outer", (FieldSpec(t("Mid", "b"), "mid"),))
    b_mid = MessageSpec("b", "Mid", (FieldSpec(t("Point", "c"), "point"),))
    c_point = MessageSpec("c", "Point", (FieldSpec(t("Point", "a"), "inner"),))
    d_top = MessageSpec("d", "Top", (FieldSpec(arr("Outer", FIXED, 2, package="a"), "outers"),))
    groups: dict[str, list[Spec]] = {
        "a": [a_outer, a_point],
        "b": [b_mid],
        "c": [c_point],
        "d": [d_top],
    }
    sources = generate_modules(groups)
    assert list(sources) == ["a", "b", "c", "d", "_a__b__c"]
    assert "from . import a\n" in sources["d"] and "\nclass " not in sources["a"]
    assert "a_msg_Point" in sources["_a__b__c"] and "Point: TypeAlias" in sources["c"]
    package = write_package(tmp_path, "cyc", sources)
    use = (
        "from cyc import a, b, c, d\n"
        "top = d.Top.model_validate({'outers': [{'mid': {'point': {'inner': {'x': 3}}}}, {}]})\n"
        "assert top.outers[0].mid.point.inner.x == 3 and type(top.outers[1].mid) is b.Mid\n"
        "assert c.Point.model_fields['inner'].annotation is a.Point is not c.Point\n"
        "assert a.Point.model_json_schema()['title'] == 'Point'\n"
    )
    import_each_first(tmp_path, "cyc", ("a", "b", "c", "d", "_a__b__c"), use)
    linted = ruff(package, "check", "--select", "E,F,W,I,B,UP,ASYNC,RUF", "--line-length", "100")
    assert linted.returncode == 0, linted.stdout
    formatted = ruff(package, "format", "--check", "--line-length", "100")
    assert formatted.returncode == 0, formatted.stdout


def test_a_cycle_through_a_message_not_asked_for_is_found_too(tmp_path: Path) -> None:
    # a/Top nests a/Hidden, found through resolve_spec, which nests b/Mid, which nests a/Leaf.
    hidden = MessageSpec("a", "Hidden", (FieldSpec(t("Mid", "b"), "mid"),))
    leaf = MessageSpec("a", "Leaf", (FieldSpec(t("int8"), "x", 5),))
    found = {spec.type_name: spec for spec in (hidden, leaf)}
    top = MessageSpec("a", "Top", (FieldSpec(t("Hidden", "a"), "hidden"),))
    mid = MessageSpec("b", "Mid", (FieldSpec(t("Leaf", "a"), "leaf"),))
    sources = generate_modules(
        {"a": [top], "b": [mid]}, resolve_spec=lambda type_: found[type_.qualified_name]
    )
    assert list(sources) == ["a", "b", "_a__b"]
    write_package(tmp_path, "hid", sources)
    use = "from hid import a, b\nassert a.Top().hidden.mid.leaf.x == 5 == b.Mid().leaf.x\n"
    import_each_first(tmp_path, "hid", ("a", "b"), use)


def test_modules_name_a_prefixed_class_of_another_module_as_that_module_does(
    tmp_path: Path,
) -> None:
    # p has a message and a service both named Arrays, so its module prefixes both classes. q
    # nests the message; a and b nest each other and a nests it too, from their shared module.
    arrays = MessageSpec("p", "Arrays", (FieldSpec(arr("int32", UNBOUNDED), "values"),))
    request = MessageSpec("p", "Arrays_Request", (FieldSpec(t("Arrays", "p"), "arrays"),))
    service = ServiceSpec("p", "Arrays", request, MessageSpec("p", "Arrays_Response", ()))
    uses = MessageSpec("q", "Uses", (FieldSpec(t("Arrays", "p"), "arrays"),))
    a_top = MessageSpec(
        "a", "Top", (FieldSpec(t("Mid", "b"), "mid"), FieldSpec(t("Arrays", "p"), "arrays"))
    )
    a_leaf = MessageSpec("a", "Leaf", (FieldSpec(t("int8"), "x", 5),))
    b_mid = MessageSpec("b", "Mid", (FieldSpec(t("Leaf", "a"), "leaf"),))
    groups: dict[str, list[Spec]] = {
        "q": [uses],
        "a": [a_top, a_leaf],
        "b": [b_mid],
        "p": [arrays, service],
    }
    sources = generate_modules(groups)
    assert list(sources) == ["q", "a", "b", "p", "_a__b"]
    assert "    arrays: p.p_msg_Arrays = " in sources["q"]
    assert "    arrays: p.p_msg_Arrays = " in sources["_a__b"]
    write_package(tmp_path, "named", sources)
    use = (
        "from named import a, p, q\n"
        "assert q.Uses.model_fields['arrays'].annotation is p.p_msg_Arrays\n"
        "assert a.Top.model_fields['arrays'].annotation is p.p_msg_Arrays\n"
        "assert q.Uses.model_validate({'arrays': {'values': [1, 2]}}).arrays.values == [1, 2]\n"
        "assert a.Top().mid.leaf.x == 5 and p.p_srv_Arrays.Request().arrays.values == []\n"
    )
    import_each_first(tmp_path, "named", ("q", "a", "b", "p", "_a__b"), use)


def test_a_message_nested_from_a_group_that_lacks_it_is_an_interface_error() -> None:
    point = MessageSpec("p", "Point", (FieldSpec(t("int8"), "x"),))
    uses = MessageSpec("q", "Uses", (FieldSpec(t("Other", "p"), "other"),))
    with pytest.raises(InterfaceError) as caught:
        generate_modules({"q": [uses], "p": [point]})
    assert str(caught.value) == (
        "p/msg/Other is nested but not among the interfaces of p's module; add it to the group of p"
    )
