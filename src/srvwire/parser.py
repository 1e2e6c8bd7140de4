"""Parse ROS 2 interface files (``.msg``, ``.srv``, ``.action``) into :mod:`srvwire.idl` specs.

The grammar is the one ROS 2's reference parser (``rosidl_adapter``) reads; ``docs/interfaces.md``
describes it for users. Written as rules, one function per rule below::

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
* The text is cut into lines at ``\\r\\n``, ``\\r`` and ``\\n`` only, after dropping one leading
  byte-order mark. No line ever holds a line break, so every message is one line.
* Each line is read once, left to right, by a :class:`_Cursor`. Positions are 0-based indexes
  into the line; they become 1-based columns only when an error is raised, and a column counts
  characters (a tab is one column).
* ``ws`` is a space or a tab and nothing else. Any other character (a no-break space, a form
  feed) belongs to the token it touches, and the token's error shows it escaped.
* A ``#`` outside a quoted string starts a comment, even one glued to a token
  (``int32 x#doc``). Quotes are only recognised where a value starts, so comment stripping is
  quote-aware by construction; :func:`split_comment` finds a line's comment by reading the
  line with the same rules.
* Every problem is raised as :class:`~srvwire.errors.InterfaceSyntaxError` through
  :meth:`_Cursor.error` (or :func:`_error` for whole-file problems), pointing at the first
  character of the offending token; a missing separator is reported on the file's last line.
  No other exception leaves this module for any input text; only :func:`parse_file` may also
  raise :class:`OSError` when the file cannot be read.
* Nested types are not looked up: whether ``Point`` exists is the loader's business.

Decisions where the reference parser is silent, crashes or surprises
-------------------------------------------------------------------
1. Leading whitespace before a declaration is allowed (rosidl fails on an indented field).
   An indented *comment* line directly below a declaration continues that declaration's doc,
   as in rosidl.
2. ``#`` inside a quoted string is part of the string (rosidl cuts the line at the first ``#``).
3. A line is a constant only when the token after the type is followed by ``=``
   (``int32 MAX=5``, ``int32 MAX = 5``); ``string s "a=b"`` and ``string s a=b`` are fields with
   the default ``a=b`` (rosidl makes any line holding ``=`` a constant).
4. ``bool`` values are ``true``/``false``/``1``/``0`` in any case, as in rosidl.
5. Integers are decimal, ``0x`` hex, ``0o`` octal or ``0b`` binary, with an optional sign;
   Python's ``_`` digit separators are refused. Floats are decimal with an optional exponent
   (``1e-3``, ``-.5``, ``2.``); ``inf`` and ``nan`` are refused, so that every type's default
   instance is standard JSON (values set at run time may still be non-finite).
   A ``float32`` value beyond the largest finite float32 is out of range.
6. Inside quotes the only escape is a backslash before the enclosing quote, as in rosidl; every
   other backslash is kept. A quoted string therefore cannot end in a backslash.
7. After a quoted string or an array only whitespace and a comment may follow (rosidl would
   take ``"a" b`` literally, quotes and all).
8. A ``string`` constant with nothing after ``=`` is an error; write ``""``. Constants take
   unbounded primitive scalar types only, as in rosidl.
9. The separator line may be indented and carry a trailing comment (rosidl wants exactly
   ``---``). Comments directly after a separator document the next part.
10. A comment block documents the declaration *directly* below it; a blank line in between
    detaches it (rosidl keeps it). The first comment block before any declaration documents
    the message, as in rosidl.
11. ``Header`` is a same-package type like any other; write ``std_msgs/Header``. ROS 1's
    ``time`` and ``duration`` are unknown types (use ``builtin_interfaces/Time``/``Duration``).
12. ``package/msg/Type`` is accepted as a long spelling of ``package/Type``.
13. Array sizes and string bounds are at most 2**32 - 1 (OMG IDL's unsigned long); rosidl sets
    no limit.
"""

from __future__ import annotations

import codecs
import difflib
import math
import os
import re
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Final

from srvwire.errors import InterfaceSyntaxError
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

__all__ = ["parse_action", "parse_file", "parse_message", "parse_service", "split_comment"]

WS: Final = " \t"
QUOTES: Final = "\"'"
LINE_BREAK: Final = re.compile(r"\r\n|\r|\n")
SEPARATOR: Final = re.compile(r"[ \t]*---[ \t]*(?:#.*)?")
NEAR_SEPARATOR: Final = re.compile(r"[ \t]*--[^#]*(?:#.*)?")  # a line that looks meant as one

FIELD_NAME: Final = re.compile(r"(?!.*__)(?!.*_$)[a-z][a-z0-9_]*")
PACKAGE_NAME: Final = FIELD_NAME
TYPE_NAME: Final = re.compile(r"[A-Z][A-Za-z0-9]*")
CONSTANT_NAME: Final = re.compile(r"[A-Z](?:[A-Z0-9_]?[A-Z0-9]+)*")
SIZE: Final = re.compile(r"[0-9]+")
INTEGER: Final = re.compile(
    r"(?P<sign>[+-]?)(?:0[xX](?P<hex>[0-9a-fA-F]+)|0[oO](?P<oct>[0-7]+)|0[bB](?P<bin>[01]+)"
    r"|(?P<dec>[0-9]+))"
)
BASES: Final = {"dec": 10, "hex": 16, "oct": 8, "bin": 2}  # INTEGER's digit groups
FLOAT: Final = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
FLOAT32_MAX: Final = 3.4028234663852886e38
MAX_SIZE: Final = 2**32 - 1  # array sizes and string bounds are 32-bit unsigned in OMG IDL

SNAKE_RULE: Final = (
    "it must start with a lowercase letter and contain only lowercase letters, digits and "
    "underscores, with no double or trailing underscore"
)
TYPE_RULE: Final = "it must start with an uppercase letter and contain only letters and digits"
CONSTANT_RULE: Final = (
    "it must start with an uppercase letter and contain only uppercase letters, digits and "
    "single underscores between them"
)
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


# --- positions and errors ---------------------------------------------------------------------


def _show(text: str) -> str:
    """Quote a token for an error message, escaping anything invisible or line-breaking."""
    return f"'{text}'" if text.isprintable() else repr(text)


def _error(message: str, path: str | None, line: int = 1, column: int = 1) -> InterfaceSyntaxError:
    return InterfaceSyntaxError(message, path=path, line=line, column=column)


@dataclass
class _Cursor:
    """One line of source and a position in it; knows how to raise an error at a position."""

    text: str
    line: int
    path: str | None
    pos: int = 0

    def peek(self) -> str:
        return self.text[self.pos] if self.pos < len(self.text) else ""

    def at_end(self) -> bool:
        return self.pos >= len(self.text)

    def at_comment_or_end(self) -> bool:
        return self.pos >= len(self.text) or self.text[self.pos] == "#"

    def skip_ws(self) -> int:
        start = self.pos
        while self.pos < len(self.text) and self.text[self.pos] in WS:
            self.pos += 1
        return self.pos - start

    def take_until(self, stops: str) -> str:
        """Consume and return characters up to (not including) one of ``stops`` or the end."""
        start = self.pos
        while self.pos < len(self.text) and self.text[self.pos] not in stops:
            self.pos += 1
        return self.text[start : self.pos]

    def error(self, message: str, pos: int | None = None) -> InterfaceSyntaxError:
        column = (self.pos if pos is None else pos) + 1
        return InterfaceSyntaxError(message, path=self.path, line=self.line, column=column)


# --- public API -------------------------------------------------------------------------------


def parse_message(text: str, package: str, name: str, *, path: str | None = None) -> MessageSpec:
    """Parse the text of a ``.msg`` file into a :class:`MessageSpec` named ``package/name``."""
    _check_names(package, name, "message", path)
    lines = _split_lines(text)
    ((first, part),) = _parts(lines, 1, path)
    return _message(part, first, package, name, path)


def parse_service(text: str, package: str, name: str, *, path: str | None = None) -> ServiceSpec:
    """Parse the text of a ``.srv`` file: a request and a response split by one ``---`` line."""
    _check_names(package, name, "service", path)
    lines = _split_lines(text)
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
    lines = _split_lines(text)
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
        raise _error(
            f"unknown interface file suffix {_show(file.suffix)}: expected .msg, .srv or .action",
            shown,
        )
    if package is None:
        package = Path(os.path.abspath(file)).parent.parent.name
        if not package:
            raise _error("cannot tell the package from the file's path; pass package=", shown)
    text = _decode(file.read_bytes(), shown).removeprefix("\ufeff")
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
    cur = _Cursor(line, 1, None)
    cur.skip_ws()
    if SEPARATOR.fullmatch(line):
        cur.take_until("#")  # past the dashes: what is left is a comment or nothing
    if cur.at_comment_or_end():
        comment = None if cur.at_end() else _comment(cur)
    else:
        # The package only qualifies the type names, which do not move a comment.
        spec, _ = _declaration(cur, package="")
        comment = _trailing_comment(cur, spec)
    if comment is None:
        return line, None
    return line[: len(line) - len(comment) - 1], comment


# --- files and parts --------------------------------------------------------------------------


def _decode(data: bytes, path: str) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        breaks = list(re.finditer(rb"\r\n|\r|\n", data[: exc.start]))
        line_start = (
            breaks[-1].end() if breaks else len(codecs.BOM_UTF8) * data.startswith(codecs.BOM_UTF8)
        )
        column = len(data[line_start : exc.start].decode("utf-8", "replace")) + 1
        message = f"the file is not valid UTF-8: byte 0x{data[exc.start]:02x} cannot be decoded"
        raise _error(message, path, len(breaks) + 1, column) from exc


def _check_names(package: str, name: str, kind: str, path: str | None) -> None:
    if not PACKAGE_NAME.fullmatch(package):
        raise _error(f"{_show(package)} is an invalid package name: {SNAKE_RULE}", path)
    if not TYPE_NAME.fullmatch(name):
        raise _error(f"{_show(name)} is an invalid {kind} name: {TYPE_RULE}", path)


def _split_lines(text: str) -> list[str]:
    return LINE_BREAK.split(text.removeprefix("\ufeff"))


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
        raise _error(message, path, index + 1, column)
    if len(separators) < count - 1:
        for index, line in enumerate(lines):
            if NEAR_SEPARATOR.fullmatch(line) and index not in separators:
                found = _show(line.split("#")[0].strip(WS))
                column = line.index("-") + 1
                raise _error(
                    f"expected a separator line '---', found {found}", path, index + 1, column
                )
        found = "none" if not separators else "only one"
        message = {
            2: "a service needs a '---' line between the request and the response; found none",
            3: f"an action needs two '---' lines between goal, result and feedback; found {found}",
        }[count]
        raise _error(message, path, len(lines), 1)
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
        _line(_Cursor(text, first + offset, path), message, package)
    return message.build(package, name, path)


def _line(cur: _Cursor, message: _Message, package: str) -> None:
    indent = cur.skip_ws()
    if cur.at_end():
        message.blank()
        return
    if cur.peek() == "#":
        message.comment(_comment(cur), indented=indent > 0)
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


def _comment(cur: _Cursor) -> str:
    text = cur.text[cur.pos + 1 :]
    cur.pos = len(cur.text)
    return text


def _trailing_comment(cur: _Cursor, spec: FieldSpec | ConstantSpec) -> str | None:
    """Read what may follow a declaration: whitespace, then an optional comment."""
    if isinstance(spec, ConstantSpec):
        what = "constant value"
    else:
        what = "field name" if spec.default is None else "default value"
    return _end_of_line(cur, what)


def _end_of_line(cur: _Cursor, after: str) -> str | None:
    """Read optional whitespace and an optional comment up to the end of the line."""
    cur.skip_ws()
    if cur.at_end():
        return None
    if cur.peek() == "#":
        return _comment(cur)
    pos = cur.pos
    token = cur.take_until(WS + "#")
    raise cur.error(f"unexpected {_show(token)} after the {after}", pos)


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


def _declaration(cur: _Cursor, package: str) -> tuple[FieldSpec | ConstantSpec, int]:
    """Read ``type name`` and what follows; return the spec and the position of its name."""
    type_pos = cur.pos
    type_token = _type_token(cur)
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
            hint = f"; the array suffix goes on the type: '{type_token}{suffix} {bare}'"
        raise cur.error(f"{_show(name)} is an invalid field name: {SNAKE_RULE}{hint}", name_pos)
    default: Value | None = None
    if spaced and not cur.at_comment_or_end():
        default = _default_value(cur, type_)
    return FieldSpec(type_, name, default, line=cur.line), name_pos


# --- types ------------------------------------------------------------------------------------


def _type_token(cur: _Cursor) -> str:
    """Consume a type token: up to whitespace, ``#``, or an ``=`` that is not part of ``<=``."""
    start = cur.pos
    text = cur.text
    while cur.pos < len(text) and text[cur.pos] not in WS + "#":
        if text[cur.pos] == "=" and (cur.pos == start or text[cur.pos - 1] != "<"):
            break
        cur.pos += 1
    return text[start : cur.pos]


def _type(cur: _Cursor, token: str, pos: int, package: str) -> TypeSpec:
    """Read a whole type token: base type, optional string bound, optional array suffix."""
    bracket = token.find("[")
    base = token if bracket < 0 else token[:bracket]
    if not base or base.startswith("-"):
        found = token or cur.peek()
        hint = "; a separator line is exactly '---'" if base.startswith("-") else ""
        raise cur.error(f"expected a type, found {_show(found)}{hint}", pos)
    array, size = ArrayKind.NONE, None
    if bracket >= 0:
        array, size = _array_suffix(cur, token[bracket:], pos + bracket)
    bound_at = base.find("<=")
    bound = None
    if bound_at >= 0:
        bound = _size(cur, base[bound_at + 2 :], pos + bound_at + 2, "a string bound")
        base = base[:bound_at]
    name, type_package = _base_type(cur, base, pos, package)
    if bound is not None and (type_package is not None or name not in STRING_TYPES):
        raise cur.error(
            f"only string and wstring take a length bound '<=N'; '{base}' does not", pos + bound_at
        )
    return TypeSpec(name, type_package, bound, array, size)


def _array_suffix(cur: _Cursor, suffix: str, pos: int) -> tuple[ArrayKind, int | None]:
    """Read ``[]``, ``[N]`` or ``[<=N]`` at the end of a type token."""
    close = suffix.find("]")
    if close < 0:
        raise cur.error("expected ']' to close the array suffix", pos + len(suffix))
    rest = suffix[close + 1 :]
    if rest.startswith("["):
        raise cur.error("arrays of arrays are not supported", pos + close + 1)
    if rest:
        raise cur.error(f"unexpected {_show(rest)} after the array suffix", pos + close + 1)
    inner = suffix[1:close]
    if not inner:
        return ArrayKind.UNBOUNDED, None
    if inner.startswith("<="):
        return ArrayKind.BOUNDED, _size(cur, inner[2:], pos + 3, "an array bound")
    return ArrayKind.FIXED, _size(cur, inner, pos + 1, "an array size")


def _size(cur: _Cursor, text: str, pos: int, what: str) -> int:
    digits = text.lstrip("0")
    if not SIZE.fullmatch(text) or not digits:
        found = _show(text) if text else "nothing"
        raise cur.error(f"{what} must be a positive integer, found {found}", pos)
    # The length test keeps int() clear of Python's limit on the digits it converts.
    if len(digits) > len(str(MAX_SIZE)) or int(digits) > MAX_SIZE:
        raise cur.error(f"{what} must be at most {MAX_SIZE}, found {text}", pos)
    return int(digits)


def _base_type(cur: _Cursor, text: str, pos: int, package: str) -> tuple[str, str | None]:
    """Resolve a type name to (name, package); the package is None for a primitive."""
    if text in PRIMITIVE_TYPES:
        return text, None
    if "/" in text:
        parts = text.split("/")
        if len(parts) == 3 and parts[1] == "msg":
            parts = [parts[0], parts[2]]
        if len(parts) != 2:
            raise cur.error(
                f"invalid type {_show(text)}: expected 'Type', 'package/Type' or "
                "'package/msg/Type'",
                pos,
            )
        type_package, name = parts
        if not type_package:
            raise cur.error("expected a package name before '/'", pos)
        if not name:
            raise cur.error("expected a type name after '/'", pos + len(text))
        if not PACKAGE_NAME.fullmatch(type_package):
            raise cur.error(f"{_show(type_package)} is an invalid package name: {SNAKE_RULE}", pos)
        if not TYPE_NAME.fullmatch(name):
            name_pos = pos + len(text) - len(name)
            raise cur.error(f"{_show(name)} is an invalid type name: {TYPE_RULE}", name_pos)
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
        raise cur.error(f"{_show(text)} is an invalid type name: {TYPE_RULE}", pos)
    alias = FOREIGN_TYPES.get(text)
    close = [alias] if alias else sorted(difflib.get_close_matches(text, PRIMITIVE_TYPES, n=3))
    if close:
        quoted = [f"'{c}'" for c in close]
        listed = quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} or {quoted[-1]}"
        raise cur.error(f"unknown type {_show(text)}; did you mean {listed}?", pos)
    raise cur.error(
        f"unknown type {_show(text)}: expected a primitive type such as 'int32' or a message "
        "type such as 'Point' or 'geometry_msgs/Point'",
        pos,
    )


# --- constants and default values -------------------------------------------------------------


def _constant(
    cur: _Cursor, type_: TypeSpec, type_token: str, type_pos: int, name: str, name_pos: int
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
            f"{_show(name)} is an invalid constant name: {CONSTANT_RULE}{hint}", name_pos
        )
    cur.skip_ws()
    if cur.at_comment_or_end():
        hint = '; write "" for an empty string' if type_.name in STRING_TYPES else ""
        raise cur.error(f"expected a value after '='{hint}")
    value = _scalar_value(cur, type_, "constant")
    return ConstantSpec(type_, name, value, line=cur.line)


def _default_value(cur: _Cursor, type_: TypeSpec) -> Value:
    if not type_.is_primitive:
        raise cur.error(f"a field of message type '{type_}' cannot have a default value")
    if type_.is_array:
        return _array_value(cur, type_)
    return _scalar_value(cur, type_, "default")


def _array_value(cur: _Cursor, type_: TypeSpec) -> tuple[Scalar, ...]:
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
                found = _show(cur.take_until(WS + ",]#"))
                raise cur.error(f"expected ',' or ']', found {found}", pos)
    count = len(values)
    elements = f"{count} element" + ("" if count == 1 else "s")
    if type_.array is ArrayKind.FIXED and count != type_.size:
        raise cur.error(f"default has {elements} but {type_} needs exactly {type_.size}", open_pos)
    if type_.array is ArrayKind.BOUNDED and type_.size is not None and count > type_.size:
        raise cur.error(f"default has {elements} but {type_} allows at most {type_.size}", open_pos)
    return tuple(values)


def _scalar_value(cur: _Cursor, type_: TypeSpec, what: str, stops: str = "") -> Scalar:
    """Read one value of a primitive scalar type; ``stops`` end an unquoted value early."""
    pos = cur.pos
    if type_.name not in STRING_TYPES:
        token = cur.take_until(WS + "#" + stops)
        return _literal(cur, type_.name, token, pos, what)
    if cur.peek() in QUOTES:
        value = _quoted_string(cur)
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


def _quoted_string(cur: _Cursor) -> str:
    """Read ``"..."`` or ``'...'``; a backslash before the enclosing quote escapes it."""
    quote = cur.peek()
    start = cur.pos
    cur.pos += 1
    chunks: list[str] = []
    text = cur.text
    while cur.pos < len(text):
        char = text[cur.pos]
        if char == "\\" and text[cur.pos + 1 : cur.pos + 2] == quote:
            chunks.append(quote)
            cur.pos += 2
        elif char == quote:
            cur.pos += 1
            return "".join(chunks)
        else:
            chunks.append(char)
            cur.pos += 1
    raise cur.error(f"unterminated string: expected a closing {quote}", start)


def _literal(cur: _Cursor, type_name: str, token: str, pos: int, what: str) -> Scalar:
    """Turn the text of a bool, integer or float value into a Python value."""
    parse = _LITERALS["float" if type_name in FLOAT_TYPES else type_name]
    return parse(cur, type_name, token, pos, what)


def _bool(cur: _Cursor, type_name: str, token: str, pos: int, what: str) -> Scalar:
    lowered = token.lower()
    if lowered in ("true", "1"):
        return True
    if lowered in ("false", "0"):
        return False
    raise cur.error(f"{_show(token)} is not a valid bool: expected true, false, 1 or 0", pos)


def _integer(cur: _Cursor, type_name: str, token: str, pos: int, what: str) -> Scalar:
    match = INTEGER.fullmatch(token)
    if match is None:
        raise cur.error(
            f"{_show(token)} is not a valid {type_name}: expected an integer "
            "(decimal, 0x hex, 0o octal or 0b binary)",
            pos,
        )
    low, high = INTEGER_RANGES[type_name]
    base, digits = next((b, d) for b, d in zip(BASES, match.group(*BASES), strict=True) if d)
    # More than 70 digits is out of range in every base (2**70 > 2**64), and int() need not see
    # them: Python refuses to convert more than 4300 decimal digits.
    digits = digits.lstrip("0") or "0"
    value = int(digits, BASES[base]) if len(digits) <= 70 else None
    if value is not None and match.group("sign") == "-":
        value = -value
    if value is None or not low <= value <= high:
        raise cur.error(f"{what} {token} is out of range for {type_name} ({low}..{high})", pos)
    return value


def _float(cur: _Cursor, type_name: str, token: str, pos: int, what: str) -> Scalar:
    if token.lower().lstrip("+-") in ("inf", "infinity", "nan"):
        raise cur.error(
            f"{_show(token)} is not allowed for {type_name}: defaults and constants must be finite",
            pos,
        )
    if not FLOAT.fullmatch(token):
        raise cur.error(
            f"{_show(token)} is not a valid {type_name}: expected a number such as 1.5, -2 or 1e-3",
            pos,
        )
    value = float(token)
    if not math.isfinite(value) or (type_name == "float32" and abs(value) > FLOAT32_MAX):
        raise cur.error(f"{what} {token} is out of range for {type_name}", pos)
    return value


_LITERALS: Final[dict[str, Callable[[_Cursor, str, str, int, str], Scalar]]] = {
    "bool": _bool,
    "float": _float,
    **dict.fromkeys(INTEGER_RANGES, _integer),
}
