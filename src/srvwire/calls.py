"""What a call sends and gets back, on the client's side: types, requests, deadlines.

A client resolves a service's type by name through a :data:`TypeResolver` (by default the
interface loader) or from the server's description of it, validates and writes a request with
:func:`encode_request`, and decodes a reply with the :class:`~srvwire.models.ModelDecoder` of
the type's ``Response``; the :class:`ServiceTypes` of a client keeps both, one per type, for
the client's life.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeAlias

from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticSerializationError

from srvwire.errors import (
    InterfaceConflictError,
    InterfaceError,
    InterfaceNotFoundError,
    InvalidParams,
)
from srvwire.idl import MessageSpec, TypeSpec
from srvwire.models import (
    INF_NAN_MODES,
    Action,
    InfNan,
    Message,
    ModelDecoder,
    Service,
    ServiceRequest,
    build_action,
    build_message,
    build_service,
    dump_json,
    error_data,
    json_writer,
    listed_errors,
    summarize_errors,
    unencodable_strings,
    validate_python,
    values_past,
)
from srvwire.parser import parse_action, parse_message, parse_service
from srvwire.protocol import describe_value, encode_json, timeout_seconds
from srvwire.typeregistry import (
    TypeRegistry,
    definition_lines,
    fingerprint,
    first_difference,
    full_definition,
    process_types,
)

__all__ = [
    "MessageResolver",
    "ServiceCodec",
    "ServiceInfo",
    "ServiceTypes",
    "SrvType",
    "TypeResolver",
    "check_timeout",
    "encode_message",
    "encode_request",
    "remote_message",
    "typed_by_request",
    "validate_request",
]

SrvType: TypeAlias = type[Service] | str
"""A service type: the class, or its name (``pkg/srv/Name``) to resolve."""

TypeResolver: TypeAlias = Callable[[str], type[Service]]
"""Turns a service type name into its class, or raises InterfaceError; default: the loader.

A name it does not know is an :class:`~srvwire.errors.InterfaceNotFoundError`; the client then
asks the server for the type's definition."""

MessageResolver: TypeAlias = Callable[[str], type[Message]]
"""Turns a message type name into its class, or raises InterfaceError; default: the loader."""


@dataclass(frozen=True, slots=True)
class ServiceInfo:
    """One service a server offers: its canonical name and its type (``pkg/srv/Name``)."""

    name: str
    type: str


def check_timeout(timeout: float, what: str = "timeout") -> float:
    """Return ``timeout`` as a deadline in seconds: finite and > 0, or raise saying why."""
    if type(timeout) is float and 0.0 < timeout < math.inf:  # the common case, quickly
        return timeout
    if isinstance(timeout, bool) or not isinstance(timeout, int | float):
        raise TypeError(f"{what} must be a number of seconds, not {type(timeout).__name__}")
    seconds = timeout_seconds(timeout)
    if not seconds:  # not a finite number >= 0, or zero
        raise ValueError(
            f"{what} must be a finite number of seconds > 0, not {describe_value(timeout)}"
        )
    return seconds


def _refused(method: str, data: dict[str, Any]) -> InvalidParams:
    """The error for a request the client will not send: it does not validate or encode."""
    errors = data["errors"]
    return InvalidParams(
        f"invalid params for {method}: {summarize_errors(errors, data.get('error_count'))} "
        "(checked by the client; nothing was sent)",
        data,
        service=method,
    )


def validate_request(method: str, srv: type[Service], request: Mapping[str, Any]) -> Message:
    """Build ``srv``'s ``Request`` from a mapping of its fields, as the server would.

    Raise :class:`~srvwire.errors.InvalidParams` with the field paths (the same
    ``data["errors"]`` the server sends) when it does not validate.
    """
    try:
        return validate_python(srv.Request, request)
    except ValidationError as exc:
        raise _refused(method, error_data(exc)) from None


def typed_by_request(method: str, codec: ServiceCodec, request: Any) -> type[Service] | None:
    """The service that types a call of ``method`` (whose type is ``codec``'s) given ``request``
    and no ``srv_type``: the service a ``Request`` of another class names
    (:attr:`~srvwire.models.ServiceRequest.service_`, a class ``srvwire gen`` wrote, say) when
    it has ``codec``'s type name; None for anything else, which :func:`encode_request` checks.

    Raise ``TypeError`` naming both types when the request's service is of another type.
    """
    if not isinstance(request, ServiceRequest):  # a mapping, say: quickly
        return None
    service: type[Service] | None = getattr(type(request), "service_", None)
    if service is None or service is codec.service:
        return None
    if service.type_name != codec.service.type_name:
        raise TypeError(
            f"{method} takes {codec.service.type_name} requests, not {service.type_name} "
            f"requests ({_model_name(type(request))})"
        )
    return service


def _model_name(cls: type[Any]) -> str:
    """How an error names a model class: its module and name."""
    return f"{cls.__module__}.{cls.__qualname__}"


def encode_request(
    method: str, codec: ServiceCodec | None, request: BaseModel | Mapping[str, Any] | None
) -> str:
    """Validate ``request`` when its type is known and return its JSON text (an object).

    Raise :class:`~srvwire.errors.InvalidParams` for a request that does not validate or
    cannot be written (nothing is sent then), ``TypeError`` for a model of another type or
    one that is not written as a JSON object.
    """
    srv = None if codec is None else codec.service
    if codec is not None and type(request) is codec.request:  # the common case
        written = codec.params(request)
        if written is not None:
            return written.decode()
    value: BaseModel | Mapping[str, Any] = {} if request is None else request
    if srv is not None and not isinstance(value, srv.Request):
        if isinstance(value, BaseModel):
            named = getattr(type(value), "type_name", None)
            raise TypeError(
                f"{method} takes {srv.type_name} requests, not "
                + (f"{named} ({_model_name(type(value))})" if named else _model_name(type(value)))
            )
        value = validate_request(method, srv, value)
    if not isinstance(value, BaseModel | Mapping):
        raise TypeError(
            f"the request for {method} must be a model or a mapping, not {type(value).__qualname__}"
        )
    try:
        if not isinstance(value, BaseModel):
            return encode_json(dict(value))
        if codec is None:
            text = dump_json(value).decode()
        elif type(value) is codec.service.Request:
            text = codec.write(value).decode()
        else:  # a subclass: by its own class, in the client's mode
            text = json_writer(type(value), codec.inf_nan)(value).decode()
    except PydanticSerializationError as exc:
        # A string with a lone surrogate validates, but cannot be written as UTF-8.
        errors = unencodable_strings(value) or [
            {"path": "", "message": str(exc), "type": "serialization_error"}
        ]
        raise _refused(method, listed_errors(errors)) from None
    if not text.startswith("{"):  # a RootModel or a custom serializer: not params by name
        raise TypeError(
            f"the request for {method} must serialize to a JSON object (params by name); "
            f"{type(value).__qualname__} serializes to {text[:40]!r}"
        )
    return text


class ServiceCodec:
    """A service type with what its calls need at hand: its response decoder, its request's
    writer, which writes non-finite floats as ``inf_nan`` says (built once, here)."""

    __slots__ = ("decoder", "inf_nan", "request", "service", "write")

    def __init__(self, service: type[Service], inf_nan: InfNan = INF_NAN_MODES[0]) -> None:
        self.service = service
        self.request: type[Message] = service.Request
        self.inf_nan: InfNan = inf_nan
        self.decoder: ModelDecoder[Message] = ModelDecoder(service.Response)
        self.write: Callable[[Any], bytes] = json_writer(service.Request, inf_nan)

    def params(self, request: Any) -> bytes | None:
        """The JSON object text of ``request``, an instance of exactly :attr:`request`; None
        when it cannot be written so, for :func:`encode_request` to say why."""
        try:
            written = self.write(request)
        except PydanticSerializationError:
            return None
        return written if written[:1] == b"{" else None


def _described(
    method: str, name: str, kind: str, definitions: Mapping[str, str] | None, source: str
) -> tuple[str, str, str]:
    """The text, package and short name of the ``kind`` (``srv`` or ``action``) type ``name``
    in the server's ``definitions``; raise InterfaceNotFoundError when they do not have it."""
    text = None if definitions is None else definitions.get(name)
    parts = name.split("/")
    if text is None or len(parts) != 3 or parts[1] != kind:
        why = "does not describe it" if definitions is not None else "does not describe types"
        what = "calls" if kind == "srv" else "goals"
        raise InterfaceNotFoundError(
            name,
            f"cannot type the {what} of {method}: {name} is not on the local search path, "
            f"and the {source} {why}",
        )
    return text, parts[0], parts[2]


class ServiceTypes:
    """Which type a call's messages have, each made ready once, for the client's life.

    A type comes from, in order:

    1. the class the call gives (``srv_type``);
    2. the local search path, by name (the name the call gives, or the type the server
       advertised), through the client's resolver;
    3. the server's description of the service (``rpc.discover``'s ``x-srvwire-definitions``):
       its definition text is parsed and built here. Each type it nests is taken from the local
       search path first, and from the description when it is not there. A described type
       one of whose messages, made without its fields, would hold more values than
       ``max_values`` (the client's ``max_message_size``) is refused: no message holding them
       could be sent or received whole, and a reply that left them out would have this client
       make them all (one line, ``int32[4294967295] a``, asks for 4294967295).

    Every class goes through the process's :class:`~srvwire.typeregistry.TypeRegistry`, so a
    type the server defines as a local file does is the local class, and one it defines
    differently is an :class:`~srvwire.errors.InterfaceConflictError` naming the file and the
    server. A type found in neither place is an :class:`~srvwire.errors.InterfaceNotFoundError`:
    a call never falls back to plain dicts.
    """

    def __init__(
        self,
        resolve: TypeResolver,
        resolve_message: MessageResolver,
        types: TypeRegistry | None = None,
        inf_nan: InfNan = INF_NAN_MODES[0],
        max_values: int | None = None,
    ) -> None:
        self._resolve = resolve
        self._max_values = max_values
        self._resolve_message = resolve_message
        self._types = process_types() if types is None else types
        self._inf_nan: InfNan = inf_nan
        self._by_name: dict[str, ServiceCodec] = {}
        self._by_class: dict[type[Service], ServiceCodec] = {}
        self._fingerprints: dict[type[Any], str | None] = {}

    def known(self, srv_type: SrvType | None, advertised: str | None) -> ServiceCodec | None:
        """Return the type of a call when it is known already (the quick path), else None."""
        if srv_type is not None and not isinstance(srv_type, str):
            return self._codec(srv_type)
        name = srv_type if srv_type is not None else advertised
        return None if name is None else self._by_name.get(name)

    def local(self, name: str) -> ServiceCodec | None:
        """Return the type ``name`` from the local search path, or None when it is not there."""
        if len(name.split("/")) != 3:  # not a file's name (a class written by hand): not here
            return None
        try:
            service = self._resolve(name)
        except InterfaceNotFoundError:
            return None
        codec = self._by_name[name] = self._codec(service)
        return codec

    def remote(
        self, method: str, name: str, definitions: Mapping[str, str] | None, source: str
    ) -> ServiceCodec:
        """Build the type ``name`` from the server's ``definitions`` (text by full name).

        ``source`` says where they came from (``server ws://...``); it is the "file" of every
        error in them. Raise :class:`~srvwire.errors.InterfaceError` when they do not define
        ``name`` or do not build.
        """
        text, package, short = _described(method, name, "srv", definitions, source)
        spec = parse_service(text, package, short, path=source)
        nested = self._nested(definitions, source)
        nested.refuse_too_many_values((spec.request, spec.response), self._max_values)
        service = self._types.intern(spec, source, lambda: build_service(spec, nested))
        codec = self._by_name[name] = self._codec(service)
        return codec

    def remote_action(
        self, method: str, name: str, definitions: Mapping[str, str] | None, source: str
    ) -> type[Action]:
        """Build the action ``name`` from the server's ``definitions``, as :meth:`remote`
        builds a service type."""
        text, package, short = _described(method, name, "action", definitions, source)
        spec = parse_action(text, package, short, path=source)
        nested = self._nested(definitions, source)
        nested.refuse_too_many_values((spec.goal, spec.result, spec.feedback), self._max_values)
        return self._types.intern(spec, source, lambda: build_action(spec, nested))

    def _nested(self, definitions: Mapping[str, str] | None, source: str) -> _RemoteMessages:
        """The messages the server's ``definitions`` describe, each compared with what is
        known of it first, so that nothing is built from a conflicting description, then
        built."""
        nested = _RemoteMessages(definitions or {}, source, self._resolve_message, self._types)
        messages = [other for other in definitions or {} if _is_message_name(other)]
        for other in messages:
            nested.check(other)
        for other in messages:
            nested.load(other)
        return nested

    def fingerprint(self, service: type[Any]) -> str | None:
        """The fingerprint of ``service``'s full definition (a service, action or message
        class), computed once per class; None for a class with no spec (written by hand),
        which has nothing to compare."""
        if service not in self._fingerprints:
            definition = full_definition(service)
            self._fingerprints[service] = None if definition is None else fingerprint(definition)
        return self._fingerprints[service]

    def conflict(
        self, service: type[Any], definitions: Mapping[str, str] | None, source: str
    ) -> InterfaceConflictError:
        """The error for a local ``service`` (or action, or a topic's message) whose
        fingerprint differs from the server's.

        ``definitions`` is the server's description (text by full name), when it could be
        had, to say which type differs and how; ``source`` says where it came from.
        """
        ours = full_definition(service) or {}
        theirs: dict[str, tuple[str, ...]] = {}
        try:
            for name, text in (definitions or {}).items():
                theirs[name] = definition_lines(_parse_named(name, text, source))
        except InterfaceError:
            theirs = {}
        if theirs:
            name, difference = first_difference(ours, theirs)
        else:
            name, difference = service.type_name, "their fingerprints differ"
        known = self._types.get(name)
        if known is not None and known.definition != ours.get(name):
            known = None  # the process's class is not the local one that differs (a copy's)
        spec_path = getattr(getattr(service, "spec", None), "path", None)
        local = known.source if known is not None else (spec_path or "the local class")
        return InterfaceConflictError(name, local, source, difference)

    def _codec(self, service: type[Service]) -> ServiceCodec:
        codec = self._by_class.get(service)
        if codec is None:
            codec = self._by_class[service] = ServiceCodec(service, self._inf_nan)
        return codec


def _parse_named(name: str, text: str, source: str) -> Any:
    """Parse the definition ``text`` of the full type ``name`` (msg, srv or action)."""
    parts = name.split("/")
    if len(parts) != 3:
        raise InterfaceError(f"the {source} describes a type with no full name: {name!r}")
    package, kind, short = parts
    parse = {"msg": parse_message, "srv": parse_service, "action": parse_action}.get(kind)
    if parse is None:
        raise InterfaceError(f"the {source} describes {name!r}, of no known kind")
    return parse(text, package, short, path=source)


def encode_message(topic: str, msg_type: type[BaseModel], message: Any) -> str:
    """Validate a message for ``topic`` and return its JSON text; raise
    :class:`~srvwire.errors.InvalidParams` with the fields' paths (``message.position[0]``)."""
    if type(message) is not msg_type:
        if isinstance(message, BaseModel):
            raise TypeError(
                f"{topic} takes {getattr(msg_type, 'type_name', msg_type.__name__)} messages, "
                f"not {type(message).__qualname__}"
            )
        try:
            message = validate_python(msg_type, message)
        except ValidationError as exc:
            data = error_data(exc)
            for error in data["errors"]:
                path = error["path"]
                error["path"] = "message" + ("" if path[:1] in ("", "[") else ".") + path
            raise InvalidParams(
                f"invalid message for {topic}: "
                f"{summarize_errors(data['errors'], exc.error_count())}",
                data,
                service=topic,
            ) from None
    try:
        return dump_json(message).decode()
    except PydanticSerializationError:
        errors = unencodable_strings(message) or [
            {"path": "", "message": "cannot be written as JSON", "type": "serialization_error"}
        ]
        raise InvalidParams(
            f"invalid message for {topic}: {summarize_errors(errors)}",
            listed_errors(errors),
            service=topic,
        ) from None


def remote_message(
    name: str,
    definitions: Mapping[str, str],
    source: str,
    resolve_message: MessageResolver,
    types: TypeRegistry | None = None,
    max_values: int | None = None,
) -> type[Message]:
    """The message type ``name`` (a topic's), local first, else built from ``definitions``
    (the server's, from ``source``), checked as a service's types are (``max_values`` too)."""
    nested = _RemoteMessages(
        definitions, source, resolve_message, process_types() if types is None else types
    )
    for other in definitions:
        if _is_message_name(other):
            nested.check(other)
    cls = nested.load(name)
    nested.refuse_too_many_values((cls.spec,), max_values)
    return cls


def _is_message_name(name: str) -> bool:
    parts = name.split("/")
    return len(parts) == 3 and parts[1] == "msg"


class _RemoteMessages:
    """Resolves the messages a server-described type nests: local first, then the server's."""

    def __init__(
        self,
        definitions: Mapping[str, str],
        source: str,
        local: MessageResolver,
        types: TypeRegistry,
    ) -> None:
        self.definitions = definitions
        self.source = source
        self.local = local
        self.types = types
        self.chain: list[str] = []
        self._values: dict[str, int] = {}  # message name -> values of an instance made bare

    def __call__(self, type_: TypeSpec) -> type[Message]:
        return self.load(type_.qualified_name)

    def spec(self, name: str, text: str) -> MessageSpec:
        package, _, short = name.split("/")
        return parse_message(text, package, short, path=self.source)

    def check(self, name: str) -> None:
        """Compare the server's ``name`` with the local file or the process's class, if any."""
        spec = self.spec(name, self.definitions[name])
        local: type[Message] | None = None
        try:
            local = self.local(name)
        except InterfaceNotFoundError:
            if self.types.get(name) is None:
                return
        self.types.intern(spec, self.source, lambda: local)

    def refuse_too_many_values(self, parts: tuple[MessageSpec, ...], limit: int | None) -> None:
        """Raise InterfaceError naming the part of ``parts``, and its largest field, whose
        instance made bare would hold more than ``limit`` values (None: no limit)."""
        for part in parts:
            held = values_past(limit, part, self.spec_of, self._values)
            if held is not None:
                raise InterfaceError(
                    f"the {self.source} describes {part.package}/{part.name}, which holds "
                    f"{held}, more than max_message_size={limit} can carry; refused, "
                    "so that a reply that leaves them out cannot make this client hold them"
                )

    def spec_of(self, name: str) -> MessageSpec:
        """The spec of the message ``name``, as this process has its class."""
        return self.load(name).spec

    def load(self, name: str) -> type[Message]:
        """Return the process's class of the message ``name``, checked against the server's."""
        text = self.definitions.get(name)
        if text is None:  # the server did not describe it: the local one, or an error
            return self.local(name)
        if name in self.chain:
            cycle = " -> ".join((*self.chain[self.chain.index(name) :], name))
            raise InterfaceError(
                f"the {self.source} describes a message that nests itself: {cycle}"
            )
        spec = self.spec(name, text)

        def build() -> type[Message]:
            try:
                return self.local(name)  # the local file first; the loader interns it
            except InterfaceNotFoundError:
                self.chain.append(name)
                try:
                    return build_message(spec, self)
                finally:
                    self.chain.pop()

        return self.types.intern(spec, self.source, build)
