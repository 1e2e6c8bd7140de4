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
* **Self-contained, or beside its siblings.** Every message a generated class nests is
  generated in the same module, before its first use; the module imports only ``typing``,
  ``pydantic``, :mod:`srvwire.idl` and :mod:`srvwire.models`. The one exception is a package
  named in ``siblings``: its messages are not copied but used from the module of that name in
  the same Python package (``from . import std_msgs``, then ``std_msgs.Header``), which is how
  ``srvwire gen`` into a folder writes one module per package, so that a message nested by
  two of them is one class. Packages whose messages nest each other (``a`` nests a message of
  ``b``, which nests one of ``a``) cannot be modules that import each other, since each would
  need a class of the other before its own end: :func:`generate_modules` writes their classes
  together in one module (``_a__b``), and the module of each package takes its own classes
  from there, so the modules import in any order.
* **No name capture.** An imported helper whose name equals a generated class (``std_msgs``
  has ``String``, ``Int32`` and ``Bool``) is reached through its module, imported under a
  leading underscore (``import srvwire.models as _models``, then ``_models.String``). In a
  class with a field named ``list`` or ``bytes``, that builtin is written ``_builtins.list``
  (``_builtins.bytes``). Constants and ``type_name`` come before the fields, so a field named
  ``str`` or ``bool`` shadows nothing.
  A constant named like a class that the same message nests cannot be written and is refused.
* **Deterministic.** The output depends only on the input: same specs, same text.
* **Lint-clean as written.** The module passes ruff (its default rules, and ``E,F,W,I,B,UP,
  ASYNC,RUF`` at line length 100 with isort's default settings), ``ruff format`` leaves it as
  it is (line length 100), and ``mypy --strict`` accepts it. :mod:`srvwire.pysource` lays out
  every statement as ruff would; imports never use ``from m import a as b``, which isort places
  differently depending on its ``combine-as-imports`` setting.
"""

from __future__ import annotations

import dataclasses
import enum
import os
import textwrap
import typing
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
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
from srvwire.models import Action, Message, Service, default_value, python_name, zero_value
from srvwire.primitives import PRIMITIVE_ALIASES
from srvwire.pysource import (
    LINE,
    Call,
    Expr,
    Keyword,
    Text,
    all_key,
    as_docstring,
    expression,
    import_line,
    isort_key,
    scalar,
    statement,
)

__all__ = ["Interface", "SpecResolver", "generate_module", "generate_modules", "write_module"]

Interface: TypeAlias = (
    MessageSpec | ServiceSpec | ActionSpec | type[Message] | type[Service] | type[Action]
)
"""What :func:`generate_module` accepts: a spec, or a class built from one."""

SpecResolver: TypeAlias = Callable[[TypeSpec], MessageSpec]
"""Given a nested element type (``package`` set, no array part), return its message spec."""

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
        "ServiceRequest",
        "TypedService",
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
    siblings: Collection[str] = (),
) -> str:
    """Return the source of a module declaring the classes of ``interfaces``.

    ``interfaces`` are message, service and action specs, or classes built from them. The
    messages they nest are included too: found among ``interfaces``, inside the given classes,
    or else through ``resolve_spec``; a nested type found nowhere is an
    :class:`~srvwire.errors.InterfaceError`. The messages of the packages in ``siblings`` are
    not included but imported from the modules of the same names beside this one, under their
    ROS names (which such a module gives them unless two of its classes share a name: then
    :func:`generate_modules` knows the names they take). ``docstring`` replaces the module
    docstring, which otherwise lists the interfaces.
    """
    plan = _Plan(resolve_spec, frozenset(siblings))
    for interface in interfaces:
        plan.add(interface)
    return _Writer(plan).module(docstring)


def generate_modules(
    groups: Mapping[str, Iterable[Interface]], *, resolve_spec: SpecResolver | None = None
) -> dict[str, str]:
    """Return the source of each module of a Python package holding ``groups``, by module name.

    ``groups`` maps each interface package to its interfaces. Each package gets a module of its
    name, which imports the messages it nests from the other packages' modules (as
    :func:`generate_module` does with ``siblings``), by the names those modules give them
    (``p.p_msg_Arrays`` when ``p`` has a message and a service both named ``Arrays``); a message
    nested from a package whose group does not hold it is an
    :class:`~srvwire.errors.InterfaceError`. Packages whose messages nest each other,
    directly or through others, have their classes written together in one more module,
    ``_`` and their names joined by ``__`` (``_my_nav__my_robot``), and each of their modules
    takes its own classes from there under the names it would have given them. The packages'
    modules come first, in the order of ``groups``, then these.
    """
    members = {package: list(interfaces) for package, interfaces in groups.items()}
    plans = {
        package: _plan_of(interfaces, resolve_spec, frozenset(members) - {package})
        for package, interfaces in members.items()
    }
    # What each package's module names its classes, which the modules that import them use.
    exported = {package: _class_names(plan.ordered()) for package, plan in plans.items()}
    writers = {package: _Writer(plan, exported) for package, plan in plans.items()}
    # The sibling packages whose messages each module uses, its own nested ones' included.
    nests = {
        package: frozenset(name.split("/")[0] for name in writer.plan.imported)
        for package, writer in writers.items()
    }
    facades: dict[str, str] = {}
    shared_modules: dict[str, str] = {}
    for packages in _import_cycles(nests):
        shared = "_" + "__".join(packages)
        together = [interface for package in packages for interface in members[package]]
        plan = _plan_of(together, resolve_spec, frozenset(members) - set(packages))
        writer = _Writer(plan, exported)
        shared_modules[shared] = writer.module(None)
        for package in packages:
            others = [other for other in packages if other != package]
            facades[package] = writers[package].facade(shared, writer.class_names, others)
    sources = {
        package: facades.get(package) or writers[package].module(None) for package in members
    }
    return sources | shared_modules


def _plan_of(
    interfaces: Iterable[Interface], resolve_spec: SpecResolver | None, siblings: frozenset[str]
) -> _Plan:
    plan = _Plan(resolve_spec, siblings)
    for interface in interfaces:
        plan.add(interface)
    return plan


def _import_cycles(nests: Mapping[str, frozenset[str]]) -> list[tuple[str, ...]]:
    """The groups of two or more packages that nest each other, each sorted (Tarjan's SCCs)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[tuple[str, ...]] = []

    def visit(package: str) -> None:
        index[package] = low[package] = len(index)
        stack.append(package)
        for other in sorted(nests[package] & nests.keys()):
            if other not in index:
                visit(other)
                low[package] = min(low[package], low[other])
            elif other in stack:
                low[package] = min(low[package], index[other])
        if low[package] == index[package]:
            component = stack[stack.index(package) :]
            del stack[stack.index(package) :]
            if len(component) > 1:
                found.append(tuple(sorted(component)))

    for package in sorted(nests):
        if package not in index:
            visit(package)
    return sorted(found)


def write_module(
    path: str | os.PathLike[str],
    interfaces: Iterable[Interface],
    *,
    resolve_spec: SpecResolver | None = None,
    docstring: str | None = None,
    siblings: Collection[str] = (),
) -> Path:
    """Write :func:`generate_module`'s source to ``path`` (UTF-8) and return the path."""
    source = generate_module(
        interfaces, resolve_spec=resolve_spec, docstring=docstring, siblings=siblings
    )
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

    def __init__(self, resolve_spec: SpecResolver | None, siblings: frozenset[str]) -> None:
        self._resolve_spec = resolve_spec
        self.siblings = siblings
        self.imported: dict[str, str] = {}  # type name -> sibling package, for nested messages
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
        """The items, each after the ones it nests; the same list each time it is asked."""
        self.items = []
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
                if field.type.package in self.siblings:
                    self.imported[field.type.qualified_name] = field.type.package
                elif not field.type.is_primitive:
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


def _part_type_name(item: _Item, part: MessageSpec) -> str:
    return f"{item.type_name.rpartition('/')[0]}/{part.name}"


def _part_attribute(item: _Item, part: MessageSpec) -> str:
    spec = item.spec
    if isinstance(spec, ServiceSpec):
        return "request" if part is spec.request else "response"
    assert isinstance(spec, ActionSpec)
    return "goal" if part is spec.goal else "result" if part is spec.result else "feedback"


def _class_names(items: Iterable[_Item]) -> dict[str, str]:
    """Map each type name (``pkg/msg/Name``, ``pkg/srv/Name_Request``...) to a class name.

    The one place that names the classes of a module: the module that defines them and every
    module that imports them from it use these names. A class takes its ROS name (``Point``,
    ``AddTwoInts_Request``) unless another class of the module would take the same one; then
    both are prefixed with their package and kind (``geometry_msgs_msg_Point``). ROS type names
    hold no ``_``, so these cannot collide with a ROS name.
    """
    wanted: dict[str, tuple[str, str]] = {}  # type name -> (ROS name, qualified fallback)
    for item in items:
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
    names = {key: short if counts[short] == 1 else full for key, (short, full) in wanted.items()}
    if len(set(names.values())) != len(names):
        raise InterfaceError("two interfaces would get the same class name; split the module")
    return names


# --- writing ---------------------------------------------------------------------------------


class _Writer:
    """Turns a plan into source text; knows the Python name of every class and helper.

    ``exported`` holds, by sibling package, the class names its module gives its types; a
    sibling not there is taken to give them their ROS names.
    """

    def __init__(
        self, plan: _Plan, exported: Mapping[str, Mapping[str, str]] | None = None
    ) -> None:
        self.plan = plan
        self.items = plan.ordered()
        self.class_names = _class_names(self.items)
        self.exported = exported or {}
        self.used: set[str] = set()
        self.builtins_used = False

    def class_of(self, type_name: str) -> str:
        """The expression naming the class of the message ``type_name`` in this module."""
        if type_name in self.class_names:
            return self.class_names[type_name]
        package = self.plan.imported[type_name]
        if package not in self.exported:
            return f"{package}.{type_name.rpartition('/')[2]}"
        name = self.exported[package].get(type_name)
        if name is None:
            raise InterfaceError(
                f"{type_name} is nested but not among the interfaces of {package}'s module; "
                f"add it to the group of {package}"
            )
        return f"{package}.{name}"

    def name(self, helper: str) -> str:
        """Return the local name of an imported helper, recording that it is used."""
        self.used.add(helper)
        if helper in self.class_names.values():
            return f"{_module_alias(_MODULE_OF[helper])}.{helper}"
        return helper

    # module ----------------------------------------------------------------------------------

    def module(self, docstring: str | None) -> str:
        body: list[str] = []
        specs: list[str] = []
        for item in self.items:
            if isinstance(item.spec, MessageSpec):
                body.append(self.message(item.spec, item.type_name))
                specs.append(self.assign_spec(item.type_name, item.spec))
                continue
            answered_by = None
            if isinstance(item.spec, ServiceSpec):  # the Request names its Response class
                answered_by = self.class_names[_part_type_name(item, item.spec.response)]
            for part in item.parts:
                is_request = isinstance(item.spec, ServiceSpec) and part is item.spec.request
                body.append(
                    self.message(
                        part, _part_type_name(item, part), answered_by if is_request else None
                    )
                )
            body.append(self.group(item))
            specs.append(self.assign_spec(item.type_name, item.spec))
            for part in item.parts:
                attribute = _part_attribute(item, part)
                specs.append(
                    statement(
                        "",
                        f"{self.class_names[_part_type_name(item, part)]}.spec",
                        None,
                        f"{self.class_names[item.type_name]}.spec.{attribute}",
                    ).rstrip("\n")
                )
        if docstring is None:
            listed = "\n".join(f"* ``{item.type_name}``" for item in self.plan.requested)
            docstring = (
                f"Interface classes generated by srvwire for:\n\n{listed}\n\n"
                "Do not edit this file: change the interface files and generate it again."
            )
        names = sorted(self.class_names.values(), key=all_key)
        everything = Call("[", tuple(Text(name) for name in names), "]")
        # isort puts one blank line between the imports and a statement that is not a class.
        header = "\n\n".join(
            part
            for part in (
                as_docstring(docstring, "") or statement("", "__doc__", None, Text(docstring)),
                self.imports(),
                statement("", "__all__", None, everything),
            )
            if part
        )
        parts = [
            header,
            *body,
            "# What the interface files say, as srvwire.parser reads them (paths left out).\n"
            + "\n".join(specs),
        ]
        return "\n\n\n".join(part.rstrip("\n") for part in parts if part) + "\n"

    def facade(self, shared: str, shared_names: dict[str, str], others: Iterable[str]) -> str:
        """A module that takes its classes from the module ``shared`` (named ``shared_names``).

        ``others`` are the packages whose classes ``shared`` holds besides this module's. Each
        class keeps the name this module would give it, so the other modules reach it as they
        would if it were defined here.
        """
        listed = "\n".join(f"* ``{item.type_name}``" for item in self.plan.requested)
        why = textwrap.fill(
            f"They are defined in ``{shared}``, with those of {', '.join(others)}: the messages "
            "of these packages nest each other, so one module each could not be imported first.",
            LINE,
        )
        docstring = (
            f"Interface classes generated by srvwire for:\n\n{listed}\n\n{why}\n\n"
            "Do not edit this file: change the interface files and generate it again."
        )
        type_alias = self.name("TypeAlias")
        typing_import = (
            "from typing import TypeAlias"
            if type_alias == "TypeAlias"
            else "import typing as _typing"
        )
        names = sorted(self.class_names.values(), key=all_key)
        header = (
            as_docstring(docstring, "") or statement("", "__doc__", None, Text(docstring)),
            f"{typing_import}\n\n{import_line('.', [shared])}",
            statement("", "__all__", None, Call("[", tuple(Text(name) for name in names), "]")),
        )
        type_names = {name: type_name for type_name, name in self.class_names.items()}
        aliases = "\n".join(
            statement("", name, type_alias, f"{shared}.{shared_names[type_names[name]]}")
            for name in names
        )
        return "\n\n".join((*header, aliases)) + "\n"

    def imports(self) -> str:
        """The import block, as isort (ruff's ``I`` rules) would order it in a user's project.

        Two sections: the standard library (``builtins``, ``typing``), then third-party packages,
        where ``pydantic`` and ``srvwire`` both belong in a project that depends on srvwire.
        Names are sorted case-insensitively, as isort does.
        """
        standard = ["import builtins as _builtins"] if self.builtins_used else []
        third_party: list[str] = []
        from_imports: list[str] = []  # after the plain imports of their section
        for module, names in _HELPERS.items():
            group = standard if module == "typing" else third_party
            used = [name for name in names if name in self.used]
            if any(name in self.class_names.values() for name in used):
                group.append(f"import {module} as {_module_alias(module)}")
            chosen = sorted((n for n in used if n not in self.class_names.values()), key=isort_key)
            if chosen:
                (from_imports if group is third_party else group).append(
                    import_line(module, chosen)
                )
        standard.sort(key=lambda line: not line.startswith("import "))
        third_party.extend(from_imports)
        used_siblings = sorted({name.split("/")[0] for name in self.plan.imported}, key=isort_key)
        local = [import_line(".", used_siblings)] if used_siblings else []
        groups = (standard, third_party, local)
        return "\n\n".join("\n".join(group) for group in groups if group)

    # classes ---------------------------------------------------------------------------------

    def message(self, spec: MessageSpec, type_name: str, answered_by: str | None = None) -> str:
        class_name = self.class_names[type_name]
        nested = {
            self.class_of(f.type.qualified_name) for f in spec.fields if not f.type.is_primitive
        }
        for field in spec.fields:
            if python_name(field.name) in self.plan.siblings:
                raise InterfaceError(
                    f"{type_name}: field {field.name} has the name of the module of package "
                    f"{field.name}, which the module imports; rename one"
                )
        for constant in spec.constants:
            if constant.name in nested:
                raise InterfaceError(
                    f"{type_name}: constant {constant.name} has the name of the class of one of "
                    "its fields, so the module cannot name both; rename one"
                )
        shadowed = {python_name(f.name) for f in spec.fields} & {"list", "bytes"}
        bases = [self.name("Message")]
        if answered_by is not None:  # defined after this class, so named as a string
            bases.append(f'{self.name("ServiceRequest")}["{answered_by}"]')
        lines = [_class_line(class_name, bases)]
        if spec.doc:
            doc = as_docstring(spec.doc, "    ")
            lines.append(doc or statement("    ", "__doc__", None, Text(spec.doc)))
            lines.append("")
        class_var = self.name("ClassVar")
        if class_name != spec.name:
            config = Call(f"{self.name('ConfigDict')}(", (Keyword("title", Text(spec.name)),))
            lines.append(statement("    ", "model_config", None, config))
        lines.append(statement("    ", "type_name", f"{class_var}[str]", Text(type_name)))
        if spec.constants:
            lines.append("")
        for constant in spec.constants:
            python_type = _CONSTANT_TYPES[constant.type.name]
            value = expression(_as_written(constant.type.name, constant.value))
            lines.append(statement("    ", constant.name, f"{class_var}[{python_type}]", value))
        if spec.fields:
            lines.append("")
        for field in spec.fields:
            lines.append(self.field(field, shadowed))
        return "\n".join(lines)

    def field(self, field: FieldSpec, shadowed: set[str]) -> str:
        type_ = field.type
        # A field named `list` or `bytes` hides the builtin in the class body.
        list_, bytes_ = (self.builtin(name, shadowed) for name in ("list", "bytes"))
        is_bytes = type_.is_array and type_.is_primitive and type_.name in ARRAY_PRIMITIVES_AS_BYTES
        if is_bytes:
            element = bytes_
        elif type_.is_primitive:
            element = self.name(PRIMITIVE_ALIASES[type_.name])
            if type_.string_bound is not None:
                element = (
                    f"{self.name('Annotated')}[{element}, "
                    f"{self.name('Field')}(max_length={type_.string_bound})]"
                )
        else:
            element = self.class_of(type_.qualified_name)
        annotation: Expr = element
        if type_.is_array:
            annotation = element if is_bytes else f"{list_}[{element}]"
            metadata: list[str] = []
            if type_.array is ArrayKind.FIXED:
                metadata.append(
                    f"{self.name('Field')}(min_length={type_.size}, max_length={type_.size})"
                )
            elif type_.array is ArrayKind.BOUNDED:
                metadata.append(f"{self.name('Field')}(max_length={type_.size})")
            if is_bytes:
                metadata.append(self.name("AcceptBase64"))
            if metadata:
                annotation = Call(f"{self.name('Annotated')}[", (annotation, *metadata), "]")
        keywords: list[Keyword] = []
        name = python_name(field.name)
        if name != field.name:
            keywords.append(Keyword("alias", Text(field.name)))
        if field.doc:
            keywords.append(Keyword("description", Text(field.doc)))
        if type_.is_array and not is_bytes:  # as models._field_info
            keywords.append(Keyword("fail_fast", "True"))
        default: Keyword
        if type_.is_primitive and type_.array is ArrayKind.FIXED and field.default is None:
            # As models._field_info: N zero values made per instance, never at import.
            zero = scalar(zero_value(type_))
            zeros = f"{bytes_}({type_.size})" if is_bytes else f"[{zero}] * {type_.size}"
            default = Keyword("default_factory", f"lambda: {zeros}")
        elif type_.is_primitive:
            value = default_value(field)
            written = _bytes_value(value, bytes_) if isinstance(value, bytes) else None
            if isinstance(value, list):
                default = Keyword("default_factory", self.list_value(value, list_))
            elif not keywords:
                return statement("    ", name, annotation, written or expression(value))
            else:
                default = Keyword("default", written or expression(value))
        elif not type_.is_array:
            default = Keyword("default_factory", f"lambda: {element}()")
        elif type_.array is ArrayKind.FIXED:
            default = Keyword(
                "default_factory", f"lambda: [{element}() for _ in range({type_.size})]"
            )
        else:
            default = Keyword("default_factory", list_)
        call = Call(f"{self.name('Field')}(", (default, *keywords))
        return statement("    ", name, annotation, call)

    def builtin(self, name: str, shadowed: set[str]) -> str:
        """The builtin ``name`` as the class body can reach it: ``_builtins.name`` if shadowed."""
        if name not in shadowed:
            return name
        self.builtins_used = True
        return f"_builtins.{name}"

    def list_value(self, value: list[Scalar], list_: str) -> Expr:
        if not value:
            return list_  # `lambda: []` would be a lambda that only calls `list`
        return Call("lambda: [", tuple(expression(item) for item in value), "]")

    def group(self, item: _Item) -> str:
        spec = item.spec
        assert not isinstance(spec, MessageSpec)
        if isinstance(spec, ServiceSpec):
            request, response = (self.class_names[_part_type_name(item, p)] for p in item.parts)
            base = f"{self.name('TypedService')}[{request}, {response}]"
        else:
            base = self.name("Action")
        class_var = self.name("ClassVar")
        lines = [_class_line(self.class_names[item.type_name], [base])]
        for part in item.parts:
            attribute = _part_attribute(item, part).capitalize()
            target = self.class_names[_part_type_name(item, part)]
            lines.append(statement("    ", attribute, self.name("TypeAlias"), target))
        lines.append(statement("    ", "type_name", f"{class_var}[str]", Text(item.type_name)))
        lines.append(statement("    ", "text", f"{class_var}[str]", Text(spec.text)))
        return "\n".join(lines)

    # specs -----------------------------------------------------------------------------------

    def assign_spec(self, type_name: str, spec: MessageSpec | ServiceSpec | ActionSpec) -> str:
        class_name = self.class_names[type_name]
        overrides = {} if isinstance(spec, MessageSpec) else {"text": f"{class_name}.text"}
        return statement("", f"{class_name}.spec", None, self.literal(spec, overrides))

    def literal(self, value: Any, overrides: dict[str, str] | None = None) -> Expr:
        """Spell a spec value (a dataclass, tuple, enum member or scalar) as an expression."""
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            arguments: list[Keyword] = []
            for f in dataclasses.fields(value):
                item = getattr(value, f.name)
                if f.name != "path" and item != f.default:
                    spelled = (overrides or {}).get(f.name) or self.literal(item)
                    arguments.append(Keyword(f.name, spelled))
            return Call(f"{self.name(type(value).__name__)}(", tuple(arguments))
        if isinstance(value, tuple):
            return Call("(", tuple(self.literal(item) for item in value), ")")
        if isinstance(value, enum.Enum):
            return f"{self.name(type(value).__name__)}.{value.name}"
        return expression(value)


def _class_line(name: str, bases: list[str]) -> str:
    """``class name(bases):``, split as ruff format splits a line that is too long.

    A single base that is a subscript (``TypedService[A, B]``) is split inside its brackets.
    """
    line = f"class {name}({', '.join(bases)}):"
    if len(line) <= LINE:
        return line
    inner = "    " + ", ".join(bases)
    if len(inner) <= LINE:
        return f"class {name}(\n{inner}\n):"
    if len(bases) == 1 and bases[0].endswith("]"):
        head, _, arguments = bases[0][:-1].partition("[")
        items = arguments.split(", ")
        if len(f"        {arguments}") <= LINE:
            return f"class {name}(\n    {head}[\n        {arguments}\n    ],\n):"
        listed = "".join(f"        {item},\n" for item in items)
        return f"class {name}(\n    {head}[\n{listed}    ],\n):"
    return f"class {name}(\n" + "".join(f"    {base},\n" for base in bases) + "):"


def _bytes_value(value: bytes, bytes_: str) -> Expr:
    """Spell a ``bytes`` default: ``bytes(4)`` for zeros, else a literal (``b"\\x00\\xff"``)."""
    if value and not any(value):
        return f"{bytes_}({len(value)})"
    return 'b"' + "".join(f"\\x{octet:02x}" for octet in value) + '"'


def _as_written(type_name: str, value: Scalar) -> Scalar:
    if type_name in FLOAT_TYPES and not isinstance(value, bool) and isinstance(value, int):
        return float(value)
    return value


def _module_alias(module: str) -> str:
    return "_" + module.rpartition(".")[2]
