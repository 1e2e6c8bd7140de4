"""The text of an interface file as lines, and the tokens of a line, for :mod:`srvwire.parser`.

A :class:`Cursor` holds one line and a position in it, and takes what is there: whitespace, a
type token, everything up to a stop. Each function below it reads one token at the cursor (a
comment, a size, a quoted string, the literal of a bool, an integer or a float) and leaves the
cursor after it, or raises an error that points at it. What a token means (which literal a type
takes, what a type token names) is the parser's business.

Invariants
----------
* The text is cut into lines where ROS 2's parser cuts it (:meth:`str.splitlines`): at
  ``\\r\\n``, ``\\r``, ``\\n``, ``\\v``, ``\\f``, ``\\x1c``-``\\x1e``, ``\\x85``, ``\\u2028`` and
  ``\\u2029``, after dropping one leading byte-order mark. So a form feed in a comment ends the
  comment, and a line number counts the lines ROS 2 counts. No line ever holds a line break, so
  every message is one line.
* Positions are 0-based indexes into the line; they become 1-based columns only when an error
  is raised, and a column counts characters (a tab is one column).
* The parser reads :func:`source_lines`, where every tab is a space, as ROS 2 replaces every tab
  before it parses: a tab in a quoted string, a default or a comment reads as a space.
* ``ws`` is a space or a tab and nothing else. Any other character (a no-break space, a form
  feed) belongs to the token it touches, and the token's error shows it escaped (:func:`show`).
* Every problem is an :class:`~srvwire.errors.InterfaceSyntaxError` made by
  :meth:`Cursor.error` (or :func:`file_error` for whole-file problems), pointing at the first
  character of the offending token.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Final

from srvwire.errors import InterfaceSyntaxError

__all__ = [
    "CONSTANT_NAME",
    "CONSTANT_RULE",
    "FIELD_NAME",
    "PACKAGE_NAME",
    "QUOTES",
    "SNAKE_RULE",
    "TYPE_NAME",
    "TYPE_RULE",
    "WS",
    "Cursor",
    "bool_literal",
    "comment",
    "decode",
    "end_of_line",
    "file_error",
    "float_literal",
    "integer_literal",
    "quoted_string",
    "show",
    "size",
    "source_lines",
    "split_lines",
]

LINE_BREAK: Final = re.compile(r"\r\n|[\n\r\v\f\x1c\x1d\x1e\x85\u2028\u2029]")  # splitlines()'s
WS: Final = " \t"
QUOTES: Final = "\"'"

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
# What rounds to a finite float32 lies within it: primitives.FLOAT32_BOUND, which this layer
# may not import (tests/test_models.py holds the two together).
FLOAT32_BOUND: Final = 2.0**128 - 2.0**103
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


# --- text, lines, positions and errors --------------------------------------------------------


def show(text: str) -> str:
    """Quote a token for an error message, escaping anything invisible or line-breaking."""
    return f"'{text}'" if text.isprintable() else repr(text)


def file_error(
    message: str, path: str | None, line: int = 1, column: int = 1
) -> InterfaceSyntaxError:
    """An error about the file as a whole, or at a place no :class:`Cursor` is on."""
    return InterfaceSyntaxError(message, path=path, line=line, column=column)


def decode(data: bytes, path: str) -> str:
    """The text of a file's bytes, which must be UTF-8; an error points at the first bad byte."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        lines = split_lines(data[: exc.start].decode("utf-8"))  # valid up to the bad byte
        message = f"the file is not valid UTF-8: byte 0x{data[exc.start]:02x} cannot be decoded"
        raise file_error(message, path, len(lines), len(lines[-1]) + 1) from exc


def split_lines(text: str) -> list[str]:
    """Cut ``text`` into lines, dropping one leading byte-order mark."""
    return LINE_BREAK.split(text.removeprefix("\ufeff"))


def source_lines(text: str) -> list[str]:
    """The lines the parser reads: :func:`split_lines`, each tab made a space first."""
    return split_lines(text.replace("\t", " "))


@dataclass
class Cursor:
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

    def take_type_token(self) -> str:
        """Consume a type token: up to whitespace, ``#``, or an ``=`` that is not part of ``<=``."""
        start = self.pos
        text = self.text
        while self.pos < len(text) and text[self.pos] not in WS + "#":
            if text[self.pos] == "=" and (self.pos == start or text[self.pos - 1] != "<"):
                break
            self.pos += 1
        return text[start : self.pos]

    def error(self, message: str, pos: int | None = None) -> InterfaceSyntaxError:
        column = (self.pos if pos is None else pos) + 1
        return InterfaceSyntaxError(message, path=self.path, line=self.line, column=column)


# --- comments and sizes -----------------------------------------------------------------------


def comment(cur: Cursor) -> str:
    """Consume a comment from its ``#`` to the end of the line; return the text after the ``#``."""
    text = cur.text[cur.pos + 1 :]
    cur.pos = len(cur.text)
    return text


def end_of_line(cur: Cursor, after: str) -> str | None:
    """Read optional whitespace and an optional comment up to the end of the line."""
    cur.skip_ws()
    if cur.at_end():
        return None
    if cur.peek() == "#":
        return comment(cur)
    pos = cur.pos
    token = cur.take_until(WS + "#")
    raise cur.error(f"unexpected {show(token)} after the {after}", pos)


def size(cur: Cursor, text: str, pos: int, what: str) -> int:
    """Read an array size or a string bound, ``text`` at ``pos``: from 1 to ``2**32 - 1``."""
    digits = text.lstrip("0")
    if not SIZE.fullmatch(text) or not digits:
        found = show(text) if text else "nothing"
        raise cur.error(f"{what} must be a positive integer, found {found}", pos)
    # The length test keeps int() clear of Python's limit on the digits it converts.
    if len(digits) > len(str(MAX_SIZE)) or int(digits) > MAX_SIZE:
        raise cur.error(f"{what} must be at most {MAX_SIZE}, found {text}", pos)
    return int(digits)


# --- literals ---------------------------------------------------------------------------------


def quoted_string(cur: Cursor) -> str:
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


def bool_literal(cur: Cursor, token: str, pos: int) -> bool:
    """The bool ``token`` (at ``pos``) spells: ``true``, ``false``, ``1`` or ``0``, in any case."""
    lowered = token.lower()
    if lowered in ("true", "1"):
        return True
    if lowered in ("false", "0"):
        return False
    raise cur.error(f"{show(token)} is not a valid bool: expected true, false, 1 or 0", pos)


def integer_literal(
    cur: Cursor, token: str, pos: int, what: str, type_name: str, low: int, high: int
) -> int:
    """The integer ``token`` spells, which must fit ``type_name`` (``low..high``).

    ``what`` names the value in an error: ``default`` or ``constant``.
    """
    match = INTEGER.fullmatch(token)
    if match is None:
        raise cur.error(
            f"{show(token)} is not a valid {type_name}: expected an integer "
            "(decimal, 0x hex, 0o octal or 0b binary)",
            pos,
        )
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


def float_literal(cur: Cursor, token: str, pos: int, what: str, type_name: str) -> float:
    """The float ``token`` spells: finite, and for ``float32`` one that rounds to a finite
    ``float32`` (a magnitude below ``FLOAT32_BOUND``)."""
    if token.lower().lstrip("+-") in ("inf", "infinity", "nan"):
        raise cur.error(
            f"{show(token)} is not allowed for {type_name}: defaults and constants must be finite",
            pos,
        )
    if not FLOAT.fullmatch(token):
        raise cur.error(
            f"{show(token)} is not a valid {type_name}: expected a number such as 1.5, -2 or 1e-3",
            pos,
        )
    value = float(token)
    if not math.isfinite(value) or (type_name == "float32" and abs(value) >= FLOAT32_BOUND):
        raise cur.error(f"{what} {token} is out of range for {type_name}", pos)
    return value
