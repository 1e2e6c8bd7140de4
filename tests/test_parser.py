"""The interface-file parser: data-driven valid and invalid cases, ROS 2's corpus, properties.

Invalid inputs live in ``tests/data/invalid/<Case>.<suffix>`` with the exact error beside them in
``<Case>.err``; the test parses them from inside ``tests/data`` so the path in the message reads
``invalid/<Case>.<suffix>`` wherever the checkout is. Case files are CamelCase because the file's
stem is the interface name, and a snake_case stem is itself an error (see ``bad_name.msg``).
Their package is inferred from the folder two levels up, which is ``data``.

Valid inputs live in ``tests/data/valid/demo_pkg/{msg,srv,action}/`` with the expected structure
in ``<Name>.expected.yaml``, written by hand.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings, strategies as st

import ros_corpus
from srvwire.errors import InterfaceSyntaxError
from srvwire.idl import (
    INTEGER_RANGES,
    PRIMITIVE_TYPES,
    STRING_TYPES,
    ActionSpec,
    ArrayKind,
    ConstantSpec,
    FieldSpec,
    MessageSpec,
    Scalar,
    ServiceSpec,
    TypeSpec,
    Value,
)
from srvwire.parser import (
    parse_action,
    parse_file,
    parse_message,
    parse_service,
    split_comment,
)
from support import DATA, ros_test_interfaces

INVALID = DATA / "invalid"
VALID = DATA / "valid"
SUFFIXES = (".msg", ".srv", ".action")
Spec = MessageSpec | ServiceSpec | ActionSpec


def parts(spec: Spec) -> list[MessageSpec]:
    if isinstance(spec, ServiceSpec):
        return [spec.request, spec.response]
    if isinstance(spec, ActionSpec):
        return [spec.goal, spec.result, spec.feedback]
    return [spec]


def parse_text(suffix: str, text: str, package: str, name: str) -> Spec:
    if suffix == ".srv":
        return parse_service(text, package, name)
    if suffix == ".action":
        return parse_action(text, package, name)
    return parse_message(text, package, name)


# --- invalid files: one per error, message asserted verbatim -----------------------------------

INVALID_CASES = sorted(p for p in INVALID.iterdir() if p.suffix != ".err")


def test_every_invalid_case_has_its_error_and_every_error_its_case() -> None:
    sources = {p.stem for p in INVALID_CASES}
    errors = {p.stem for p in INVALID.glob("*.err")}
    assert sources == errors
    assert len(sources) == len(INVALID_CASES), "two cases share a stem"
    assert len(INVALID_CASES) >= 40


@pytest.mark.parametrize("source", INVALID_CASES, ids=lambda p: p.name)
def test_invalid_file(source: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    expected = source.with_suffix(".err").read_text(encoding="utf-8").removesuffix("\n")
    monkeypatch.chdir(DATA)
    with pytest.raises(InterfaceSyntaxError) as info:
        parse_file(source.relative_to(DATA))
    assert str(info.value) == expected
    assert info.value.path == f"invalid/{source.name}"


# --- valid files: the structure expected beside each --------------------------------------------

VALID_CASES = sorted(p for p in VALID.rglob("*") if p.suffix in SUFFIXES)


def describe_part(message: MessageSpec) -> dict[str, Any]:
    def entry(spec: FieldSpec | ConstantSpec) -> dict[str, Any]:
        out: dict[str, Any] = {"line": spec.line, "type": str(spec.type), "name": spec.name}
        value = spec.default if isinstance(spec, FieldSpec) else spec.value
        if value is not None:
            key = "default" if isinstance(spec, FieldSpec) else "value"
            out[key] = list(value) if isinstance(value, tuple) else value
        if spec.doc:
            out["doc"] = spec.doc
        return out

    return {
        "name": message.name,
        "doc": message.doc,
        "fields": [entry(f) for f in message.fields],
        "constants": [entry(c) for c in message.constants],
    }


def describe(spec: Spec) -> dict[str, Any]:
    if isinstance(spec, ServiceSpec):
        return {
            "kind": "service",
            "name": spec.name,
            "request": describe_part(spec.request),
            "response": describe_part(spec.response),
        }
    if isinstance(spec, ActionSpec):
        return {
            "kind": "action",
            "name": spec.name,
            "goal": describe_part(spec.goal),
            "result": describe_part(spec.result),
            "feedback": describe_part(spec.feedback),
        }
    return {"kind": "message", **describe_part(spec)}


def test_every_valid_case_has_its_expectation() -> None:
    expectations = sorted(VALID.rglob("*.expected.yaml"))
    assert [p.name.removesuffix(".expected.yaml") for p in expectations] == [
        p.stem for p in sorted(VALID_CASES, key=lambda p: p.with_suffix(".expected.yaml"))
    ]
    assert {p.parent.name for p in VALID_CASES} == {"msg", "srv", "action"}


@pytest.mark.parametrize("source", VALID_CASES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_valid_file(source: Path) -> None:
    expected_path = source.with_name(f"{source.stem}.expected.yaml")
    expected = yaml.safe_load(expected_path.read_text(encoding="utf-8"))
    spec = parse_file(source)
    assert describe(spec) == expected
    assert spec.package == "demo_pkg"
    assert spec.path == str(source)
    assert all(part.package == "demo_pkg" and part.path == str(source) for part in parts(spec))


@pytest.mark.parametrize("source", VALID_CASES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_line_endings_do_not_change_the_result(source: Path) -> None:
    text = source.read_bytes().decode("utf-8").removeprefix("\ufeff")
    lf = text.replace("\r\n", "\n").replace("\r", "\n")
    results = [
        describe(parse_text(source.suffix, variant, "demo_pkg", source.stem))
        for variant in (lf, lf.replace("\n", "\r\n"), lf.replace("\n", "\r"), "\ufeff" + lf)
    ]
    assert results[1:] == results[:1] * 3


# --- line breaks, as ROS 2 cuts lines (str.splitlines) ------------------------------------------

# What rosidl_adapter reads from "# Section one<BREAK>int32 hidden\nint32 x\n", for each character
# str.splitlines breaks at besides \r and \n: two fields, the first on line 2.
SPLITLINES_ONLY = "\v\f\x1c\x1d\x1e\x85\u2028\u2029"


@pytest.mark.parametrize("brk", SPLITLINES_ONLY, ids=repr)
def test_a_line_break_of_splitlines_in_a_comment_ends_the_comment(brk: str) -> None:
    spec = parse_message(f"# Section one{brk}int32 hidden\nint32 x\n", "pkg", "Msg")
    assert [(field.name, field.line) for field in spec.fields] == [("hidden", 2), ("x", 3)]
    # rosidl refuses what follows such a break in a trailing comment; so does srvwire, and the
    # error counts the lines as rosidl does.
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        parse_message(f"int32 a{brk}int32 b # c{brk}d\n", "pkg", "Msg", path="Msg.msg")
    assert str(excinfo.value) == (
        "Msg.msg:3:1: unknown type 'd': expected a primitive type such as 'int32' or a message "
        "type such as 'Point' or 'geometry_msgs/Point'"
    )
    # Inside a quoted string the break ends the line, and the string with it, as in rosidl.
    with pytest.raises(InterfaceSyntaxError, match=r"^<string>:1:10: unterminated string"):
        parse_message(f'string s "x{brk}y"\n', "pkg", "Msg")


def test_a_bad_byte_is_placed_by_the_lines_splitlines_cuts(tmp_path: Path) -> None:
    source = tmp_path / "pkg" / "msg" / "Bad.msg"
    source.parent.mkdir(parents=True)
    source.write_bytes("# a\fint32 a\u2028int32 b".encode() + b"\xff\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        parse_file(source)
    assert (excinfo.value.line, excinfo.value.column) == (3, 8)


def test_float32s_maximum_as_commonly_written_is_a_float32_constant_and_default() -> None:
    # rosidl accepts these; each rounds to the largest float32. From 2**128 - 2**103 on, a value
    # rounds to infinity, and srvwire refuses it.
    for written in ("3.4028235e38", "3.40282347e+38", "-3.4028235e38"):
        spec = parse_message(f"float32 X={written}\nfloat32 x {written}\n", "pkg", "Msg")
        assert spec.constants[0].value == spec.fields[0].default == float(written)
    for beyond in ("3.4028235677973366e38", "-3.40282356779733661637539395458142568448e38"):
        with pytest.raises(InterfaceSyntaxError) as excinfo:
            parse_message(f"float32 X={beyond}\n", "pkg", "Msg")
        assert str(excinfo.value) == f"<string>:1:11: constant {beyond} is out of range for float32"
        with pytest.raises(InterfaceSyntaxError, match=r"^<string>:1:11: default .* out of range"):
            parse_message(f"float32 x {beyond}\n", "pkg", "Msg")


def test_a_tab_reads_as_a_space_as_in_ros_2() -> None:
    # rosidl_adapter replaces every tab with a space before it parses, so a tab in a string
    # default or constant is a space to a ROS 2 node; it is to srvwire too.
    text = (
        'string s "a\tb"\nstring t a\tb\nstring[] u ["a\tb", c\td]\n'
        'string S="a\tb"\nstring T=a\tb\n# one\ttab\nint32\tx\t# and\tanother\n'
    )
    spec = parse_message(text, "pkg", "Msg")
    assert [(field.name, field.default) for field in spec.fields] == [
        ("s", "a b"),
        ("t", "a b"),
        ("u", ("a b", "c d")),
        ("x", None),
    ]
    assert [(constant.name, constant.value) for constant in spec.constants] == [
        ("S", "a b"),
        ("T", "a b"),
    ]
    assert spec.fields[-1].doc == "one tab\nand another"
    assert spec.text == text  # the text is kept as written
    with pytest.raises(InterfaceSyntaxError, match=r"^<string>:1:9: 'b' is not a valid int32"):
        parse_message("int32\tx\tb\n", "pkg", "Msg")  # a tab is still one column


# --- the public API's promises ------------------------------------------------------------------


def test_service_keeps_its_text_and_names_its_parts() -> None:
    text = "int64 a\nint64 b\n---\nint64 sum\n"
    spec = parse_service(text, "demo_pkg", "AddTwoInts", path="AddTwoInts.srv")
    assert spec.text == text
    assert spec.type_name == "demo_pkg/srv/AddTwoInts"
    assert (spec.request.name, spec.response.name) == ("AddTwoInts_Request", "AddTwoInts_Response")
    assert spec.request.type_name == "demo_pkg/msg/AddTwoInts_Request"
    assert spec.path == spec.request.path == spec.response.path == "AddTwoInts.srv"


def test_action_keeps_its_text_and_names_its_parts() -> None:
    text = "int32 order\n---\nint32[] sequence\n---\nint32[] partial\n"
    spec = parse_action(text, "demo_pkg", "Fibonacci")
    assert spec.text == text
    assert [p.name for p in parts(spec)] == [
        "Fibonacci_Goal",
        "Fibonacci_Result",
        "Fibonacci_Feedback",
    ]


def test_parse_file_reads_the_service_text_without_its_bom(tmp_path: Path) -> None:
    source = tmp_path / "my_pkg" / "srv" / "Ping.srv"
    source.parent.mkdir(parents=True)
    source.write_bytes(b"\xef\xbb\xbfstring msg\r\n---\r\nstring reply\r\n")
    spec = parse_file(source)
    assert isinstance(spec, ServiceSpec)
    assert spec.package == "my_pkg"
    assert spec.text == "string msg\r\n---\r\nstring reply\r\n"


def test_parse_file_takes_an_explicit_package() -> None:
    spec = parse_file(VALID / "demo_pkg" / "msg" / "Nested.msg", package="other_pkg")
    assert spec.package == "other_pkg"
    assert isinstance(spec, MessageSpec)
    assert spec.fields[0].type == TypeSpec("Point", "other_pkg")


def test_parse_file_lets_a_missing_file_raise_oserror(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        parse_file(tmp_path / "pkg" / "msg" / "Missing.msg")


def test_error_without_a_path_names_a_string() -> None:
    with pytest.raises(InterfaceSyntaxError) as info:
        parse_message("int32 x\nint32 Y_\n", "demo_pkg", "Thing")
    error = info.value
    assert (error.path, error.line, error.column) == (None, 2, 7)
    assert str(error).startswith("<string>:2:7: 'Y_' is an invalid field name")


@pytest.mark.parametrize(
    ("call", "expected"),
    [
        (
            lambda: parse_message("", "Demo", "Thing", path="x.msg"),
            "x.msg:1:1: 'Demo' is an invalid package name",
        ),
        (
            lambda: parse_service("---", "demo_pkg", "add_two_ints", path="x.srv"),
            "x.srv:1:1: 'add_two_ints' is an invalid service name",
        ),
        (
            lambda: parse_action("---\n---", "demo_pkg", "Fib_1", path="x.action"),
            "x.action:1:1: 'Fib_1' is an invalid action name",
        ),
    ],
)
def test_names_passed_in_are_checked(call: Any, expected: str) -> None:
    with pytest.raises(InterfaceSyntaxError) as info:
        call()
    assert str(info.value).startswith(expected + ": ")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("int64 x " + "9" * 5000, "<string>:1:9: default 9999"),
        ("int8 X=-0x" + "f" * 5000, "<string>:1:8: constant -0xffff"),
        ("int32[" + "9" * 5000 + "] x", "<string>:1:7: an array size must be at most 4294967295"),
    ],
)
def test_huge_numbers_are_errors_not_crashes(text: str, expected: str) -> None:
    # Python refuses to convert more than 4300 decimal digits with a bare ValueError.
    with pytest.raises(InterfaceSyntaxError) as info:
        parse_message(text, "demo_pkg", "Huge")
    assert str(info.value).startswith(expected)


def test_leading_zeros_are_not_a_crash_either() -> None:
    spec = parse_message("int32[" + "0" * 5000 + "3] x [1, 2, 0" + "0" * 5000 + "3]", "p", "Z")
    assert spec.fields[0].default == (1, 2, 3)


def test_an_empty_message_and_a_comment_only_message() -> None:
    assert parse_message("", "demo_pkg", "Nothing") == MessageSpec("demo_pkg", "Nothing")
    spec = parse_message("  \t\n# just this\n#\n", "demo_pkg", "Nothing")
    assert (spec.fields, spec.constants, spec.doc) == ((), (), "just this")


# --- ROS 2's own test interfaces ----------------------------------------------------------------

# The counts, defaults and constants come from ros_corpus (test_conformance checks them too); the
# field types below are checked here only.
ROS_TYPES: dict[str, dict[str, str]] = {
    "msg/MultiNested.msg": {
        "array_of_arrays": "test_msgs/Arrays[3]",
        "bounded_sequence_of_bounded_sequences": "test_msgs/BoundedSequences[<=3]",
        "unbounded_sequence_of_unbounded_sequences": "test_msgs/UnboundedSequences[]",
    },
    "msg/Strings.msg": {"bounded_string_value_default1": "string<=22"},
    "msg/WStrings.msg": {"bounded_sequence_of_wstrings": "wstring[<=3]"},
}


def test_the_ros_corpus_is_listed_completely() -> None:
    folder = ros_test_interfaces()
    found = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.suffix in SUFFIXES}
    assert found == set(ros_corpus.COUNTS)


@pytest.mark.parametrize("relative", sorted(ros_corpus.COUNTS))
def test_ros_corpus_file(relative: str) -> None:
    spec = parse_file(ros_test_interfaces() / relative, package="test_msgs")
    counts = [
        (len(p.fields), len(p.constants), sum(f.default is not None for f in p.fields))
        for p in parts(spec)
    ]
    assert counts == ros_corpus.COUNTS[relative]
    for part, written in zip(parts(spec), ros_corpus.defaults_by_part(relative), strict=True):
        defaults = {f.name: f.default for f in part.fields if f.default is not None}
        assert defaults == written
        constants = {c.name: c.value for c in part.constants}
        assert constants == ros_corpus.CONSTANTS.get(relative, {})
        types = {f.name: str(f.type) for f in part.fields}
        assert types | ROS_TYPES.get(relative, {}) == types


# --- properties ---------------------------------------------------------------------------------

GRAMMAR_PIECES = st.sampled_from(
    [
        *sorted(PRIMITIVE_TYPES),
        *" \t\n\r#\"'\\[]<=,-./_\ufeff\xa0\x0c",
        "\r\n",
        "---",
        "Point",
        "pkg/",
        "msg/",
        "0x",
        "0b1",
        "1",
        "-7",
        ".5",
        "e9",
        "300",
        "true",
        "inf",
        "x",
        "name",
        "MAX",
    ]
)
RANDOM_TEXT = st.lists(GRAMMAR_PIECES | st.text(max_size=3), max_size=40).map("".join)


@settings(deadline=None, max_examples=300)
@given(text=RANDOM_TEXT, suffix=st.sampled_from(SUFFIXES))
def test_random_text_raises_nothing_but_syntax_errors(text: str, suffix: str) -> None:
    try:
        parse_text(suffix, text, "fuzz_pkg", "Fuzz")
    except InterfaceSyntaxError as error:
        rendered = str(error)
        assert "\n" not in rendered and "\r" not in rendered
        lines = (text.removeprefix("\ufeff") + "\0").splitlines()  # as ROS 2 cuts them
        lines[-1] = lines[-1][:-1]
        assert 1 <= error.line <= len(lines)
        assert 1 <= error.column <= len(lines[error.line - 1]) + 1


FIELD_NAMES = st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True).filter(
    lambda s: "__" not in s and not s.endswith("_")
)
CONSTANT_NAMES = st.from_regex(r"[A-Z](?:[A-Z0-9_]?[A-Z0-9]){0,4}", fullmatch=True)
TYPE_NAMES = st.from_regex(r"[A-Z][A-Za-z0-9]{0,6}", fullmatch=True)
PACKAGES = st.sampled_from(["demo_pkg", "geometry_msgs", "std_msgs"])
DOC_LINES = st.text(
    st.characters(exclude_categories=("Cc", "Cs", "Zl", "Zp")), min_size=1, max_size=20
).filter(lambda s: s == s.strip() and s != "")
FLOAT32_MAX = 3.4028234663852886e38
LINE_BREAKS = "\r\n\v\f\x1c\x1d\x1e\x85\u2028\u2029"  # where str.splitlines cuts


def values_of(type_: TypeSpec) -> st.SearchStrategy[Scalar]:
    name = type_.name
    if name == "bool":
        return st.booleans()
    if name in INTEGER_RANGES:
        low, high = INTEGER_RANGES[name]
        return st.integers(low, high)
    if name == "float32":
        return st.floats(-FLOAT32_MAX, FLOAT32_MAX)
    if name == "float64":
        return st.floats(allow_nan=False, allow_infinity=False)
    # No line break, and no tab, which reads as a space.
    characters = st.characters(exclude_characters=LINE_BREAKS + "\t", exclude_categories=["Cs"])
    return st.text(characters, max_size=type_.string_bound or 12).filter(
        lambda s: not s.endswith("\\")
    )


@st.composite
def types(draw: st.DrawFn, *, scalar_primitive: bool = False) -> TypeSpec:
    if scalar_primitive or draw(st.integers(0, 5)):
        name, package = draw(st.sampled_from(sorted(PRIMITIVE_TYPES))), None
    else:
        name, package = draw(TYPE_NAMES), draw(PACKAGES)
    if scalar_primitive:
        return TypeSpec(name)
    bound = draw(st.none() | st.integers(1, 9)) if name in STRING_TYPES else None
    array = draw(st.sampled_from(list(ArrayKind)))
    size = draw(st.integers(1, 4)) if array in (ArrayKind.FIXED, ArrayKind.BOUNDED) else None
    return TypeSpec(name, package, bound, array, size)


@st.composite
def fields(draw: st.DrawFn) -> FieldSpec:
    type_ = draw(types())
    default: Value | None = None
    if type_.is_primitive and draw(st.booleans()):
        if type_.is_array:
            fixed = type_.array is ArrayKind.FIXED
            low = type_.size if fixed and type_.size else 0
            high = type_.size if type_.size else 4
            elements = draw(st.lists(values_of(type_.element), min_size=low, max_size=high))
            default = tuple(elements)
        else:
            default = draw(values_of(type_))
    doc = draw(st.just("") | DOC_LINES)
    return FieldSpec(type_, draw(FIELD_NAMES), default, doc)


@st.composite
def constants(draw: st.DrawFn) -> ConstantSpec:
    type_ = draw(types(scalar_primitive=True))
    doc = draw(st.just("") | DOC_LINES)
    return ConstantSpec(type_, draw(CONSTANT_NAMES), draw(values_of(type_)), doc)


@st.composite
def messages(draw: st.DrawFn, name: str = "Random") -> MessageSpec:
    return MessageSpec(
        "demo_pkg",
        name,
        tuple(draw(st.lists(fields(), max_size=6, unique_by=lambda f: f.name))),
        tuple(draw(st.lists(constants(), max_size=4, unique_by=lambda c: c.name))),
        "\n".join(draw(st.lists(DOC_LINES, max_size=3))),
    )


def render_value(value: Value) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(render_value(v) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace('"', '\\"') + '"'
    return repr(value)


def render(message: MessageSpec) -> str:
    """Write a message back as interface-file text (the test's own tiny renderer)."""
    lines = [f"# {line}" for line in message.doc.split("\n")] + [""] if message.doc else []
    for constant in message.constants:
        doc = f"  # {constant.doc}" if constant.doc else ""
        lines.append(f"{constant.type} {constant.name}={render_value(constant.value)}{doc}")
    for field in message.fields:
        default = "" if field.default is None else f" {render_value(field.default)}"
        doc = f"  # {field.doc}" if field.doc else ""
        lines.append(f"{field.type} {field.name}{default}{doc}")
    return "\n".join(lines) + "\n"


def without_lines(message: MessageSpec) -> MessageSpec:
    return dataclasses.replace(
        message,
        fields=tuple(dataclasses.replace(f, line=0) for f in message.fields),
        constants=tuple(dataclasses.replace(c, line=0) for c in message.constants),
    )


@settings(deadline=None, max_examples=200)
@given(message=messages())
def test_rendering_a_message_and_parsing_it_gives_it_back(message: MessageSpec) -> None:
    parsed = parse_message(render(message), "demo_pkg", "Random")
    assert without_lines(parsed) == message


@settings(deadline=None, max_examples=50)
@given(request=messages("Random_Request"), response=messages("Random_Response"))
def test_rendering_a_service_and_parsing_it_gives_it_back(
    request: MessageSpec, response: MessageSpec
) -> None:
    spec = parse_service(f"{render(request)}---\n{render(response)}", "demo_pkg", "Random")
    assert (without_lines(spec.request), without_lines(spec.response)) == (request, response)


# --- comments -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("line", "code", "comment"),
    [
        ("", "", None),
        (" \t", " \t", None),
        ("int32 x", "int32 x", None),
        ("int32 x  # doc", "int32 x  ", " doc"),
        ("int32 x#doc", "int32 x", "doc"),
        ("# only a comment", "", " only a comment"),
        ("  --- # the response", "  --- ", " the response"),
        ("---", "---", None),
        ('string s "a # b"  # c', 'string s "a # b"  ', " c"),
        ('string S="a # b"# c', 'string S="a # b"', " c"),
        ("string[] s ['a # b', \"#\"] # c", "string[] s ['a # b', \"#\"] ", " c"),
        ('string s "a \\" # b"', 'string s "a \\" # b"', None),
        # Quotes open a string only where a value starts; elsewhere they are text.
        ('string s a "b # c"', 'string s a "b ', ' c"'),
        ("int32 x 1 # it's", "int32 x 1 ", " it's"),
    ],
)
def test_split_comment(line: str, code: str, comment: str | None) -> None:
    assert split_comment(line) == (code, comment)


def test_split_comment_of_a_line_that_does_not_parse() -> None:
    with pytest.raises(InterfaceSyntaxError) as info:
        split_comment("int32 2bad  # doc")
    assert str(info.value).startswith("<string>:1:7: '2bad' is an invalid field name: ")


def without_docs(message: MessageSpec) -> MessageSpec:
    return dataclasses.replace(
        message,
        doc="",
        fields=tuple(dataclasses.replace(f, doc="") for f in message.fields),
        constants=tuple(dataclasses.replace(c, doc="") for c in message.constants),
    )


def strip_comments(text: str) -> str:
    """Cut every comment from ``text`` with split_comment, checking that nothing else goes."""
    codes = []
    for line in re.split(r"\r\n|\r|\n", text):
        code, comment = split_comment(line)
        assert (code if comment is None else f"{code}#{comment}") == line
        codes.append(code)
    return "\n".join(codes)


@pytest.mark.parametrize("source", VALID_CASES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_stripping_comments_from_a_valid_file_keeps_its_declarations(source: Path) -> None:
    text = source.read_bytes().decode("utf-8").removeprefix("\ufeff")
    original = parse_text(source.suffix, text, "demo_pkg", source.stem)
    stripped = parse_text(source.suffix, strip_comments(text), "demo_pkg", source.stem)
    assert [without_docs(p) for p in parts(stripped)] == [without_docs(p) for p in parts(original)]


@settings(deadline=None, max_examples=200)
@given(message=messages())
def test_stripping_comments_from_a_rendered_message_keeps_its_declarations(
    message: MessageSpec,
) -> None:
    parsed = parse_message(strip_comments(render(message)), "demo_pkg", "Random")
    assert without_lines(parsed) == without_docs(message)
