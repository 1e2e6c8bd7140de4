"""Write a typed Python module that declares interface classes statically.

:func:`generate_module` turns specs (or classes built by :mod:`srvwire.models`) into the source of
a module in which every message, service and action is an ordinary class statement, so editors
and ``mypy --strict`` see each field with its real type (``int``, ``float``, ``str``,
``list[float]``, a nested class). :func:`write_module` writes that source to a file. The command
``srvwire gen`` is a thin shell over the two.

Invariants
----------
* **Same classes as the builder.** Each field is written with the annotation
  :mod:`srvwire.models` composes at run time, spelled with its public aliases (``Int32``,
  ``Float32``, ``AcceptBase64``...) and ``Field(...)`` bounds, and with the same defaults, alias
  and description. Constants, ``type_name`` and ``spec`` are attached the same way, so a
  generated class validates, serializes, documents itself (JSON schema) and compares exactly
  like the class :func:`~srvwire.models.build_message` makes. The only differences: the
  ``spec`` leaves out ``path`` (where the files were on the generating machine), and when two
  interfaces in one module share a name (``a/Point`` and ``b/Point``) both classes are renamed
  ``a_msg_Point``/``b_msg_Point`` (their JSON schema title stays ``Point``).
* **Self-contained.** Every message a generated class nests is generated in the same module,
  before its first use; the module imports only ``typing``, ``pydantic``, :mod:`srvwire.idl`
  and :mod:`srvwire.models`.
* **No name capture.** An imported helper whose name equals a generated class (``std_msgs``
  has ``String``, ``Int32`` and ``Bool``) is imported under a leading underscore instead. In a
  class with a field named ``list``, ``list[...]`` is written ``_builtins.list[...]``. Constants
  and ``type_name`` come before the fields, so a field named ``str`` or ``bool`` shadows nothing.
  A constant named like a class that the same message nests cannot be written and is refused.
* **Deterministic.** The output depends only on the input: same specs, same text.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import typing
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeAlias

from srvwire.errors import InterfaceError
from srvwire.idl import (
    ARRAY_PRIMITIVES_AS_BYTES,
    FLOAT_TYPES,
    INTEGER_RANGES,
    ActionSpec,
    ArrayKind,
    FieldSpec,
    MessageSpec,
    Scalar,
    ServiceSpec,
    TypeSpec,
)
from srvwire.models import (
    PRIMITIVE_ALIASES,
    Action,
    Message,
    Service,
    default_value,
    python_name,
)

__all__ = ["Interface", "SpecResolver", "generate_module", "write_module"]

Interface: TypeAlias = (
    MessageSpec | ServiceSpec | ActionSpec | type[Message] | type[Service] | type[Action]
)
"""What :func:`generate_module` accepts: a spec, or a class built from one."""

SpecResolver: TypeAlias = Callable[[TypeSpec], MessageSpec]
"""Given a nested element type (``package`` set, no array part), return its message spec."""

_LINE = 100  # longest line the writer aims for

_HELPERS = {
    "typing": ("Annotated", "ClassVar", "TypeAlias"),
    "pydantic": ("ConfigDict", "Field"),
    "srvwire.idl": (
        "ActionSpec",
        "ArrayKind",
        "ConstantSpec",
        "FieldSpec",
        "MessageSpec",
        "ServiceSpec",
        "TypeSpec",
    ),
    "srvwire.models": (
        "AcceptBase64",
        "Action",
        "Message",
        "Service",
        *sorted(PRIMITIVE_ALIASES.values()),
    ),
}
_MODULE_OF = {name: module for module, names in _HELPERS.items() for name in names}
_CONSTANT_TYPES = {
    **dict.fromkeys(INTEGER_RANGES, "int"),
    **dict.fromkeys(FLOAT_TYPES, "float"),
    "bool": "bool",
    "string": "str",
    "wstring": "str",
}


def generate_module(
    interfaces: Iterable[Interface],
    *,
    resolve_spec: SpecResolver | None = None,
    docstring: str | None = None,
) -> str:
    """Return the source of a module declaring the classes of ``interfaces``.

    ``interfaces`` are message, service and action specs, or classes built from them. The
    messages they nest are included too: found among ``interfaces``, inside the given classes,
    or else through ``resolve_spec``; a nested type found nowhere is an
    :class:`~srvwire.errors.InterfaceError`. ``docstring`` replaces the module docstring, which
    otherwise lists the interfaces.
    """
    plan = _Plan(resolve_spec)
    for interface in interfaces:
        plan.add(interface)
    return _Writer(plan).module(docstring)


def write_module(
    path: str | os.PathLike[str],
    interfaces: Iterable[Interface],
    *,
    resolve_spec: SpecResolver | None = None,
    docstring: str | None = None,
) -> Path:
    """Write :func:`generate_module`'s source to ``path`` (UTF-8) and return the path."""
    source = generate_module(interfaces, resolve_spec=resolve_spec, docstring=docstring)
    target = Path(path)
    target.write_text(source, encoding="utf-8")
    return target


# --- what goes in the module, in which order ------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Item:
    """One top-level interface: a message, service or action, with its type name."""

    spec: MessageSpec | ServiceSpec | ActionSpec
    type_name: str

    @property
    def kind(self) -> str:
        return self.type_name.split("/")[1]

    @property
    def parts(self) -> tuple[MessageSpec, ...]:
        if isinstance(self.spec, ServiceSpec):
            return (self.spec.request, self.spec.response)
        if isinstance(self.spec, ActionSpec):
            return (self.spec.goal, self.spec.result, self.spec.feedback)
        return (self.spec,)


class _Plan:
    """Collects the items to write, dependencies first, and finds the specs they nest."""

    def __init__(self, resolve_spec: SpecResolver | None) -> None:
        self._resolve_spec = resolve_spec
        self._known: dict[str, MessageSpec] = {}  # pkg/msg/Name -> spec, for nested lookups
        self.requested: list[_Item] = []
        self.items: list[_Item] = []

    def add(self, interface: Interface) -> None:
        if isinstance(interface, MessageSpec | ServiceSpec | ActionSpec):
            item = _Item(interface, interface.type_name)
        elif isinstance(interface, type) and issubclass(interface, Message | Service | Action):
            item = _Item(interface.spec, interface.type_name)
            for cls in _parts_of(interface):
                self._learn_nested(cls)
        else:
            raise TypeError(f"generate_module takes specs or srvwire classes, not {interface!r}")
        if isinstance(item.spec, MessageSpec):
            self._known.setdefault(item.type_name, item.spec)
        if all(item.type_name != other.type_name for other in self.requested):
            self.requested.append(item)

    def _learn_nested(self, cls: type[Message]) -> None:
        for info in cls.model_fields.values():
            for nested in _message_classes(info.annotation):
                if nested.type_name not in self._known:
                    self._known[nested.type_name] = nested.spec
                    self._learn_nested(nested)

    def ordered(self) -> list[_Item]:
        done: set[str] = set()
        for item in self.requested:
            self._visit(item, done, ())
        return self.items

    def _visit(self, item: _Item, done: set[str], chain: tuple[str, ...]) -> None:
        if item.type_name in done:
            return
        if item.type_name in chain:
            cycle = " -> ".join((*chain[chain.index(item.type_name) :], item.type_name))
            raise InterfaceError(f"a message cannot contain itself: {cycle}")
        for part in item.parts:
            for field in part.fields:
                if not field.type.is_primitive:
                    nested = self.lookup(field.type, part)
                    self._visit(_Item(nested, nested.type_name), done, (*chain, item.type_name))
        done.add(item.type_name)
        self.items.append(item)

    def lookup(self, type_: TypeSpec, owner: MessageSpec) -> MessageSpec:
        name = type_.qualified_name
        spec = self._known.get(name)
        if spec is None:
            if self._resolve_spec is None:
                raise InterfaceError(
                    f"{owner.name} nests {name}, which is not among the interfaces given, "
                    "and no resolve_spec was given to find it"
                )
            spec = self._known[name] = self._resolve_spec(type_.element)
        return spec


def _parts_of(cls: type[Message] | type[Service] | type[Action]) -> tuple[type[Message], ...]:
    if issubclass(cls, Service):
        return (cls.Request, cls.Response)
    if issubclass(cls, Action):
        return (cls.Goal, cls.Result, cls.Feedback)
    return (cls,)


def _message_classes(annotation: Any) -> Iterator[type[Message]]:
    if isinstance(annotation, type) and issubclass(annotation, Message):
        yield annotation
    for argument in typing.get_args(annotation):
        yield from _message_classes(argument)


# --- writing ---------------------------------------------------------------------------------


class _Writer:
    """Turns a plan into source text; knows the Python name of every class and helper."""

    def __init__(self, plan: _Plan) -> None:
        self.plan = plan
        self.items = plan.ordered()
        self.class_names = self._class_names()
        self.used: set[str] = set()
        self.builtins_used = False

    def _class_names(self) -> dict[str, str]:
        """Map each type name (``pkg/msg/Name``, ``pkg/srv/Name_Request``...) to a class name.

        A class takes its ROS name (``Point``, ``AddTwoInts_Request``) unless another class of
        the module would take the same one; then both are prefixed with their package and kind
        (``geometry_msgs_msg_Point``). ROS type names hold no ``_``, so these cannot collide
        with a ROS name.
        """
        wanted: dict[str, tuple[str, str]] = {}  # type name -> (ROS name, qualified fallback)
        for item in self.items:
            spec = item.spec
            fallback = f"{spec.package}_{item.kind}_{spec.name}"
            wanted[item.type_name] = (spec.name, fallback)
            if not isinstance(spec, MessageSpec):
                for part in item.parts:
                    suffix = part.name.removeprefix(spec.name)
                    suffix = suffix if suffix != part.name else f"_{part.name}"
                    wanted[_part_type_name(item, part)] = (part.name, f"{fallback}{suffix}")
        counts: dict[str, int] = {}
        for short, _ in wanted.values():
            counts[short] = counts.get(short, 0) + 1
        names = {
            key: short if counts[short] == 1 else full for key, (short, full) in wanted.items()
        }
        if len(set(names.values())) != len(names):
            raise InterfaceError("two interfaces would get the same class name; split the module")
        return names

    def name(self, helper: str) -> str:
        """Return the local name of an imported helper, recording that it is used."""
        self.used.add(helper)
        return f"_{helper}" if helper in self.class_names.values() else helper

    # module ----------------------------------------------------------------------------------

    def module(self, docstring: str | None) -> str:
        body: list[str] = []
        specs: list[str] = []
        for item in self.items:
            if isinstance(item.spec, MessageSpec):
                body.append(self.message(item.spec, item.type_name))
                specs.append(self.assign_spec(item.type_name, item.spec))
                continue
            for part in item.parts:
                body.append(self.message(part, _part_type_name(item, part)))
            body.append(self.group(item))
            specs.append(self.assign_spec(item.type_name, item.spec))
            for part in item.parts:
                attribute = _part_attribute(item, part)
                specs.append(
                    f"{self.class_names[_part_type_name(item, part)]}.spec = "
                    f"{self.class_names[item.type_name]}.spec.{attribute}"
                )
        if docstring is None:
            listed = "\n".join(f"* ``{item.type_name}``" for item in self.plan.requested)
            docstring = (
                f"Interface classes generated by srvwire for:\n\n{listed}\n\n"
                "Do not edit this file: change the interface files and generate it again."
            )
        everything = sorted(self.class_names.values())
        parts = [
            _docstring(docstring, "") + "\n\n" + self.imports(),
            _list_assignment("__all__", everything),
            *body,
            "# What the interface files say, as srvwire.parser reads them (paths left out).\n"
            + "\n".join(specs),
        ]
        return "\n\n\n".join(part.rstrip("\n") for part in parts if part) + "\n"

    def imports(self) -> str:
        lines: list[str] = []
        if self.builtins_used:
            lines.append("import builtins as _builtins")
        groups: list[list[str]] = [lines, [], []]
        for module, names in _HELPERS.items():
            chosen = sorted(name for name in names if name in self.used)
            if not chosen:
                continue
            spelled = [n if self.name(n) == n else f"{n} as _{n}" for n in chosen]
            group = groups[0 if module == "typing" else 1 if module == "pydantic" else 2]
            group.append(_import_line(module, spelled))
        return "\n\n".join("\n".join(group) for group in groups if group)

    # classes ---------------------------------------------------------------------------------

    def message(self, spec: MessageSpec, type_name: str) -> str:
        class_name = self.class_names[type_name]
        nested = {
            self.class_names[f.type.qualified_name] for f in spec.fields if not f.type.is_primitive
        }
        for constant in spec.constants:
            if constant.name in nested:
                raise InterfaceError(
                    f"{type_name}: constant {constant.name} has the name of the class of one of "
                    "its fields, so the module cannot name both; rename one"
                )
        shadowed_list = any(python_name(f.name) == "list" for f in spec.fields)
        lines = [f"class {class_name}({self.name('Message')}):"]
        if spec.doc:
            lines.append(_docstring(spec.doc, "    "))
            lines.append("")
        class_var = self.name("ClassVar")
        if class_name != spec.name:
            lines.append(f"    model_config = {self.name('ConfigDict')}(title={_str(spec.name)})")
        lines.append(f"    type_name: {class_var}[str] = {_str(type_name)}")
        if spec.constants:
            lines.append("")
        for constant in spec.constants:
            python_type = _CONSTANT_TYPES[constant.type.name]
            value = _scalar(_as_written(constant.type.name, constant.value))
            lines.append(f"    {constant.name}: {class_var}[{python_type}] = {value}")
        if spec.fields:
            lines.append("")
        for field in spec.fields:
            lines.append(self.field(field, shadowed_list))
        return "\n".join(lines)

    def field(self, field: FieldSpec, shadowed_list: bool) -> str:
        type_ = field.type
        if type_.is_primitive:
            element = self.name(PRIMITIVE_ALIASES[type_.name])
            if type_.string_bound is not None:
                element = (
                    f"{self.name('Annotated')}[{element}, "
                    f"{self.name('Field')}(max_length={type_.string_bound})]"
                )
        else:
            element = self.class_names[type_.qualified_name]
        annotation = element
        if type_.is_array:
            if shadowed_list:
                self.builtins_used = True
            annotation = f"{'_builtins.list' if shadowed_list else 'list'}[{element}]"
            metadata: list[str] = []
            if type_.array is ArrayKind.FIXED:
                metadata.append(
                    f"{self.name('Field')}(min_length={type_.size}, max_length={type_.size})"
                )
            elif type_.array is ArrayKind.BOUNDED:
                metadata.append(f"{self.name('Field')}(max_length={type_.size})")
            if type_.is_primitive and type_.name in ARRAY_PRIMITIVES_AS_BYTES:
                metadata.append(self.name("AcceptBase64"))
            if metadata:
                annotation = f"{self.name('Annotated')}[{annotation}, {', '.join(metadata)}]"
        keywords: list[str] = []
        name = python_name(field.name)
        if name != field.name:
            keywords.append(f"alias={_str(field.name)}")
        if field.doc:
            keywords.append(f"description={_str(field.doc)}")
        if type_.is_primitive:
            value = default_value(field)
            if isinstance(value, list):
                default = f"default_factory=lambda: {self.list_value(field, value)}"
            elif not keywords:
                return _assignment(name, annotation, "", [_scalar(value)])
            else:
                default = f"default={_scalar(value)}"
        elif not type_.is_array:
            default = f"default_factory=lambda: {element}()"
        elif type_.array is ArrayKind.FIXED:
            default = f"default_factory=lambda: [{element}() for _ in range({type_.size})]"
        else:
            default = "default_factory=lambda: []"
        return _assignment(name, annotation, self.name("Field"), [default, *keywords])

    def list_value(self, field: FieldSpec, value: list[Scalar]) -> str:
        if field.default is None and value:  # N zero values of a fixed array
            return f"[{_scalar(value[0])}] * {len(value)}"
        return "[" + ", ".join(_scalar(item) for item in value) + "]"

    def group(self, item: _Item) -> str:
        spec = item.spec
        assert not isinstance(spec, MessageSpec)
        base = "Service" if isinstance(spec, ServiceSpec) else "Action"
        class_var = self.name("ClassVar")
        lines = [f"class {self.class_names[item.type_name]}({self.name(base)}):"]
        for part in item.parts:
            attribute = _part_attribute(item, part).capitalize()
            target = self.class_names[_part_type_name(item, part)]
            lines.append(f"    {attribute}: {self.name('TypeAlias')} = {target}")
        lines.append(f"    type_name: {class_var}[str] = {_str(item.type_name)}")
        text_lines = spec.text.splitlines(keepends=True)
        if len(text_lines) <= 1:
            lines.append(f"    text: {class_var}[str] = {_str(spec.text)}")
        else:
            lines.append(f"    text: {class_var}[str] = (")
            lines.extend(f"        {_str(line)}" for line in text_lines)
            lines.append("    )")
        return "\n".join(lines)

    # specs -----------------------------------------------------------------------------------

    def assign_spec(self, type_name: str, spec: MessageSpec | ServiceSpec | ActionSpec) -> str:
        class_name = self.class_names[type_name]
        overrides = {} if isinstance(spec, MessageSpec) else {"text": f"{class_name}.text"}
        head = f"{class_name}.spec = "
        return head + self.literal(spec, 0, len(head), overrides)

    def literal(
        self, value: Any, indent: int, column: int, overrides: dict[str, str] | None = None
    ) -> str:
        """Spell a spec value as a Python expression starting at ``column``, wrapped to fit.

        ``indent`` is the indentation of the line the value starts on; wrapped items are
        indented four spaces more.
        """
        pad = " " * (indent + 4)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            arguments: list[tuple[str, Any]] = []
            for f in dataclasses.fields(value):
                item = getattr(value, f.name)
                if f.name != "path" and item != f.default:
                    arguments.append((f.name, item))
            head = self.name(type(value).__name__)
            flat = f"{head}(" + ", ".join(
                f"{key}={(overrides or {}).get(key) or self.literal(item, 0, 0)}"
                for key, item in arguments
            )
            flat += ")"
            if column + len(flat) < _LINE and "\n" not in flat:
                return flat
            lines: list[str] = []
            for key, item in arguments:
                spelled = (overrides or {}).get(key)
                if spelled is None:
                    spelled = self.literal(item, indent + 4, len(pad) + len(key) + 1)
                lines.append(f"{pad}{key}={spelled},\n")
            inner = "".join(lines)
            return f"{head}(\n{inner}{' ' * indent})"
        if isinstance(value, tuple):
            flat_items = [self.literal(item, 0, 0) for item in value]
            flat = "(" + ", ".join(flat_items) + ("," if len(flat_items) == 1 else "") + ")"
            if column + len(flat) < _LINE and "\n" not in flat:
                return flat
            items = [self.literal(item, indent + 4, len(pad)) for item in value]
            return "(\n" + "".join(f"{pad}{item},\n" for item in items) + " " * indent + ")"
        if isinstance(value, enum.Enum):
            return f"{self.name(type(value).__name__)}.{value.name}"
        return _scalar(value)


def _assignment(name: str, annotation: str, call: str, arguments: list[str]) -> str:
    """Write ``name: annotation = call(arguments)`` (no call when ``call`` is empty), wrapped."""
    value = f"{call}({', '.join(arguments)})" if call else arguments[0]
    head = f"    {name}: {annotation} = "
    if len(head) + len(value) <= _LINE:
        return head + value
    annotated = annotation.endswith("]") and "[" in annotation
    if len(head) + len(call) + 1 > _LINE and annotated:
        outer, _, inner = annotation.partition("[")
        head = f"    {name}: {outer}[\n        {inner[:-1]}\n    ] = "
        if len("    ] = ") + len(value) <= _LINE:
            return head + value
    if not call:
        return head + value
    lines = "".join(f"        {argument},\n" for argument in arguments)
    return f"{head}{call}(\n{lines}    )"


def _part_type_name(item: _Item, part: MessageSpec) -> str:
    return f"{item.type_name.rpartition('/')[0]}/{part.name}"


def _part_attribute(item: _Item, part: MessageSpec) -> str:
    spec = item.spec
    if isinstance(spec, ServiceSpec):
        return "request" if part is spec.request else "response"
    assert isinstance(spec, ActionSpec)
    return "goal" if part is spec.goal else "result" if part is spec.result else "feedback"


def _as_written(type_name: str, value: Scalar) -> Scalar:
    if type_name in FLOAT_TYPES and not isinstance(value, bool) and isinstance(value, int):
        return float(value)
    return value


# --- literals --------------------------------------------------------------------------------


def _scalar(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "(1e999 - 1e999)"  # nan, written without a name a field could shadow
        if math.isinf(value):
            return "1e999" if value > 0 else "-1e999"
        return repr(value)
    if isinstance(value, str):
        return _str(value)
    raise InterfaceError(f"cannot write {value!r} as a literal")


_ESCAPES = {"\\": "\\\\", '"': '\\"', "\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _str(text: str) -> str:
    """A double-quoted string literal; unprintable characters are escaped."""
    out: list[str] = []
    for char in text:
        if char in _ESCAPES:
            out.append(_ESCAPES[char])
        elif char.isprintable():
            out.append(char)
        elif ord(char) <= 0xFF:
            out.append(f"\\x{ord(char):02x}")
        elif ord(char) <= 0xFFFF:
            out.append(f"\\u{ord(char):04x}")
        else:
            out.append(f"\\U{ord(char):08x}")
    return '"' + "".join(out) + '"'


def _docstring(text: str, indent: str) -> str:
    """A docstring holding ``text``; ``inspect.cleandoc`` of it gives ``cleandoc(text)``."""
    safe = '"""' not in text and "\\" not in text and not text.endswith('"')
    if not safe or not all(c.isprintable() or c == "\n" for c in text):
        return f"{indent}{_str(text)}"
    lines = text.split("\n")
    body = "\n".join(f"{indent}{line}" if line else "" for line in lines[1:])
    if len(lines) == 1:
        return f'{indent}"""{text}"""'
    return f'{indent}"""{lines[0]}\n{body}\n{indent}"""'


def _import_line(module: str, names: list[str]) -> str:
    flat = f"from {module} import {', '.join(names)}"
    if len(flat) <= _LINE:
        return flat
    inner = "".join(f"    {name},\n" for name in names)
    return f"from {module} import (\n{inner})"


def _list_assignment(target: str, names: list[str]) -> str:
    flat = f"{target} = [{', '.join(_str(n) for n in names)}]"
    if len(flat) <= _LINE:
        return flat
    inner = "".join(f"    {_str(name)},\n" for name in names)
    return f"{target} = [\n{inner}]"
