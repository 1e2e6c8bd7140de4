"""One class per type: what counts as the same definition, conflicts, failures, adoption."""

from __future__ import annotations

import pytest

from srvwire.errors import InterfaceConflictError
from srvwire.models import build_message, build_service
from srvwire.parser import parse_message, parse_service
from srvwire.typeregistry import (
    TypeRegistry,
    definition_lines,
    fingerprint,
    first_difference,
    full_definition,
    process_types,
)

POINT = "# A point.\nfloat64 x  # along x\nfloat64 y 1.5\nuint8 ORIGIN=0\n"


def test_comments_blank_lines_and_paths_are_not_the_definition() -> None:
    plain = parse_message("uint8 ORIGIN=0\n\nfloat64 x\nfloat64 y 1.5\n", "geo", "Point")
    commented = parse_message(POINT, "geo", "Point", path="/somewhere/geo/msg/Point.msg")
    assert definition_lines(plain) == definition_lines(commented)
    assert definition_lines(commented) == ("uint8 ORIGIN=0", "float64 x", "float64 y 1.5")


def test_a_service_is_its_parts_split_by_a_line() -> None:
    spec = parse_service("geo/Point a  # first\n---\nbool ok\n", "geo", "Check")
    assert definition_lines(spec) == ("geo/Point a", "---", "bool ok")


def test_the_same_definition_is_the_same_class_and_builds_once() -> None:
    types = TypeRegistry()
    built: list[type] = []

    def build(text: str) -> type:
        cls = build_message(parse_message(text, "geo", "Point"))
        built.append(cls)
        return cls

    first = types.intern(parse_message(POINT, "geo", "Point"), "a.msg", lambda: build(POINT))
    plain = "uint8 ORIGIN=0\nfloat64 x\nfloat64 y 1.5\n"
    again = types.intern(parse_message(plain, "geo", "Point"), "b.msg", lambda: build(plain))
    assert again is first and built == [first]
    recorded = types.get("geo/msg/Point")
    assert recorded is not None and (recorded.cls, recorded.source) == (first, "a.msg")


def test_another_definition_under_the_same_name_names_both_sources() -> None:
    types = TypeRegistry()
    spec = parse_message(POINT, "geo", "Point")
    types.intern(spec, "/ws/geo/msg/Point.msg", lambda: build_message(spec))
    other = parse_message("uint8 ORIGIN=0\nfloat64 x\n", "geo", "Point")
    with pytest.raises(InterfaceConflictError) as excinfo:
        types.intern(other, "server ws://robot:8765", lambda: build_message(other))
    assert str(excinfo.value) == (
        "two different definitions of geo/msg/Point: /ws/geo/msg/Point.msg and server "
        "ws://robot:8765 (declaration 3: 'float64 y 1.5' against nothing); a type name has one "
        "definition per process"
    )
    assert (excinfo.value.first, excinfo.value.second) == (
        "/ws/geo/msg/Point.msg",
        "server ws://robot:8765",
    )


def test_a_definition_that_changed_at_its_source_says_so() -> None:
    """A server that was upgraded describes a type anew: the source is the same, and the
    error says it changed rather than naming it twice."""
    types = TypeRegistry()
    spec = parse_message(POINT, "geo", "Point")
    types.intern(spec, "server ws://robot:8765", lambda: build_message(spec))
    other = parse_message("uint8 ORIGIN=0\nfloat64 x\n", "geo", "Point")
    with pytest.raises(InterfaceConflictError) as excinfo:
        types.intern(other, "server ws://robot:8765", lambda: build_message(other))
    assert str(excinfo.value) == (
        "two different definitions of geo/msg/Point from server ws://robot:8765: it changed "
        "since this process built its class (declaration 3: 'float64 y 1.5' against nothing); "
        "a type name has one definition per process: restart the process to use the new one"
    )


def test_a_failed_build_records_nothing() -> None:
    types = TypeRegistry()
    spec = parse_message(POINT, "geo", "Point")

    def fail() -> type:
        raise RuntimeError("broken")

    with pytest.raises(RuntimeError):
        types.intern(spec, "a.msg", fail)
    assert types.get("geo/msg/Point") is None
    assert types.intern(spec, "a.msg", lambda: build_message(spec)) is not None


def test_a_builder_that_records_the_name_itself_is_checked() -> None:
    # A loader interns what it finds; the caller's definition must agree with it.
    types = TypeRegistry()
    local = parse_message("int32 a\n", "geo", "Thing")
    remote = parse_message("int64 a\n", "geo", "Thing")

    def load_locally() -> type:
        return types.intern(local, "/ws/geo/msg/Thing.msg", lambda: build_message(local))

    with pytest.raises(InterfaceConflictError) as excinfo:
        types.intern(remote, "server ws://robot:8765", load_locally)
    assert (excinfo.value.first, excinfo.value.second) == (
        "/ws/geo/msg/Thing.msg",
        "server ws://robot:8765",
    )
    same = parse_message("int32 a  # the same\n", "geo", "Thing")
    assert types.intern(same, "server ws://robot:8765", load_locally) is load_locally()


def test_adopt_records_a_class_declared_elsewhere_once() -> None:
    types = TypeRegistry()
    spec = parse_service("int32 a\n---\nint32 b\n", "geo", "Twice")
    declared = build_service(spec)
    assert types.adopt(declared, "module app.types") is declared
    assert types.adopt(build_service(spec), "module other") is declared
    with pytest.raises(TypeError, match="has no interface spec"):
        types.adopt(int, "nowhere")


def test_the_process_has_one_registry() -> None:
    assert process_types() is process_types()
    assert repr(TypeRegistry()) == "<TypeRegistry of 0 types>"


def speed_service(limits: str) -> type:
    Limits = build_message(parse_message(limits, "fp", "Limits"))
    spec = parse_service("Limits limits\nLimits[] more\n---\nbool ok\n", "fp", "SetSpeed")
    return build_service(spec, lambda type_: Limits)


def test_a_fingerprint_covers_the_service_and_every_message_it_nests() -> None:
    plain = speed_service("float32 max_speed\n")
    assert full_definition(plain) == {
        "fp/srv/SetSpeed": ("fp/Limits limits", "fp/Limits[] more", "---", "bool ok"),
        "fp/msg/Limits": ("float32 max_speed",),
    }
    commented = speed_service("# Limits.\nfloat32 max_speed  # m/s\n")
    other = speed_service("float64 max_speed\n")
    same, differs = (fingerprint(full_definition(s) or {}) for s in (commented, other))
    assert fingerprint(full_definition(plain) or {}) == same != differs
    assert len(same) == 16 and int(same, 16) >= 0
    assert first_difference(full_definition(plain) or {}, full_definition(other) or {}) == (
        "fp/msg/Limits",
        "declaration 1: 'float32 max_speed' against 'float64 max_speed'",
    )
    assert first_difference({"a": ("x",)}, {"a": ("x",), "b": ()}) == (
        "b",
        "only the second defines it",
    )


def test_a_class_written_by_hand_has_no_definition() -> None:
    class Handmade:
        pass

    assert full_definition(Handmade) is None
