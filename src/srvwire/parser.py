"""Parse ROS 2 interface files (``.msg``, ``.srv``, ``.action``) into :mod:`srvwire.idl` specs.

The grammar is the one ROS 2's reference parser (``rosidl_adapter``) reads; ``docs/interfaces.md``
describes it for users. Written as rules, one function per rule below (the tokens, ``comment``,
``size`` and the literals of a value, are read by :mod:`srvwire.scanner`)::

    file          = part { separator part }      .msg: 1 part, .srv: 2, .action: 3
    separator     = ws* "---" ws* [ comment ]
    line          = ws* [ comment | declaration ws* [ comment ] ]
    declaration   = type ws+ name ( ws* "=" ws* constant-value | [ ws+ default-value ] )
    type          = base-type [ "<=" size ] [ array-suffix ]
    base-type     = primitive | Type | package "/" Type | package "/msg/" Type
    array-suffix  = "[" [ [ "<=" ] size ] "]"
    default-value = array-value | scalar-value
    array-value   = "[" [ scalar-value { "," scalar-value } ] "]"
    comment       = "#" anything

Invariants
----------
* :mod:`srvwire.scanner` cuts the text into lines and reads the tokens of each (comments,
  sizes, quoted strings, literals) with a :class:`~srvwire.scanner.Cursor`, once, left to
  right; it keeps the rules of line breaks, positions, columns and whitespace.
* A ``#`` outside a quoted string starts a comment, even one glued to a token
  (``int32 x#doc``). Quotes are only recognised where a value starts, so comment stripping is
  quote-aware by construction; :func:`split_comment` finds a line's comment by reading the
  line with the same rules.
* Every problem is raised as :class:`~srvwire.errors.InterfaceSyntaxError`, pointing at the
  first character of the offending token; a missing separator is reported on the file's last
  line. No other exception leaves this module for any input text; only :func:`parse_file` may
  also raise :class:`OSError` when the file cannot be read.
* Nested types are not looked up: whether ``Point`` exists is the loader's business.

Decisions
---------
Where the reference parser is silent, crashes or surprises, this one decides as below.
``docs/interfaces.md`` states each for users: the differences from rosidl, with their reasons,
under "Where srvwire differs from rosidl", the rest in the section on each construct.

1. Indented declarations are allowed; an indented comment right below one continues its doc.
2. ``#`` inside a quoted string is part of the string.
3. A line is a constant only when the name after the type is followed by ``=``.
4. ``bool`` values are ``true``/``false``/``1``/``0`` in any case.
5. Integers are decimal, ``0x``, ``0o`` or ``0b`` with an optional sign, and no ``_``; floats
   are decimal with an optional exponent and never ``inf`` or ``nan``; ``float32`` values fit.
6. Inside quotes the only escape is a backslash before the enclosing quote.
7. After a quoted string or an array only whitespace and a comment may follow.
8. A ``string`` constant needs a value (``""``); constants are unbounded primitive scalars.
9. A separator may be indented and carry a comment; comments after it document the next part.
10. A blank line detaches a comment block from the declaration below it; the first block
    documents the message.
11. ``Header`` is a same-package type like any other; ``time`` and ``duration`` are unknown.
12. ``package/msg/Type`` is a long spelling of ``package/Type``.
13. Array sizes and string bounds are at most 2**32 - 1.
"""

from __future__ import annotations

import difflib
import os
import re
import textwrap
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Final

from srvwire.idl import (
    FLOAT_TYPES,
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
from srvwire.scanner import (
    CONSTANT_NAME,
    CONSTANT_RULE,
    FIELD_NAME,
    PACKAGE_NAME,
    QUOTES,
    SNAKE_RULE,
    TYPE_NAME,
    TYPE_RULE,
    WS,
    Cursor,
    bool_literal,
    comment,
    decode,
    end_of_line,
    file_error,
    float_literal,
    integer_literal,
    quoted_string,
    show,
    size,
    source_lines,
)

__all__ = ["parse_action", "parse_file", "parse_message", "parse_service", "split_comment"]

SEPARATOR: Final = re.compile(r"[ \t]*---[ \t]*(?:#.*)?")
NEAR_SEPARATOR: Final = re.compile(r"[ \t]*--[^#]*(?:#.*)?")  # a line that looks meant as one

# Type names from other languages, and the primitive an error message suggests instead.
FOREIGN_TYPES: Final = {
    "boolean": "bool",
    "double": "float64",
    "int": "int32",
    "integer": "int32",
    "long": "int64",
    "short": "int16",
    "str": "string",
    "unsigned": "uint32",
}
SUFFIXES: Final = {".msg": "message", ".srv": "service", ".action": "action"}


# --- public API -------------------------------------------------------------------------------


def parse_message(text: str, package: str, name: str, *, path: str | None = None) -> MessageSpec:
    """Parse the text of a ``.msg`` file into a :class:`MessageSpec` named ``package/name``."""
    _check_names(package, name, "message", path)
    lines = source_lines(text)
    ((first, part),) = _parts(lines, 1, path)
    return replace(_message(part, first, package, name, path), text=text)


def parse_service(text: str, package: str, name: str, *, path: str | None = None) -> ServiceSpec:
    """Parse the text of a ``.srv`` file: a request and a response split by one ``---`` line."""
    _check_names(package, name, "service", path)
    lines = source_lines(text)
    (first_a, request), (first_b, response) = _parts(lines, 2, path)
    return ServiceSpec(
        package,
        name,
        _message(request, first_a, package, f"{name}_Request", path),
        _message(response, first_b, package, f"{name}_Response", path),
        text=text,
        path=path,
    )


def parse_action(text: str, package: str, name: str, *, path: str | None = None) -> ActionSpec:
    """Parse the text of a ``.action`` file: goal, result and feedback split by ``---`` lines."""
    _check_names(package, name, "action", path)
    lines = source_lines(text)
    (first_a, goal), (first_b, result), (first_c, feedback) = _parts(lines, 3, path)
    return ActionSpec(
        package,
        name,
        _message(goal, first_a, package, f"{name}_Goal", path),
        _message(result, first_b, package, f"{name}_Result", path),
        _message(feedback, first_c, package, f"{name}_Feedback", path),
        text=text,
        path=path,
    )


def parse_file(
    path: str | os.PathLike[str], package: str | None = None
) -> MessageSpec | ServiceSpec | ActionSpec:
    """Parse an interface file; its suffix gives the kind and its stem the name.

    ``package`` defaults to the name of the folder two levels up, as in ROS's
    ``<package>/srv/Name.srv`` layout. The file is read as UTF-8 (a leading byte-order mark is
    dropped); bytes that are not UTF-8 are an :class:`InterfaceSyntaxError` too. Raises
    :class:`OSError` when the file cannot be read.
    """
    shown = os.fspath(path)
    file = Path(path)
    kind = SUFFIXES.get(file.suffix)
    if kind is None:
        raise file_error(
            f"unknown interface file suffix {show(file.suffix)}: expected .msg, .srv or .action",
            shown,
        )
    if package is None:
        package = Path(os.path.abspath(file)).parent.parent.name
        if not package:
            raise file_error("cannot tell the package from the file's path; pass package=", shown)
    text = decode(file.read_bytes(), shown).removeprefix("\ufeff")
    if kind == "message":
        return parse_message(text, package, file.stem, path=shown)
    if kind == "service":
        return parse_service(text, package, file.stem, path=shown)
    return parse_action(text, package, file.stem, path=shown)


def split_comment(line: str) -> tuple[str, str | None]:
    """Split one line of an interface file into its code and its comment, as the parser reads it.

    The comment is the text after the ``#`` that starts it, or None when there is none; the code
    is everything before that ``#``, whitespace included. A ``#`` inside a quoted value is part
    of the value (``string s "a # b"``). Raise :class:`InterfaceSyntaxError` (on line 1 of no
    file) when the line is not blank, a comment, a separator or a declaration.
    """
    cur = Cursor(line, 1, None)
    cur.skip_ws()
    if SEPARATOR.fullmatch(line):
        cur.take_until("#")  # past the dashes: what is left is a comment or nothing
    if cur.at_comment_or_end():
        found = None if cur.at_end() else comment(cur)
    else:
        # The package only qualifies the type names, which do not move a comment.
        spec, _ = _declaration(cur, package="")
        found = _trailing_comment(cur, spec)
    if found is None:
        return line, None
    return line[: len(line) - len(found) - 1], found


# --- files and parts --------------------------------------------------------------------------


def _check_names(package: str, name: str, kind: str, path: str | None) -> None:
    if not PACKAGE_NAME.fullmatch(package):
        raise file_error(f"{show(package)} is an invalid package name: {SNAKE_RULE}", path)
    if not TYPE_NAME.fullmatch(name):
        raise file_error(f"{show(name)} is an invalid {kind} name: {TYPE_RULE}", path)


def _parts(lines: list[str], count: int, path: str | None) -> list[tuple[int, list[str]]]:
    """Split the lines at separator lines into ``count`` parts of (first line number, lines)."""
    separators = [i for i, line in enumerate(lines) if SEPARATOR.fullmatch(line)]
    if len(separators) >= count:
        index = separators[count - 1]
        column = lines[index].index("-") + 1
        message = {
            1: "a message file has no '---' separator; only .srv and .action files have one",
            2: "a service has exactly one '---' separator; found a second one",
            3: "an action has exactly two '---' separators; found a third one",
        }[count]
        raise file_error(message, path, index + 1, column)
    if len(separators) < count - 1:
        for index, line in enumerate(lines):
            if NEAR_SEPARATOR.fullmatch(line) and index not in separators:
                found = show(line.split("#")[0].strip(WS))
                column = line.index("-") + 1
                raise file_error(
                    f"expected a separator line '---', found {found}", path, index + 1, column
                )
        found = "none" if not separators else "only one"
        message = {
            2: "a service needs a '---' line between the request and the response; found none",
            3: f"an action needs two '---' lines between goal, result and feedback; found {found}",
        }[count]
        raise file_error(message, path, len(lines), 1)
    bounds = [-1, *separators, len(lines)]
    return [(bounds[i] + 2, lines[bounds[i] + 1 : bounds[i + 1]]) for i in range(count)]


# --- a message: its lines, comments and declarations ------------------------------------------


@dataclass
class _Entry:
    spec: FieldSpec | ConstantSpec
    doc: list[str]


@dataclass
class _Message:
    """What has been read of one message so far, and where its comments go."""

    header_open: bool = True  # still inside the leading comment block (the message's doc)
    header: list[str] = field(default_factory=list)
    pending: list[str] = field(default_factory=list)  # comment lines for the next declaration
    last: _Entry | None = None  # the declaration an indented comment line would continue
    entries: list[_Entry] = field(default_factory=list)
    fields: dict[str, int] = field(default_factory=dict)  # name -> line
    constants: dict[str, int] = field(default_factory=dict)

    def blank(self) -> None:
        if self.header:
            self.header_open = False
        self.pending.clear()
        self.last = None

    def comment(self, text: str, indented: bool) -> None:
        if self.header_open:
            self.header.append(text)
        elif indented and self.last is not None:
            self.last.doc.append(text)
        else:
            self.pending.append(text)
            self.last = None

    def declare(self, spec: FieldSpec | ConstantSpec, trailing: str | None) -> None:
        self.header_open = False
        doc = [*self.pending] if trailing is None else [*self.pending, trailing]
        self.pending.clear()
        self.last = _Entry(spec, doc)
        self.entries.append(self.last)

    def build(self, package: str, name: str, path: str | None) -> MessageSpec:
        fields: list[FieldSpec] = []
        constants: list[ConstantSpec] = []
        for entry in self.entries:
            spec = replace(entry.spec, doc=_doc_text(entry.doc))
            if isinstance(spec, FieldSpec):
                fields.append(spec)
            else:
                constants.append(spec)
        header = _doc_text(self.header)
        return MessageSpec(package, name, tuple(fields), tuple(constants), header, path)


def _message(
    lines: list[str], first: int, package: str, name: str, path: str | None
) -> MessageSpec:
    message = _Message()
    for offset, text in enumerate(lines):
        _line(Cursor(text, first + offset, path), message, package)
    return message.build(package, name, path)


def _line(cur: Cursor, message: _Message, package: str) -> None:
    indent = cur.skip_ws()
    if cur.at_end():
        message.blank()
        return
    if cur.peek() == "#":
        message.comment(comment(cur), indented=indent > 0)
        return
    spec, name_pos = _declaration(cur, package)
    seen = message.fields if isinstance(spec, FieldSpec) else message.constants
    if spec.name in seen:
        kind = "field" if isinstance(spec, FieldSpec) else "constant"
        raise cur.error(
            f"duplicate {kind} name '{spec.name}': it was first declared on line {seen[spec.name]}",
            name_pos,
        )
    seen[spec.name] = cur.line
    message.declare(spec, _trailing_comment(cur, spec))


def _trailing_comment(cur: Cursor, spec: FieldSpec | ConstantSpec) -> str | None:
    """Read what may follow a declaration: whitespace, then an optional comment."""
    if isinstance(spec, ConstantSpec):
        what = "constant value"
    else:
        what = "field name" if spec.default is None else "default value"
    return end_of_line(cur, what)


def _doc_text(lines: list[str]) -> str:
    """Turn comment lines (text after the ``#``) into documentation text."""
    cleaned: list[str] = []
    for line in lines:
        text = line.lstrip("#").rstrip()
        if text or (cleaned and cleaned[-1]):
            cleaned.append(text)
    while cleaned and not cleaned[-1]:
        cleaned.pop()
    return textwrap.dedent("\n".join(cleaned))


def _declaration(cur: Cursor, package: str) -> tuple[FieldSpec | ConstantSpec, int]:
    """Read ``type name`` and what follows; return the spec and the position of its name."""
    type_pos = cur.pos
    type_token = cur.take_type_token()
    if type_token.startswith("@"):  # newer rosidl reads annotation lines such as @optional
        name = show(type_token.split("(")[0])
        raise cur.error(
            f"{name} is an annotation, and srvwire does not support annotations: remove it "
            "(a field left out of a message takes its default)",
            type_pos,
        )
    type_ = _type(cur, type_token, type_pos, package)
    cur.skip_ws()
    name_pos = cur.pos
    name = cur.take_until(WS + "#=")
    if not name:
        if cur.peek() == "=":
            raise cur.error("expected a constant name before '='")
        raise cur.error(f"expected a field name after the type '{type_token}'")
    spaced = cur.skip_ws() > 0
    if cur.peek() == "=":
        cur.pos += 1
        return _constant(cur, type_, type_token, type_pos, name, name_pos), name_pos
    if not FIELD_NAME.fullmatch(name):
        hint = ""
        if "[" in name:
            bare, suffix = name[: name.index("[")], name[name.index("[") :]
            if not bare:  # int32 [3] a: a space between the type and its suffix
                bare = cur.take_until(WS + "#=") or "name"
                raise cur.error(
                    f"{show(name)} is an array suffix, not a field name: it goes on the type, "
                    f"with no space before it: '{type_token}{suffix} {bare}'",
                    name_pos,
                )
            hint = f"; the array suffix goes on the type: '{type_token}{suffix} {bare}'"
        raise cur.error(f"{show(name)} is an invalid field name: {SNAKE_RULE}{hint}", name_pos)
    default: Value | None = None
    if spaced and not cur.at_comment_or_end():
        default = _default_value(cur, type_)
    return FieldSpec(type_, name, default, line=cur.line), name_pos


# --- types ------------------------------------------------------------------------------------


def _type(cur: Cursor, token: str, pos: int, package: str) -> TypeSpec:
    """Read a whole type token: base type, optional string bound, optional array suffix."""
    bracket = token.find("[")
    base = token if bracket < 0 else token[:bracket]
    if not base or base.startswith("-"):
        found = token or cur.peek()
        hint = "; a separator line is exactly '---'" if base.startswith("-") else ""
        raise cur.error(f"expected a type, found {show(found)}{hint}", pos)
    array, array_size = ArrayKind.NONE, None
    if bracket >= 0:
        array, array_size = _array_suffix(cur, token[bracket:], pos + bracket)
    bound_at = base.find("<=")
    bound = None
    if bound_at >= 0:
        bound = size(cur, base[bound_at + 2 :], pos + bound_at + 2, "a string bound")
        base = base[:bound_at]
    name, type_package = _base_type(cur, base, pos, package)
    if bound is not None and (type_package is not None or name not in STRING_TYPES):
        raise cur.error(
            f"only string and wstring take a length bound '<=N'; '{base}' does not", pos + bound_at
        )
    return TypeSpec(name, type_package, bound, array, array_size)


def _array_suffix(cur: Cursor, suffix: str, pos: int) -> tuple[ArrayKind, int | None]:
    """Read ``[]``, ``[N]`` or ``[<=N]`` at the end of a type token."""
    close = suffix.find("]")
    if close < 0:
        raise cur.error("expected ']' to close the array suffix", pos + len(suffix))
    rest = suffix[close + 1 :]
    if rest.startswith("["):
        raise cur.error("arrays of arrays are not supported", pos + close + 1)
    if rest:
        raise cur.error(f"unexpected {show(rest)} after the array suffix", pos + close + 1)
    inner = suffix[1:close]
    if not inner:
        return ArrayKind.UNBOUNDED, None
    if inner.startswith("<="):
        return ArrayKind.BOUNDED, size(cur, inner[2:], pos + 3, "an array bound")
    return ArrayKind.FIXED, size(cur, inner, pos + 1, "an array size")


def _base_type(cur: Cursor, text: str, pos: int, package: str) -> tuple[str, str | None]:
    """Resolve a type name to (name, package); the package is None for a primitive."""
    if text in PRIMITIVE_TYPES:
        return text, None
    if "/" in text:
        parts = text.split("/")
        if len(parts) == 3 and parts[1] == "msg":
            parts = [parts[0], parts[2]]
        if len(parts) != 2:
            raise cur.error(
                f"invalid type {show(text)}: expected 'Type', 'package/Type' or 'package/msg/Type'",
                pos,
            )
        type_package, name = parts
        if not type_package:
            raise cur.error("expected a package name before '/'", pos)
        if not name:
            raise cur.error("expected a type name after '/'", pos + len(text))
        if not PACKAGE_NAME.fullmatch(type_package):
            raise cur.error(f"{show(type_package)} is an invalid package name: {SNAKE_RULE}", pos)
        if not TYPE_NAME.fullmatch(name):
            name_pos = pos + len(text) - len(name)
            raise cur.error(f"{show(name)} is an invalid type name: {TYPE_RULE}", name_pos)
        return name, type_package
    if TYPE_NAME.fullmatch(text):
        return text, package
    if text in ("time", "duration"):
        raise cur.error(
            f"unknown type '{text}': ROS 2 spells ROS 1's {text} as "
            f"'builtin_interfaces/{text.capitalize()}'",
            pos,
        )
    if "A" <= text[0] <= "Z":
        raise cur.error(f"{show(text)} is an invalid type name: {TYPE_RULE}", pos)
    alias = FOREIGN_TYPES.get(text)
    close = [alias] if alias else sorted(difflib.get_close_matches(text, PRIMITIVE_TYPES, n=3))
    if close:
        quoted = [f"'{c}'" for c in close]
        listed = quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} or {quoted[-1]}"
        raise cur.error(f"unknown type {show(text)}; did you mean {listed}?", pos)
    raise cur.error(
        f"unknown type {show(text)}: expected a primitive type such as 'int32' or a message "
        "type such as 'Point' or 'geometry_msgs/Point'",
        pos,
    )


# --- constants and default values -------------------------------------------------------------


def _constant(
    cur: Cursor, type_: TypeSpec, type_token: str, type_pos: int, name: str, name_pos: int
) -> ConstantSpec:
    """Read a constant after its ``=``: ``TYPE NAME=value``."""
    if not type_.is_primitive:
        raise cur.error(
            f"a constant needs a primitive type; '{type_token}' is a message type", type_pos
        )
    if type_.is_array:
        raise cur.error(f"a constant cannot be an array ('{type_token}')", type_pos)
    if type_.string_bound is not None:
        raise cur.error(
            f"a constant cannot have a bounded string type ('{type_token}'); use '{type_.name}'",
            type_pos,
        )
    if not CONSTANT_NAME.fullmatch(name):
        hint = ""
        if FIELD_NAME.fullmatch(name):
            hint = f"; to give field '{name}' a default, write '{type_token} {name} value'"
        raise cur.error(
            f"{show(name)} is an invalid constant name: {CONSTANT_RULE}{hint}", name_pos
        )
    cur.skip_ws()
    if cur.at_comment_or_end():
        hint = '; write "" for an empty string' if type_.name in STRING_TYPES else ""
        raise cur.error(f"expected a value after '='{hint}")
    value = _scalar_value(cur, type_, "constant")
    return ConstantSpec(type_, name, value, line=cur.line)


def _default_value(cur: Cursor, type_: TypeSpec) -> Value:
    if not type_.is_primitive:
        raise cur.error(f"a field of message type '{type_}' cannot have a default value")
    if type_.is_array:
        return _array_value(cur, type_)
    return _scalar_value(cur, type_, "default")


def _array_value(cur: Cursor, type_: TypeSpec) -> tuple[Scalar, ...]:
    """Read ``[v, v, ...]`` and check its length against the array's size or bound."""
    open_pos = cur.pos
    if cur.peek() != "[":
        raise cur.error(
            f"expected '[' to start the default of '{type_}', as in [1, 2, 3]"
            if type_.name not in STRING_TYPES
            else f"expected '[' to start the default of '{type_}', as in [\"a\", \"b\"]"
        )
    cur.pos += 1
    element = type_.element
    values: list[Scalar] = []
    cur.skip_ws()
    if cur.peek() == "]":
        cur.pos += 1
    else:
        while True:
            cur.skip_ws()
            if cur.at_comment_or_end():
                raise cur.error("expected ']' to close the array default", open_pos)
            if cur.peek() in ",]":
                raise cur.error(f"expected a value, found '{cur.peek()}'")
            values.append(_scalar_value(cur, element, "default", stops=",]"))
            cur.skip_ws()
            if cur.peek() == ",":
                cur.pos += 1
            elif cur.peek() == "]":
                cur.pos += 1
                break
            elif cur.at_comment_or_end():
                raise cur.error("expected ']' to close the array default", open_pos)
            else:
                pos = cur.pos
                found = show(cur.take_until(WS + ",]#"))
                raise cur.error(f"expected ',' or ']', found {found}", pos)
    count = len(values)
    elements = f"{count} element" + ("" if count == 1 else "s")
    if type_.array is ArrayKind.FIXED and count != type_.size:
        raise cur.error(f"default has {elements} but {type_} needs exactly {type_.size}", open_pos)
    if type_.array is ArrayKind.BOUNDED and type_.size is not None and count > type_.size:
        raise cur.error(f"default has {elements} but {type_} allows at most {type_.size}", open_pos)
    return tuple(values)


def _scalar_value(cur: Cursor, type_: TypeSpec, what: str, stops: str = "") -> Scalar:
    """Read one value of a primitive scalar type; ``stops`` end an unquoted value early."""
    pos = cur.pos
    if type_.name not in STRING_TYPES:
        token = cur.take_until(WS + "#" + stops)
        return _literal(cur, type_.name, token, pos, what)
    if cur.peek() in QUOTES:
        value = quoted_string(cur)
    else:
        value = cur.take_until("#" + stops).rstrip(WS)
        cur.pos = pos + len(value)
        if not value:
            raise cur.error("expected a value", pos)
    if type_.string_bound is not None and len(value) > type_.string_bound:
        raise cur.error(
            f"{what} is {len(value)} characters long but {type_.element} allows at most "
            f"{type_.string_bound}",
            pos,
        )
    return value


def _literal(cur: Cursor, type_name: str, token: str, pos: int, what: str) -> Scalar:
    """Turn the text of a bool, integer or float value into a Python value."""
    if type_name == "bool":
        return bool_literal(cur, token, pos)
    if type_name in FLOAT_TYPES:
        return float_literal(cur, token, pos, what, type_name)
    low, high = INTEGER_RANGES[type_name]
    return integer_literal(cur, token, pos, what, type_name, low, high)
