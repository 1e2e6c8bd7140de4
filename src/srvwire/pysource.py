"""Python source text laid out as ``ruff format`` writes it, for :mod:`srvwire.codegen`.

The writer builds each statement from a few expression shapes (:class:`Text`, :class:`Call`,
:class:`Keyword`, or a plain ``str`` of code) and :func:`statement` lays it out. Rules:

* **Nothing left for ruff to change.** Lines fit in :data:`LINE` (100) characters where ruff
  could make them fit. Every multi-line bracket ends its last item with a comma; ruff keeps
  such a "magic trailing comma" split one item per line, so the only layouts ruff chooses
  itself are those of strings (joined again when they fit) and of an assignment's right-hand
  side, which :func:`statement` mirrors.
* **Literals as ruff spells them.** Strings are double-quoted unless that needs more escapes,
  unprintable characters are escaped, and floats drop ``e+``. A non-finite float is written
  without a name a field could shadow (``1e999``).
* **Imports any isort setting keeps.** :func:`import_line` splits a long import one name a line
  with a trailing comma, and :func:`isort_key` orders names as isort does; :func:`all_key`
  orders ``__all__`` as ruff's RUF022 does (case matters there).
"""

from __future__ import annotations

import dataclasses
import math
import re
import textwrap
from typing import Any, TypeAlias

from srvwire.errors import InterfaceError

__all__ = [
    "IMPORT_LINE",
    "LINE",
    "Call",
    "Expr",
    "Keyword",
    "Text",
    "all_key",
    "as_docstring",
    "expression",
    "import_line",
    "isort_key",
    "scalar",
    "statement",
]

LINE = 100  # longest line the writer aims for
IMPORT_LINE = 88  # longest import statement left on one line: ruff's default line length


# --- expressions and statements, wrapped as ruff format would --------------------------------


@dataclasses.dataclass(frozen=True)
class Text:
    """A string value, written as one literal or, when it cannot fit, as several (implicit
    concatenation) inside parentheses."""

    text: str


@dataclasses.dataclass(frozen=True)
class Call:
    """``open`` items ``close``: a call, a subscript, a list or a tuple."""

    open: str
    items: tuple[Expr, ...]
    close: str = ")"


@dataclasses.dataclass(frozen=True)
class Keyword:
    key: str
    value: Expr


Expr: TypeAlias = str | Text | Call | Keyword  # a plain str is code written as it stands


def expression(value: Any) -> Expr:
    return Text(value) if isinstance(value, str) else scalar(value)


def _flat(expr: Expr) -> str:
    if isinstance(expr, str):
        return expr
    if isinstance(expr, Text):
        return _str(expr.text)
    if isinstance(expr, Keyword):
        return f"{expr.key}={_flat(expr.value)}"
    one_tuple = expr.open == "(" and len(expr.items) == 1
    inner = ", ".join(_flat(item) for item in expr.items)
    return f"{expr.open}{inner}{',' if one_tuple else ''}{expr.close}"


def _layout(expr: Expr, indent: int, column: int, suffix: int) -> str:
    """Write ``expr`` starting at ``column`` of a line indented ``indent``, followed by
    ``suffix`` characters (a comma, a bracket) on its last line."""
    flat = _flat(expr)
    if isinstance(expr, str) or column + len(flat) + suffix <= LINE:
        return flat
    if isinstance(expr, Keyword):
        head = f"{expr.key}="
        return head + _layout(expr.value, indent, column + len(head), suffix)
    pad = " " * (indent + 4)
    if isinstance(expr, Text):
        return f"(\n{_text_lines(expr.text, indent + 4)}\n{' ' * indent})"
    inner = "".join(f"{pad}{_layout(item, indent + 4, len(pad), 1)},\n" for item in expr.items)
    return f"{expr.open}\n{inner}{' ' * indent}{expr.close}"


def _text_lines(text: str, indent: int) -> str:
    """``text`` as string literals one per line at ``indent``, joined if they fit on one.

    This is how ruff format treats implicit concatenation inside parentheses: it joins the
    parts into one literal whenever that literal fits, so they are split only when it does not:
    after each line break, then after spaces, then anywhere.
    """
    pad = " " * indent
    if indent + len(_str(text)) <= LINE:
        return pad + _str(text)
    parts: list[str] = []
    for line in text.splitlines(keepends=True):
        part = ""
        for char in line:
            if part and indent + len(_str(part + char)) > LINE:
                cut = part.rfind(" ") + 1 or len(part)
                parts.append(part[:cut])
                part = part[cut:]
            part += char
        parts.append(part)
    return "\n".join(pad + _str(part) for part in parts)


def statement(indent: str, target: str, annotation: Expr | None, value: Expr) -> str:
    """Write ``target: annotation = value`` (no annotation when it is None), wrapped like ruff.

    ruff prefers, in order: one line; breaking inside the value's own brackets; the value alone
    in parentheses on the next line; and only then breaking the annotation.
    """
    column = len(indent)
    head = f"{indent}{target}: {_flat(annotation)} = " if annotation else f"{indent}{target} = "
    flat = _flat(value)
    if len(head) + len(flat) <= LINE:
        return head + flat
    if isinstance(value, Call) and len(head) + len(value.open) <= LINE:
        return head + _layout(value, column, len(head), 0)
    if len(head) + 1 <= LINE:
        if isinstance(value, Text):
            inner = _text_lines(value.text, column + 4)
        else:
            inner = " " * (column + 4) + _layout(value, column + 4, column + 4, 0)
        return f"{head}(\n{inner}\n{indent})"
    # Only a very long name gets here: break the annotation's brackets, as ruff does.
    flat_annotation = _flat(annotation) if annotation else ""
    if not flat_annotation.endswith("]"):  # nothing to break: the line stays long
        return head + (_layout(value, column, len(head), 0) if isinstance(value, Call) else flat)
    open_, _, inner = flat_annotation[:-1].partition("[")
    pad = " " * (column + 4)
    if len(pad) + len(inner) > LINE and isinstance(annotation, Call):
        inner = "".join(
            f"{pad}{_layout(item, column + 4, column + 4, 1)},\n" for item in annotation.items
        )
    else:
        inner = f"{pad}{inner}\n"
    head = f"{indent}{target}: {open_}[\n{inner}{indent}] = "
    return head + _layout(value, column, column + 4, 0)


# --- literals, docstrings and imports --------------------------------------------------------


def scalar(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "1e999 - 1e999"  # nan, written without a name a field could shadow
        if math.isinf(value):
            return "1e999" if value > 0 else "-1e999"
        return repr(value).replace("e+", "e")  # 1e+16 as ruff format writes it: 1e16
    if isinstance(value, str):
        return _str(value)
    raise InterfaceError(f"cannot write {value!r} as a literal")


_ESCAPES = {"\\": "\\\\", "\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _str(text: str) -> str:
    """A string literal; unprintable characters are escaped.

    Double-quoted unless the text holds more double than single quotes, the choice ruff format
    makes, so that it has nothing to change.
    """
    quote = "'" if text.count('"') > text.count("'") else '"'
    out: list[str] = []
    for char in text:
        if char in _ESCAPES:
            out.append(_ESCAPES[char])
        elif char == quote:
            out.append("\\" + char)
        elif char.isprintable():
            out.append(char)
        elif ord(char) <= 0xFF:
            out.append(f"\\x{ord(char):02x}")
        elif ord(char) <= 0xFFFF:
            out.append(f"\\u{ord(char):04x}")
        else:
            out.append(f"\\U{ord(char):08x}")
    return quote + "".join(out) + quote


def as_docstring(text: str, indent: str) -> str | None:
    """A docstring holding ``text``, or None when none can be written as ruff would keep it.

    ``inspect.cleandoc`` of the docstring gives ``cleandoc(text)``. It is triple-quoted when
    ``text`` is plain: no escapes needed, no ``\"\"\"``, no white space at the ends of lines.
    Otherwise it is a one-line literal with escapes, if that fits and ruff would not strip or
    pad it. Otherwise it is None, and the caller assigns ``__doc__`` a string that may be split
    over lines.
    """
    lines = text.split("\n")
    if (
        all(char.isprintable() or char == "\n" for char in text)
        and '"""' not in text
        and "\\" not in text
        and not text.startswith('"')
        and not text.endswith('"')
        and text == text.strip()
        and all(line == line.rstrip() for line in lines)
    ):
        # ruff re-indents the lines after the first to the docstring's own indentation.
        rest = textwrap.dedent("\n".join(lines[1:])).split("\n")
        written = [f'{indent}"""{lines[0]}', *(indent + line if line else "" for line in rest)]
        written = [f'{written[0]}"""'] if len(lines) == 1 else [*written, f'{indent}"""']
        if all(len(line) <= LINE for line in written):
            return "\n".join(written)
    literal = _str(text)
    if text == text.strip() and not text.endswith(("'", "\\")) and len(indent + literal) <= LINE:
        return indent + literal
    return None


def isort_key(name: str) -> tuple[int, tuple[int | str, ...], str]:
    """Order imported names as isort (and ruff's ``I`` rules, by default) does.

    ``CONSTANTS`` first, then ``Classes``, then the rest; within each, ignoring case, with
    numbers compared by value (``Int8`` before ``Int16``).
    """
    return (_name_kind(name), _natural(name.lower()), name)


def all_key(name: str) -> tuple[int, tuple[int | str, ...]]:
    """Order the names of ``__all__`` as ruff's RUF022 does.

    As :func:`isort_key`, but within each kind case matters, as it does in a natural sort:
    character by character, so ``IMUStatus`` comes before ``Imu`` and ``DoThing`` before
    ``Do_Request``.
    """
    return (_name_kind(name), _natural(name))


def _name_kind(name: str) -> int:
    """0 for ``CONSTANTS``, 1 for ``Classes``, 2 for the rest."""
    return 0 if len(name) > 1 and name.isupper() else 1 if name[:1].isupper() else 2


def _natural(name: str) -> tuple[int | str, ...]:
    """``name`` in runs of digits (their values) and of the rest, for a natural sort."""
    return tuple(int(run) if run.isdigit() else run for run in re.split(r"(\d+)", name))


def import_line(module: str, names: list[str]) -> str:
    """One import statement, split one name a line (with a trailing comma) when long.

    It is split past ruff's default line length, 88, not ours: isort joins a split import
    that fits its line length again unless it ends with a comma, so the comma keeps a split
    import as it is in projects with any line length.
    """
    flat = f"from {module} import {', '.join(names)}"
    if len(flat) <= IMPORT_LINE:
        return flat
    inner = "".join(f"    {name},\n" for name in names)
    return f"from {module} import (\n{inner})"
