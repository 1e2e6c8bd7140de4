"""Turn interface specs into pydantic classes: messages, services and actions.

:func:`build_message`, :func:`build_service` and :func:`build_action` take the frozen specs of
:mod:`srvwire.idl` and return classes. Every message class, including the ``Request`` and
``Response`` of a service and the ``Goal``, ``Result`` and ``Feedback`` of an action, derives
from :class:`Message`; a service class derives from :class:`Service` and only groups its two
message classes with the type name, spec and text.

Invariants
----------
* **One annotation per ROS type.** Each primitive has one public annotated alias, defined in
  :mod:`srvwire.primitives` and re-exported here (:data:`Int32`, :data:`Float32`, ...). A
  field's annotation is that alias, optionally wrapped for a string bound, wrapped in
  ``list[...]`` for arrays, and wrapped again for array bounds and base64 input.
  :mod:`srvwire.codegen` writes the very same composition as source text, so a built class and
  a generated one validate, serialize and describe themselves (JSON schema) identically.
* **Constraints live in pydantic-core.** Ranges, lengths and strictness are declared with
  ``Strict()`` and ``Field(ge=, le=, min_length=, max_length=)``, so validation runs in Rust.
  Only a few checks call Python: the ``float32`` range (it must let ``inf`` and ``nan``
  through, which a ``ge``/``le`` pair cannot), a non-finite float spelled as a string or
  ``null``, and the reading and writing of byte arrays (once per field).
* **An array stops at its first invalid element** (``fail_fast=True`` in its ``Field``), so
  the work and the error list of a bad request do not grow with its element count.
* **Every field has a default.** A written default is used; otherwise the field takes its ROS
  zero value. Scalars share their immutable default; every list and nested message comes from
  a ``default_factory``, so two instances never share a mutable value. ``Request()`` with no
  arguments is always valid, as in ROS.
* **Building a class allocates no array.** The zero value of a fixed array (``int32[N]``,
  ``uint8[N]``, ``Point[N]``) comes from a ``default_factory`` too, so its ``N`` values exist
  only in an instance made without that field: loading, checking or showing a type costs the
  same for ``N = 4294967295`` as for ``N = 3``.
* **The wire name is the .srv name.** A field whose name is a Python keyword or an attribute of
  :class:`Message` (``from``, ``copy``, ``json``, ``model_config``, ``spec``, ...) is stored
  under :func:`python_name` (a trailing underscore: ``from_``) with ``alias=`` the .srv name.
  Input is accepted under either name, output always uses the .srv name, and validation error
  locations use the name the input used.
* **No module state.** Each ``build_*`` call builds new classes; callers that want one class per
  type (the loader) cache them.
* **A request knows its response, statically, and its service at run time.** A service's
  ``Request`` class also derives from :class:`ServiceRequest` parametrized with its ``Response``
  class, and the service class from :class:`TypedService` parametrized with both, so that a
  type checker can tell what ``client.call(name, SetSpeed.Request(...))`` returns. These
  generic bases add no field or config (pydantic sees none in them). Making a service class
  whose ``Request`` is a :class:`ServiceRequest` sets that class's
  :attr:`~ServiceRequest.service_` to the service (the first one made with it), so that a
  client types a call by the request it is given; no field can have that name (a field name
  never ends with ``_`` unless it is reserved, and ``service`` is not).

Decisions (``docs/types.md`` explains them for users): integers, floats, booleans and strings
are strict (no ``"5"`` for an int, no ``5.0`` or ``True`` for an int, no ``1`` for a bool; an
int is accepted for a float and becomes a float); ``float32`` and ``float64`` allow ``inf`` and
``nan``, which JSON output writes as the strings ``"Infinity"``/``"NaN"`` (a server or client
can choose ``null`` or the bare tokens instead: :data:`InfNan`, :func:`json_writer`) and input
reads in all three spellings; string bounds count characters (code points); ``byte``/``uint8``
arrays are ``bytes``, written as base64 text, and also read from lists of integers.

The JSON written for one :data:`InfNan` mode comes from a serializer built for that mode once
(:func:`json_writer`), from the class's own core schema with every model's
``ser_json_inf_nan`` set to the mode: pydantic chooses the spelling when it builds a
serializer, not per call.
"""

from __future__ import annotations

import functools
import keyword
import math
import re
import types
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Annotated, Any, ClassVar, Generic, TypeAlias, TypeVar, cast

import pydantic
import pydantic_core
from pydantic import ConfigDict, Field
from pydantic_core import (
    PydanticSerializationError,
    SchemaSerializer,
    SchemaValidator,
    core_schema,
)

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
from srvwire.primitives import (
    FLOAT32_BOUND,
    FLOAT32_MAX,
    INF_NAN_MODES,
    PRIMITIVE_ALIASES,
    PRIMITIVE_ANNOTATIONS,
    AcceptBase64,
    Bool,
    Byte,
    Char,
    Float32,
    Float64,
    InfNan,
    Int8,
    Int16,
    Int32,
    Int64,
    String,
    UInt8,
    UInt16,
    UInt32,
    UInt64,
    WString,
)
from srvwire.protocol import Id, ReadRequest, timeout_seconds

__all__ = [
    "FLOAT32_BOUND",
    "FLOAT32_MAX",
    "INF_NAN_MODES",
    "MAX_LISTED_ERRORS",
    "PRIMITIVE_ALIASES",
    "AcceptBase64",
    "Action",
    "Bool",
    "Byte",
    "CallReader",
    "Char",
    "Float32",
    "Float64",
    "InfNan",
    "Int8",
    "Int16",
    "Int32",
    "Int64",
    "Message",
    "ModelDecoder",
    "Resolver",
    "Service",
    "ServiceRequest",
    "String",
    "TypedService",
    "UInt8",
    "UInt16",
    "UInt32",
    "UInt64",
    "WString",
    "build_action",
    "build_message",
    "build_service",
    "default_size",
    "dump_json",
    "error_data",
    "json_writer",
    "largest_default",
    "listed_errors",
    "python_name",
    "reply_writer",
    "summarize_errors",
    "unencodable_strings",
    "validate_python",
    "validate_wire",
    "validation_errors",
    "values_past",
    "wire_validator",
    "zero_value",
]


# --- ROS zero values and written defaults ------------------------------------------------------


def _normalize(type_name: str, value: Scalar) -> Scalar:
    """Give a written value the Python type validation would give it (``1`` -> ``1.0``)."""
    if type_name in FLOAT_TYPES and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def zero_value(type_: TypeSpec) -> Scalar:
    """Return the ROS zero value of a primitive scalar type: ``False``, ``0``, ``0.0`` or ``""``."""
    if type_.name == "bool":
        return False
    if type_.name in INTEGER_RANGES:
        return 0
    if type_.name in FLOAT_TYPES:
        return 0.0
    if type_.name in PRIMITIVE_ALIASES:
        return ""
    raise InterfaceError(f"{type_} is not a primitive type, so it has no zero value")


def default_value(field: FieldSpec) -> Scalar | list[Scalar] | bytes:
    """Return the default of a primitive field: its written default, else the ROS zero value.

    Arrays give a new list (``N`` zero values for a fixed array ``T[N]``, else empty), and
    ``byte``/``uint8`` arrays ``bytes`` instead; floats are always floats. A nested message field
    has no such value: it defaults to a new instance.
    """
    type_ = field.type
    if not type_.is_primitive:
        raise InterfaceError(f"field {field.name!r} has the nested type {type_}, not a primitive")
    if _is_bytes(type_):
        if isinstance(field.default, tuple):
            return bytes(item for item in field.default if isinstance(item, int))
        return bytes(type_.size or 0) if type_.array is ArrayKind.FIXED else b""
    if isinstance(field.default, tuple):
        return [_normalize(type_.name, item) for item in field.default]
    if field.default is not None:
        return _normalize(type_.name, field.default)
    if not type_.is_array:
        return zero_value(type_)
    if type_.array is ArrayKind.FIXED:
        return [zero_value(type_)] * (type_.size or 0)
    return []


def default_size(
    type_: TypeSpec, nested: Callable[[str], MessageSpec], counted: dict[str, int]
) -> int:
    """How many values a field of ``type_`` holds in an instance made without it.

    A scalar holds one, a fixed array ``T[N]`` ``N`` (times those of ``T`` for a message), any
    other array none; a message holds those of its fields. ``nested`` gives the spec of a
    nested message by name (``pkg/msg/Name``); ``counted`` keeps each message's count, so a
    type reached many times is counted once. Only ints are multiplied, so a size that no
    instance could hold (``int32[4294967295]``) costs nothing to count.
    """
    each = 1
    if not type_.is_primitive:
        name = type_.qualified_name
        if name not in counted:
            fields = nested(name).fields
            counted[name] = sum(default_size(field.type, nested, counted) for field in fields)
        each = counted[name]
    if type_.array is ArrayKind.FIXED:
        return each * (type_.size or 0)
    return 0 if type_.is_array else each


def largest_default(
    part: MessageSpec, nested: Callable[[str], MessageSpec], counted: dict[str, int]
) -> tuple[int, int, FieldSpec]:
    """The values an instance of ``part`` made without its fields holds (see
    :func:`default_size`), and those of its largest field, with that field; ``part`` has one."""
    sizes = [(default_size(field.type, nested, counted), field) for field in part.fields]
    size, field = max(sizes, key=lambda pair: pair[0])
    return sum(size for size, _ in sizes), size, field


def values_past(
    limit: int | None,
    part: MessageSpec,
    nested: Callable[[str], MessageSpec],
    counted: dict[str, int],
) -> str | None:
    """None when an instance of ``part`` made without its fields holds at most ``limit`` values
    (None: no limit); else what it holds, as every refusal of such a type says it:
    ``4000000 values, 4000000 of them in the field 'samples' (float64[4000000])``.

    Each value takes at least a byte of JSON, so a message of ``limit`` bytes cannot hold more
    values: such a type can be sent only with its largest fields left out, and leaving them out
    makes the reader create them all.
    """
    if limit is None or not part.fields:
        return None
    total, size, field = largest_default(part, nested, counted)
    if total <= limit:
        return None
    return f"{total} values, {size} of them in the field {field.name!r} ({field.type})"


def _is_bytes(type_: TypeSpec) -> bool:
    """Whether a field of this type is ``bytes``: an array of ``byte`` or ``uint8``."""
    return type_.is_array and type_.is_primitive and type_.name in ARRAY_PRIMITIVES_AS_BYTES


# --- the base classes --------------------------------------------------------------------------


class Message(pydantic.BaseModel):
    """The base of every message class, including the parts of services and actions.

    Instances are mutable like ROS messages, and every assignment is validated. Unknown fields
    are refused. Fields are read by their .srv name or their Python name and written by their
    .srv name (see :func:`python_name`).
    """

    model_config = ConfigDict(
        extra="forbid",
        validate_by_name=True,
        validate_by_alias=True,
        serialize_by_alias=True,
        validate_assignment=True,
        ser_json_inf_nan=INF_NAN_MODES[0],
        ser_json_bytes="base64",  # only for the JSON schema's defaults: AcceptBase64 writes them
        protected_namespaces=(),
    )

    spec: ClassVar[MessageSpec]
    """What the interface file says: fields, constants, defaults, comments."""
    type_name: ClassVar[str]
    """``pkg/msg/Name``; ``pkg/srv/Name_Request`` and so on for the parts of a service/action."""


Req = TypeVar("Req", bound=Message)
Resp = TypeVar("Resp", bound=Message)
Resp_co = TypeVar("Resp_co", bound=Message, covariant=True)


class ServiceRequest(Generic[Resp_co]):
    """The second base of a service's ``Request`` class, naming its ``Response`` class.

    ``class SetSpeed_Request(Message, ServiceRequest["SetSpeed_Response"])``: for type checkers,
    so that ``await client.call(name, SetSpeed.Request(...))`` is a ``SetSpeed.Response``. It
    adds no field or method; the class gets :attr:`service_` when its service class is made.
    """

    __slots__ = ()

    service_: ClassVar[type[Service]]
    """The service class whose ``Request`` this is: set by :class:`Service` when that class
    is made (the first one made with it), so that ``client.call(name, SetSpeed.Request())``
    is typed by ``SetSpeed`` as ``srv_type=SetSpeed`` would type it."""


class Service:
    """The base of every service class: a request type and a response type under one name."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        request = cls.__dict__.get("Request")
        if (
            isinstance(request, type)
            and issubclass(request, ServiceRequest)
            and "service_" not in request.__dict__
        ):
            request.service_ = cls

    Request: ClassVar[type[Message]]
    Response: ClassVar[type[Message]]
    type_name: ClassVar[str]
    """``pkg/srv/Name``."""
    spec: ClassVar[ServiceSpec]
    text: ClassVar[str]
    """The text of the .srv file."""


class TypedService(Service, Generic[Req, Resp]):
    """The base of a service class whose parts a type checker knows:
    ``class SetSpeed(TypedService[SetSpeed_Request, SetSpeed_Response])``.

    Every service class :func:`build_service` builds or ``srvwire gen`` writes derives from it,
    so that ``client.proxy(name, SetSpeed)`` calls return ``SetSpeed.Response``. A class
    known only as ``type[Service]`` (what :func:`~srvwire.loader.load_service` returns) gives
    its calls the static type ``Any``.
    """


class Action:
    """The base of every action class: its goal, result and feedback types under one name."""

    Goal: ClassVar[type[Message]]
    Result: ClassVar[type[Message]]
    Feedback: ClassVar[type[Message]]
    type_name: ClassVar[str]
    """``pkg/action/Name``."""
    spec: ClassVar[ActionSpec]
    text: ClassVar[str]
    """The text of the .action file."""


Resolver: TypeAlias = Callable[[TypeSpec], type[Message]]
"""Given a nested element type (``package`` set, no array part), return its message class."""

# The metaclass's attributes too: pydantic warns of a field that hides `Message.register`.
_RESERVED_NAMES = frozenset(
    {*keyword.kwlist, *dir(Message), *dir(type(Message)), *Message.__class_vars__}
)


def python_name(field_name: str) -> str:
    """Return the attribute name of the field ``field_name``: itself, unless it is reserved.

    A Python keyword or a name :class:`Message` already uses (``from``, ``copy``, ``json``,
    ``model_dump``, ``spec``, ``type_name``, its metaclass's ``register`` and ``mro``, ...) gets
    a trailing underscore. ROS field names
    never end with one, so the result cannot clash with another field.
    """
    return f"{field_name}_" if field_name in _RESERVED_NAMES else field_name


# --- building classes --------------------------------------------------------------------------

_CONSTANT_TYPES: dict[str, type[Scalar]] = {
    **dict.fromkeys(INTEGER_RANGES, int),
    **dict.fromkeys(FLOAT_TYPES, float),
    "bool": bool,
    "string": str,
    "wstring": str,
}


def _element_annotation(spec: MessageSpec, field: FieldSpec, resolve: Resolver | None) -> Any:
    type_ = field.type
    if type_.is_primitive:
        annotation = PRIMITIVE_ANNOTATIONS.get(type_.name)
        if annotation is None:
            raise InterfaceError(f"{spec.type_name}: field {field.name!r} has unknown type {type_}")
        if type_.string_bound is not None:
            annotation = Annotated[annotation, Field(max_length=type_.string_bound)]
        return annotation
    if resolve is None:
        raise InterfaceError(
            f"{spec.type_name}: field {field.name!r} has the nested type {type_.qualified_name}, "
            "and no resolver was given to find its class"
        )
    nested = resolve(type_.element)
    if not (isinstance(nested, type) and issubclass(nested, Message)):
        raise InterfaceError(
            f"{spec.type_name}: the resolver returned {nested!r} for {type_.qualified_name}, "
            "not a Message class"
        )
    return nested


def _annotation(type_: TypeSpec, element: Any) -> Any:
    """Wrap an element annotation for an array type: ``list[...]`` and its bounds."""
    if not type_.is_array:
        return element
    metadata: list[Any] = []
    if _is_bytes(type_):
        if type_.array is ArrayKind.FIXED:
            metadata.append(Field(min_length=type_.size, max_length=type_.size))
        elif type_.array is ArrayKind.BOUNDED:
            metadata.append(Field(max_length=type_.size))
        return Annotated[(bytes, *metadata, AcceptBase64)]
    if type_.array is ArrayKind.FIXED:
        metadata.append(Field(min_length=type_.size, max_length=type_.size))
    elif type_.array is ArrayKind.BOUNDED:
        metadata.append(Field(max_length=type_.size))
    if not metadata:
        return list[element]
    return Annotated[(list[element], *metadata)]


def _copies_of(values: tuple[Any, ...]) -> Callable[[], list[Any]]:
    def factory() -> list[Any]:
        return list(values)

    return factory


def _zero_list(type_: TypeSpec) -> Callable[[], list[Scalar]]:
    zero, count = zero_value(type_), type_.size or 0

    def factory() -> list[Scalar]:
        return [zero] * count

    return factory


def _zero_bytes(type_: TypeSpec) -> Callable[[], bytes]:
    count = type_.size or 0

    def factory() -> bytes:
        return bytes(count)

    return factory


def _new_message(cls: type[Message]) -> Callable[[], Message]:
    def factory() -> Message:
        return cls()

    return factory


def _new_messages(cls: type[Message], count: int) -> Callable[[], list[Message]]:
    def factory() -> list[Message]:
        return [cls() for _ in range(count)]

    return factory


def _field_info(spec: MessageSpec, field: FieldSpec, element: Any) -> Any:
    keywords: dict[str, Any] = {}
    if python_name(field.name) != field.name:
        keywords["alias"] = field.name
    if field.doc:
        keywords["description"] = field.doc
    type_ = field.type
    if type_.is_array and not _is_bytes(type_):
        keywords["fail_fast"] = True  # stop at the first invalid element: MAX_LISTED_ERRORS
    if type_.is_primitive:
        if type_.array is ArrayKind.FIXED and field.default is None:
            # N zero values, made for each instance that needs them and never when the class
            # is built: N can be 4294967295, which no process could hold.
            zeros = _zero_bytes(type_) if _is_bytes(type_) else _zero_list(type_)
            return Field(default_factory=zeros, **keywords)
        value = default_value(field)
        if isinstance(value, list):
            return Field(default_factory=_copies_of(tuple(value)), **keywords)
        return Field(default=value, **keywords)
    if field.default is not None:
        raise InterfaceError(
            f"{spec.type_name}: field {field.name!r} of message type {type_} cannot have a default"
        )
    if not type_.is_array:
        return Field(default_factory=_new_message(element), **keywords)
    if type_.array is ArrayKind.FIXED:
        return Field(default_factory=_new_messages(element, type_.size or 0), **keywords)
    return Field(default_factory=_copies_of(()), **keywords)


def _check_defaults(cls: type[Message], spec: MessageSpec) -> None:
    written = {f.name: default_value(f) for f in spec.fields if f.default is not None}
    if not written:
        return
    try:
        cls.model_validate(written)
    except pydantic.ValidationError as exc:
        problems = "; ".join(f"{e['path']}: {e['message']}" for e in validation_errors(exc))
        raise InterfaceError(f"{spec.type_name}: invalid default value ({problems})") from None


def _filler(namespace: dict[str, Any]) -> Callable[[dict[str, Any]], None]:
    def fill(class_namespace: dict[str, Any]) -> None:
        class_namespace.update(namespace)

    return fill


def _build(
    spec: MessageSpec,
    resolve: Resolver | None,
    type_name: str,
    module: str,
    bases: tuple[Any, ...] = (Message,),
) -> type[Message]:
    annotations: dict[str, Any] = {"spec": ClassVar[MessageSpec], "type_name": ClassVar[str]}
    namespace: dict[str, Any] = {
        "__module__": module,
        "__qualname__": spec.name,
        "__doc__": spec.doc or None,
        "__annotations__": annotations,
        "spec": spec,
        "type_name": type_name,
    }
    for constant in spec.constants:
        annotations[constant.name] = ClassVar[_CONSTANT_TYPES[constant.type.name]]
        namespace[constant.name] = _normalize(constant.type.name, constant.value)
    for field in spec.fields:
        element = _element_annotation(spec, field, resolve)
        name = python_name(field.name)
        annotations[name] = _annotation(field.type, element)
        namespace[name] = _field_info(spec, field, element)
    cls = cast("type[Message]", types.new_class(spec.name, bases, {}, _filler(namespace)))
    _check_defaults(cls, spec)
    return cls


def build_message(spec: MessageSpec, resolve: Resolver | None = None) -> type[Message]:
    """Build the class of a message.

    ``resolve`` finds the class of each nested type; without it a nested field is an
    :class:`~srvwire.errors.InterfaceError`. The class is named after the message, lives in the
    module ``pkg.msg`` (as rclpy's do) and has ``type_name`` ``pkg/msg/Name``. A new class is
    built on every call.
    """
    return _build(spec, resolve, spec.type_name, f"{spec.package}.msg")


def build_service(spec: ServiceSpec, resolve: Resolver | None = None) -> type[Service]:
    """Build the class of a service: ``Request`` and ``Response`` message classes under one name.

    The parts are named ``Name_Request``/``Name_Response`` with type names
    ``pkg/srv/Name_Request``/``pkg/srv/Name_Response``; see :func:`build_message`.
    """
    module = f"{spec.package}.srv"
    response = _build(spec.response, resolve, _part_name(spec, spec.response), module)
    request = _build(
        spec.request,
        resolve,
        _part_name(spec, spec.request),
        module,
        (Message, ServiceRequest[response]),  # type: ignore[valid-type]
    )
    namespace: dict[str, Any] = {
        "__module__": module,
        "__qualname__": spec.name,
        "Request": request,
        "Response": response,
        "type_name": spec.type_name,
        "spec": spec,
        "text": spec.text,
    }
    base = TypedService[request, response]  # type: ignore[valid-type]
    return cast("type[Service]", types.new_class(spec.name, (base,), {}, _filler(namespace)))


def build_action(spec: ActionSpec, resolve: Resolver | None = None) -> type[Action]:
    """Build the class of an action: ``Goal``, ``Result`` and ``Feedback`` message classes.

    The parts are named ``Name_Goal`` and so on, with type names ``pkg/action/Name_Goal``.
    """
    module = f"{spec.package}.action"
    namespace: dict[str, Any] = {
        "__module__": module,
        "__qualname__": spec.name,
        "Goal": _build(spec.goal, resolve, _part_name(spec, spec.goal), module),
        "Result": _build(spec.result, resolve, _part_name(spec, spec.result), module),
        "Feedback": _build(spec.feedback, resolve, _part_name(spec, spec.feedback), module),
        "type_name": spec.type_name,
        "spec": spec,
        "text": spec.text,
    }
    return cast("type[Action]", types.new_class(spec.name, (Action,), {}, _filler(namespace)))


def _part_name(spec: ServiceSpec | ActionSpec, part: MessageSpec) -> str:
    return f"{spec.type_name.rpartition('/')[0]}/{part.name}"


# --- validation errors ---------------------------------------------------------------------------


def _path(location: tuple[int | str, ...]) -> str:
    path = ""
    for item in location:
        if isinstance(item, int):
            path += f"[{item}]"
        else:
            path += f".{item}" if path else item
    return path


MAX_LISTED_ERRORS = 10
"""How many problems an ``INVALID_PARAMS`` error lists; ``error_count`` says how many were found.

An array's validation stops at its first invalid element (``Field(fail_fast=True)``), so a
message of a million bad elements costs one error, not a million: each array contributes at
most one problem, and ``error_count`` counts the problems found, not every bad element."""


def validation_errors(
    exc: pydantic.ValidationError, limit: int | None = None
) -> list[dict[str, str]]:
    """Describe the problems of ``exc`` (the first ``limit``) as ``{"path", "message", "type"}``.

    ``path`` points into the payload by .srv field names:
    ``pose.position.x``, ``values[3]``, ``points[0].x``; it is ``""`` when the payload as a
    whole is wrong (not an object). ``type`` is pydantic's error type (``int_type``,
    ``less_than_equal``, ``extra_forbidden``).
    """
    listed = exc.errors(include_url=False, include_context=False, include_input=False)
    return [
        {"path": _path(error["loc"]), "message": error["msg"], "type": error["type"]}
        for error in listed[:limit]
    ]


def error_data(exc: pydantic.ValidationError) -> dict[str, Any]:
    """The ``data`` of the error for ``exc``: see :func:`listed_errors`."""
    return listed_errors(validation_errors(exc, MAX_LISTED_ERRORS), exc.error_count())


def listed_errors(errors: Sequence[Mapping[str, str]], count: int | None = None) -> dict[str, Any]:
    """``{"errors": [...]}`` with the first :data:`MAX_LISTED_ERRORS` of ``errors``, and
    ``"error_count"`` (``count``, or how many ``errors`` holds) when that is more, so that a
    reply is not much larger than the request that caused it."""
    total = len(errors) if count is None else count
    data: dict[str, Any] = {"errors": list(errors[:MAX_LISTED_ERRORS])}
    if total > len(data["errors"]):
        data["error_count"] = total
    return data


def summarize_errors(errors: Sequence[Mapping[str, str]], count: int | None = None) -> str:
    """Say the first problem of a :func:`validation_errors` list, and how many more there are.

    ``values[3]: Input should be less than or equal to 255 (and 2 more)``; without the path when
    the payload as a whole is wrong. ``count`` is how many problems there were in all, when the
    list holds fewer. The one wording for an ``INVALID_PARAMS`` message, whether the server,
    the client or the command line found the problems.
    """
    first = errors[0]
    where = f"{first['path']}: " if first["path"] else ""
    total = len(errors) if count is None else count
    more = f" (and {total - 1} more)" if total > 1 else ""
    return f"{where}{first['message']}{more}"


def unencodable_strings(value: Any) -> list[dict[str, str]]:
    """Find the strings in ``value`` that cannot be written as UTF-8, as :func:`validation_errors`.

    Such a string holds a lone surrogate (``"\\ud800"``, or what ``os.fsdecode`` makes of a
    byte that is not UTF-8). Validation lets it through, to keep string checks in Rust, so it
    fails only when the value is written as JSON; this finds where it is, for the error message.
    ``value`` is a message, or the dicts and lists of one; paths use the .srv field names.
    Meant for the error path only: it walks the whole value.
    """
    found: list[dict[str, str]] = []
    _find_unencodable(value, (), found)
    return found


def _find_unencodable(
    value: Any, location: tuple[int | str, ...], found: list[dict[str, str]]
) -> None:
    if isinstance(value, str):
        if not value.isascii():
            try:
                value.encode("utf-8")
            except UnicodeEncodeError as exc:
                found.append(
                    {
                        "path": _path(location),
                        "message": (
                            f"String should not contain the lone surrogate "
                            f"{value[exc.start]!r} (at index {exc.start}): it cannot be written "
                            "as UTF-8"
                        ),
                        "type": "string_unicode",
                    }
                )
    elif isinstance(value, pydantic.BaseModel):
        for name, info in type(value).model_fields.items():
            _find_unencodable(getattr(value, name), (*location, info.alias or name), found)
    elif isinstance(value, Mapping):
        for key, item in value.items():
            _find_unencodable(item, (*location, str(key)), found)
    elif isinstance(value, list | tuple):
        for index, item in enumerate(value):
            _find_unencodable(item, (*location, index), found)


# --- the per-call codecs: the only code that reaches into pydantic's compiled validators ----
# Each skips the Python wrapper of model_validate / model_validate_json / model_dump_json, which
# costs as much as the work itself on a small message.

M = TypeVar("M", bound=pydantic.BaseModel)


def validate_python(model: type[M], data: Any) -> M:
    """``model.model_validate(data)``; raise pydantic's ``ValidationError``."""
    validated: M = model.__pydantic_validator__.validate_python(data)
    return validated


def validate_wire(model: type[M], data: Any) -> M:
    """:func:`validate_python` for data a peer sent, parsed from JSON, read as its JSON text
    would be read in one pass (``wire_validator(model).validate_json``).

    Each field goes by its JSON name only, its name in the interface file, never by its Python
    name (``from_``), which Python code may use. A number too large for a double reads as
    infinity in a float field whether it was written ``1e400`` or as an integer of 309 digits
    or more, which parsing made an ``int`` (refused by a float field in Python mode as
    ``float_type``): then, and only then, the data is validated again as JSON text.
    """
    # The class's own validator read here, a Python call less on every message once it is built.
    validator = model.__dict__.get("_srvwire_wire_validator") or wire_validator(model)
    try:
        validated: M = validator.validate_python(data)
    except pydantic.ValidationError as exc:
        if not any(
            error["type"] == "float_type" and type(error["input"]) is int for error in exc.errors()
        ):
            raise
        try:
            text = pydantic_core.to_json(data, inf_nan_mode="constants")
        except Exception:  # nothing JSON can hold (a lone surrogate): the first error stands
            raise exc from None
        validated = validator.validate_json(text)
    return validated


def wire_validator(model: type[pydantic.BaseModel]) -> SchemaValidator:
    """``model``'s validator for what a peer sends (see :func:`validate_wire`), built once per
    class: its own, with every model in it reading fields by their JSON names only. A schema
    of its own rather than ``by_name=False`` at each call, which costs a third of a small
    message's validation."""
    built = model.__dict__.get("_srvwire_wire_validator")
    if built is None:
        schema = _by_json_names(model.__pydantic_core_schema__)
        built = SchemaValidator(schema, _use_prebuilt=False)
        type.__setattr__(model, "_srvwire_wire_validator", built)
    return cast("SchemaValidator", built)


def _by_json_names(schema: Any) -> Any:
    """A copy of a core schema in which every model reads its fields by their JSON names only."""
    if isinstance(schema, list):
        return [_by_json_names(item) for item in schema]
    if not isinstance(schema, dict):
        return schema
    copied = {key: _by_json_names(value) for key, value in schema.items()}
    if schema.get("type") == "model" and isinstance(schema.get("config"), dict):
        copied["config"] = {**schema["config"], "validate_by_name": False}
    return copied


def dump_json(value: pydantic.BaseModel, *, strict: bool = False) -> bytes:
    """``value.model_dump_json(by_alias=True)`` as UTF-8 bytes, by the instance's own class.

    By its own class, so that a subclass keeps the fields it adds. With ``strict`` a value that
    does not fit its field (a handler put a ``str`` in an ``int`` list) is an error
    (``PydanticSerializationError``) rather than a warning.
    """
    serializer = type(value).__pydantic_serializer__
    if strict:
        return _write_checked(serializer.to_json, value)
    return serializer.to_json(value, by_alias=True)


def json_writer(
    model: type[M], inf_nan: InfNan | None = None, *, strict: bool = False
) -> Callable[[M], bytes]:
    """:func:`dump_json` for instances of exactly ``model``, with no lookup per call.

    ``inf_nan`` chooses how non-finite floats are written (None: as the class writes them);
    a mode the class does not write already costs one serializer, built here, never per call.
    """
    serializer = model.__pydantic_serializer__
    if inf_nan is not None and model.model_config.get("ser_json_inf_nan") != inf_nan:
        if inf_nan not in INF_NAN_MODES:
            raise ValueError(f"inf_nan must be one of {', '.join(INF_NAN_MODES)}, not {inf_nan!r}")
        schema = _with_inf_nan(model.__pydantic_core_schema__, inf_nan)
        serializer = SchemaSerializer(schema, {"ser_json_inf_nan": inf_nan}, _use_prebuilt=False)
    if strict:  # one partial without keywords: a partial's keywords cost a dict per call
        checked: Callable[[M], bytes] = functools.partial(_write_checked, serializer.to_json)
        return checked
    write: Callable[[M], bytes] = functools.partial(serializer.to_json, by_alias=True)
    return write


def reply_writer(
    model: type[M], inf_nan: InfNan | None = None, *, strict: bool = False
) -> Callable[[Id, M], bytes]:
    """Write the JSON-RPC response whose result is an instance of exactly ``model``, whole.

    ``reply_writer(model, mode)(id, value)`` is the same bytes as
    ``write_response(id, json_writer(model, mode)(value))`` for every id a request can carry (a
    string, an integer, a finite number, null: a non-finite number is refused as an id before
    anything is called, and this writer would write it in ``mode``), but pydantic-core writes the
    envelope, the id and the result into one buffer: the result is never a separate copy that
    the envelope copies again. For a reply of megabytes that is one fewer copy made, and alive
    at once, which is what decides whether the C library hands its heap back after each reply
    and faults it in again for the next one (docs/performance.md, "Large replies written
    whole"). ``strict`` as in :func:`json_writer`.
    """
    schema = model.__pydantic_core_schema__
    if inf_nan is not None:
        if inf_nan not in INF_NAN_MODES:
            raise ValueError(f"inf_nan must be one of {', '.join(INF_NAN_MODES)}, not {inf_nan!r}")
        schema = _with_inf_nan(schema, inf_nan)
    definitions: list[Any] = []
    if schema["type"] == "definitions":  # the envelope's own definitions, at its top
        definitions, schema = schema["definitions"], schema["schema"]
    envelope: Any = core_schema.typed_dict_schema(
        {
            "jsonrpc": core_schema.typed_dict_field(core_schema.str_schema()),
            # Any id a reader takes (a string, a finite number, null) is written as
            # protocol.encode_json writes it: by the same inference.
            "id": core_schema.typed_dict_field(core_schema.any_schema()),
            "result": core_schema.typed_dict_field(schema),
        }
    )
    if definitions:
        envelope = core_schema.definitions_schema(envelope, definitions)
    config: Any = {} if inf_nan is None else {"ser_json_inf_nan": inf_nan}
    to_json = SchemaSerializer(envelope, config, _use_prebuilt=False).to_json

    def write(id: Id, value: M) -> bytes:
        return to_json({"jsonrpc": "2.0", "id": id, "result": value}, by_alias=True)

    def write_checked(id: Id, value: M) -> bytes:
        return _write_checked(to_json, {"jsonrpc": "2.0", "id": id, "result": value})

    return write_checked if strict else write


def _write_checked(to_json: Callable[..., bytes], value: Any) -> bytes:
    """``to_json(value, by_alias=True)``, a pydantic serializer's, with its warnings errors."""
    filters = warnings.filters
    if not filters or filters[0] != _CHECKED_FILTER:
        _raise_serializer_warnings()
    try:
        return to_json(value, by_alias=True)  # _CHECKED_LINE: its warnings from here are errors
    except UserWarning as exc:
        raise PydanticSerializationError(str(exc)) from None


# A value that does not fit its field makes pydantic-core warn, or raise with
# ``warnings="error"``, which costs about a microsecond per call to read. The same strictness,
# cheaper: warn as usual, and a warnings filter that names the one line that calls the
# serializer in _write_checked turns that warning, and no other, into the error. The filter is
# put back in front before a write whenever something else (pytest, the application) went
# before it since.
_CHECKED_LINE = _write_checked.__code__.co_firstlineno + 6
_SERIALIZER_WARNING = "Pydantic serializer warnings"
_CHECKED_MODULE = r"srvwire\.models\Z"


def _raise_serializer_warnings() -> None:
    warnings.filterwarnings(
        "error", _SERIALIZER_WARNING, UserWarning, _CHECKED_MODULE, _CHECKED_LINE
    )


_CHECKED_FILTER = (
    "error",
    re.compile(_SERIALIZER_WARNING, re.I),
    UserWarning,
    re.compile(_CHECKED_MODULE),
    _CHECKED_LINE,
)


def _with_inf_nan(schema: Any, inf_nan: InfNan) -> Any:
    """A copy of a core schema in which every model writes non-finite floats as ``inf_nan``."""
    if isinstance(schema, list):
        return [_with_inf_nan(item, inf_nan) for item in schema]
    if not isinstance(schema, dict):
        return schema
    copied = {key: _with_inf_nan(value, inf_nan) for key, value in schema.items()}
    if schema.get("type") == "model" and isinstance(schema.get("config"), dict):
        copied["config"] = {**schema["config"], "ser_json_inf_nan": inf_nan}
    return copied


class ModelDecoder(Generic[M]):
    """Turns a result into ``model``: from JSON text in one pass, or from parsed data.

    What :meth:`srvwire.protocol.RawReply.decode` needs; both raise pydantic's
    ``ValidationError`` (a ``ValueError``) when the result does not fit. They are the compiled
    validator's own method (:func:`wire_validator`'s, which reads each field by its JSON name
    only), so a call costs no Python frame of its own; ``from_data`` is :func:`validate_wire`.
    """

    __slots__ = ("_whole", "from_data", "from_json", "model")

    def __init__(self, model: type[M]) -> None:
        self.model = model
        # A peer names each field by its JSON name only; parsed data reads as its text would.
        self.from_json: Callable[[str], M] = wire_validator(model).validate_json
        self.from_data: Callable[[Any], M] = functools.partial(validate_wire, model)
        self._whole: Callable[[str], dict[str, Any]] | None = None

    def from_reply(self, message: str, id: int) -> M:
        """The result of ``message``, the whole response to ``id`` as srvwire servers write it,
        validated with its envelope in one pass (no copy of the result's text is made).

        ``ValueError`` (pydantic's ``ValidationError``) for anything else: a result that does
        not fit, another ``id``, a member besides ``jsonrpc``, ``id`` and ``result``; the full
        parse then says which. Of a member given twice, the last counts, as in the full parse.
        The validator is built for the first reply read so.
        """
        whole = self._whole
        if whole is None:
            whole = self._whole = _reply_validator(self.model)
        envelope = whole(message)
        if envelope["id"] != id:
            raise ValueError(f"a reply to {envelope['id']}, not to {id}")
        result: M = envelope["result"]
        return result


def _reply_validator(model: type[M]) -> Callable[[str], dict[str, Any]]:
    """Validate a whole response whose result is a ``model``: exactly ``jsonrpc`` "2.0", an
    integer ``id`` and the ``result``, nothing else."""
    schema = model.__pydantic_core_schema__
    definitions: list[Any] = []
    if schema["type"] == "definitions":
        definitions, schema = schema["definitions"], schema["schema"]
    envelope: Any = core_schema.typed_dict_schema(
        {
            "jsonrpc": core_schema.typed_dict_field(core_schema.literal_schema(["2.0"])),
            "id": core_schema.typed_dict_field(core_schema.int_schema(strict=True)),
            "result": core_schema.typed_dict_field(schema),
        },
        extra_behavior="forbid",
    )
    if definitions:
        envelope = core_schema.definitions_schema(envelope, definitions)
    validate: Callable[[str], dict[str, Any]] = SchemaValidator(
        _by_json_names(envelope), _use_prebuilt=False
    ).validate_json
    return validate


# --- a request read in one pass ----------------------------------------------------------------


class CallReader:
    """Reads a request to one of some services from its JSON text in one pass of pydantic-core.

    ``requests`` maps each service's name to its ``Request`` class. The one validator is a
    union tagged by ``method`` (each name with and without its leading ``/``) of envelopes:
    ``jsonrpc`` exactly ``"2.0"``, an integer or string ``id``, and ``params``, an object that
    is that service's ``Request`` with ``_meta`` as one more field, an object or absent (the
    rest of the request's rules unchanged). :meth:`read` returns the request's fields
    (:data:`~srvwire.protocol.ReadRequest`) whose ``params`` is the request built, ``_meta``
    taken out of it and read into ``timeout``, or None for anything else: a notification, a batch,
    another method, an invalid message, params that do not validate, a member the request does
    not have besides ``_meta``, a ``_meta`` that is not an object with a valid ``timeout``.
    None means "parse it the full way", which then says what is wrong exactly as it always
    does.

    Only classes srvwire builds (:class:`Message`, no validators of their own) are read so:
    JSON-mode and Python-mode validation are known to agree on them (``tests/test_decode.py``;
    an integer literal too large for a double in a float field, which Python mode refuses, the
    full parse reads again as JSON: see :func:`validate_wire`).
    """

    __slots__ = ("validate",)

    def __init__(self, requests: Mapping[str, type[pydantic.BaseModel]]) -> None:
        choices: dict[str, Any] = {}
        definitions: dict[str, Any] = {}
        id_schema = core_schema.union_schema(
            [core_schema.int_schema(strict=True), core_schema.str_schema(strict=True)]
        )
        for name, model in requests.items():
            params = _params_schema(model, definitions)
            if params is None:
                continue
            envelope = core_schema.typed_dict_schema(
                {
                    "jsonrpc": core_schema.typed_dict_field(core_schema.literal_schema(["2.0"])),
                    "id": core_schema.typed_dict_field(id_schema),
                    "method": core_schema.typed_dict_field(core_schema.str_schema()),
                    "params": core_schema.typed_dict_field(params),
                },
                extra_behavior="ignore",  # as the full parse ignores members it does not know
            )
            choices[name] = envelope
            choices[name[1:] if name.startswith("/") else "/" + name] = envelope
        self.validate: Callable[[Any], dict[str, Any]] | None = None
        if choices:
            schema: Any = core_schema.tagged_union_schema(choices, discriminator="method")
            if definitions:
                schema = core_schema.definitions_schema(schema, list(definitions.values()))
            # Not the classes' own validators: their params refuse _meta. Fields by their JSON
            # names only, as validate_wire reads them.
            self.validate = SchemaValidator(
                _by_json_names(schema), _use_prebuilt=False
            ).validate_json

    def read(self, data: str | bytes) -> ReadRequest | None:
        """Return the request read in one pass, its params validated; else None."""
        validate = self.validate
        if validate is None:
            return None
        try:
            envelope = validate(data)
        except Exception:  # refused (a ValidationError), or a validator's own failure: the
            return None  # full parse says which, as it always did
        request: pydantic.BaseModel = envelope["params"]
        meta = request.__dict__.pop(_META)
        timeout = None
        if meta is not None:
            raw = meta.get("timeout")
            if type(raw) is float and 0.0 <= raw < math.inf:  # what clients send
                timeout = raw
            elif raw is not None:  # anything else, by the full parse's rules
                timeout = timeout_seconds(raw)
                if timeout is None:
                    return None
            request.__pydantic_fields_set__.discard(_META)
        return envelope["id"], envelope["method"], request, timeout


def _params_schema(
    model: type[pydantic.BaseModel], definitions: dict[str, Any]
) -> dict[str, Any] | None:
    """``model``'s core schema with ``_meta`` as one more field (an object, or absent), its
    definitions added to ``definitions``; None for a class not read in one pass."""
    if not _as_built(model) or model.__pydantic_custom_init__:
        return None
    decorators = model.__pydantic_decorators__
    if (
        decorators.validators
        or decorators.field_validators
        or decorators.root_validators
        or decorators.model_validators
    ):
        return None
    schema: Any = model.__pydantic_core_schema__
    if schema["type"] == "definitions":
        for definition in schema["definitions"]:
            definitions.setdefault(definition["ref"], definition)
        schema = schema["schema"]
    if schema["type"] != "model" or schema["schema"]["type"] != "model-fields":
        return None
    if not all(_as_built(nested) for nested in _model_classes(schema)):
        return None
    fields = {**schema["schema"]["fields"], _META: _META_FIELD}
    params = {**schema, "schema": {**schema["schema"], "fields": fields}}
    params.pop("ref", None)  # another schema than the class's own
    return params


# ``_meta`` as one more field of a request read in one pass: an object, or absent (None). It
# lands in the instance's fields, where the reader takes it out; any other member the class
# does not have is refused by the class's own rule, and the full parse names it.
_META = "_meta"
_META_FIELD = core_schema.model_field(
    core_schema.with_default_schema(core_schema.dict_schema(), default=None)
)


def _as_built(model: Any) -> bool:
    """Whether ``model`` is a message class as srvwire builds it, from its own spec, with the
    fields and config it was given: the classes whose JSON-mode and Python-mode validation
    are known to agree (``tests/test_decode.py``). A class written by hand, or a subclass that
    changes a field, is left to the full parse."""
    if not (isinstance(model, type) and issubclass(model, Message)):
        return False
    spec = model.__dict__.get("spec")
    if not isinstance(spec, MessageSpec):
        return False
    config = model.model_config
    if config.get("extra") != "forbid" or config.get("strict"):
        return False
    return list(model.model_fields) == [python_name(field.name) for field in spec.fields]


def _model_classes(schema: Any) -> list[Any]:
    """The classes of every model in a core schema, its definitions included."""
    found: list[Any] = []
    if isinstance(schema, dict):
        if schema.get("type") == "model":
            found.append(schema.get("cls"))
        for value in schema.values():
            found += _model_classes(value)
    elif isinstance(schema, list | tuple):
        for item in schema:
            found += _model_classes(item)
    return found
