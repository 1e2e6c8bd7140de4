"""The service registry, and the dispatch of one decoded request to one handler.

Nothing here knows about sockets: :class:`ServiceRegistry` maps names to
:class:`ServiceEntry` values, and :func:`dispatch` takes the ``params`` of one request, runs the
handler under the caller's deadline, and returns the response as the UTF-8 JSON bytes pydantic
writes (so a large response is never copied into a ``str`` and back), or raises an
:class:`~srvwire.errors.RPCError`. The server moves those bytes out as they are.

Invariants:

* **Names are canonical once registered.** A service name is segments of
  ``[A-Za-z][A-Za-z0-9_]*`` joined by ``/``, stored with a leading ``/``. A caller may leave the
  slash out; :meth:`ServiceRegistry.resolve` adds it. A bad name or a second registration under
  the same name is a :class:`~srvwire.errors.RegistrationError` at registration time, never at
  call time.
* **Handlers are introspected once.** Whether a handler is ``async``, whether it takes the
  pre-built response (the ROS shape ``handler(request, response)``), and which parameter receives
  the :class:`Context` are decided when it is registered; a call does no introspection.
* **A handler's failure is the call's failure, never the server's.** An exception from the
  handler becomes :class:`~srvwire.errors.InternalError` (its traceback goes to the log, not to
  the caller); an :class:`~srvwire.errors.RPCError` it raises, typically
  :class:`~srvwire.errors.ServiceError`, is sent as it is; a return value that is not a valid
  response is ``INTERNAL`` too, with the reason logged.
* **A response is written as the handler built it.** An instance of the response model, or of a
  subclass of it, is serialized by its own class (``by_alias``), so the fields a subclass adds
  reach the caller; a dict is validated into the response model first. Non-finite floats are
  written in the registry's ``inf_nan`` mode, by a writer each entry builds once.
* **Only a cancelled call ends in CancelledError.** :func:`dispatch` lets
  :class:`asyncio.CancelledError` through only while its own task is being cancelled
  (``Task.cancelling()``): the server cancelled the call, and knows what to answer. A
  CancelledError the handler raises by itself (it awaited a future that something else
  cancelled) is a handler failure like any other, ``INTERNAL``, so the caller is still answered.
* **Sync handlers never run on the event loop.** A plain ``def`` handler runs in the server's
  executor (by default its :class:`~srvwire.threads.HandlerThreads`). It cannot be
  interrupted: when its call is cancelled or its deadline passes, the caller is answered at
  once and :attr:`Context.cancelled` turns true (and :meth:`Context.wait` returns) so the
  handler can stop early. A call whose caller left before a thread took it never runs.
* **A service's ``max_concurrency`` counts handlers, not calls.** A call waits for a slot of
  its service (:class:`~srvwire.threads.ConcurrencyLimit`) before its handler starts; the slot
  is given back when the handler returns, which for a blocking handler may be long after its
  call was answered.
* **A deadline is the caller's, enforced by whoever runs the call.** ``_meta.timeout`` is
  measured from the moment the request was read; an already-expired deadline answers
  ``DEADLINE_EXCEEDED`` without running the handler. Past that, :func:`dispatch` is a plain
  coroutine: the server cancels its task when the deadline passes, with the reason recorded
  in the :class:`Context` (see :mod:`srvwire.serving`).
"""

from __future__ import annotations

import asyncio
import copy
import difflib
import enum
import functools
import inspect
import logging
import re
import threading
import time
import typing
from collections.abc import Callable, Coroutine, Iterable, Iterator, Mapping
from concurrent.futures import Executor
from dataclasses import dataclass, field
from types import CoroutineType
from typing import Any

from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticSerializationError

from srvwire.errors import (
    DeadlineExceeded,
    InterfaceConflictError,
    InternalError,
    InvalidParams,
    RegistrationError,
    RPCError,
    ServiceNotFound,
)
from srvwire.idl import MessageSpec
from srvwire.models import (
    INF_NAN_MODES,
    CallReader,
    InfNan,
    Message,
    Service,
    error_data,
    json_writer,
    reply_writer,
    summarize_errors,
    unencodable_strings,
    validate_wire,
    validation_errors,
    values_past,
)
from srvwire.protocol import Id, ReadRequest, canonical_name, encode_json, write_response
from srvwire.threads import ConcurrencyLimit, SlotJob
from srvwire.topics import TopicBoard
from srvwire.typeregistry import TypeRegistry, fingerprint, full_definition, process_types
from srvwire.version import __version__

__all__ = [
    "Context",
    "Handler",
    "ServiceEntry",
    "ServiceRegistry",
    "definitions",
    "dispatch",
    "handler_error",
    "normalize_name",
    "refuse_large_defaults",
    "refuse_large_service",
    "run_handler",
    "service_not_found",
    "write_result",
]

QUEUE_WARNING_FRACTION = 0.5
"""A blocking call that waits for a thread longer than this part of its deadline is logged."""
QUEUE_WARNING_INTERVAL = 10.0
"""Seconds: at most one such line per service in this time; it counts the calls in between."""

Handler = Callable[..., Any]
"""A service handler: ``(request)``, ``(request, response)``, optionally with a context."""

_DISCOVERY_CACHE = 64  # discovery documents kept, one per set of scopes that asked
_SEGMENT = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_NAME_RULE = (
    "a name is segments of letters, digits and '_', each starting with a letter, joined by '/'"
)


def normalize_name(name: str) -> str:
    """Return the canonical form of a service name (with a leading ``/``), or raise.

    Raise :class:`~srvwire.errors.RegistrationError` saying what is wrong with a bad name.
    """
    if not isinstance(name, str):
        raise RegistrationError(f"a service name must be a string, not {type(name).__name__}")
    canonical = canonical_name(name)
    if canonical == "/":
        raise RegistrationError(f"service name {name!r} is empty; {_NAME_RULE}")
    if canonical.endswith("/"):
        raise RegistrationError(f"service name {name!r} ends with '/'; {_NAME_RULE}")
    for segment in canonical[1:].split("/"):
        if not segment:
            raise RegistrationError(f"service name {name!r} contains '//'; {_NAME_RULE}")
        if not _SEGMENT.fullmatch(segment):
            raise RegistrationError(
                f"service name {name!r} has the bad segment {segment!r}; {_NAME_RULE}"
            )
    return canonical


class Context:
    """What a handler may know about the call it serves.

    A handler receives it through a parameter annotated ``Context`` or named ``context``.
    """

    __slots__ = (
        "_cancel_error",
        "_cancelled",
        "_wakeup",
        "channel",
        "deadline",
        "goal",
        "identity",
        "peer",
        "request_id",
        "service",
    )

    def __init__(
        self,
        *,
        service: str = "",
        request_id: Id = None,
        peer: Any = None,
        deadline: float | None = None,
        identity: Any = None,
        channel: Any = None,
    ) -> None:
        self.service = service
        """The canonical name of the service called, such as ``/add_two_ints``."""
        self.request_id = request_id
        """The JSON-RPC id of the call; ``None`` for a notification."""
        self.peer = peer
        """The caller's address, as the socket reports it (``(host, port)`` for TCP)."""
        self.deadline = deadline
        """When the caller stops waiting, on the :func:`time.monotonic` clock; None for never."""
        self.identity = identity
        """Who the connection authenticated as (a :class:`~srvwire.auth.Identity`); None when
        the server has no authentication."""
        self.channel = channel
        """The connection the call came on, as an action's goal needs it (server use)."""
        self.goal: Any = None
        """The :class:`~srvwire.actions.GoalHandle` of an action's goal, once accepted."""
        self._cancelled = False
        self._cancel_error: RPCError | None = None
        self._wakeup: threading.Event | None = None  # made by the first wait()

    def time_remaining(self) -> float | None:
        """Seconds until the caller's deadline (0 once passed), or None without a deadline."""
        if self.deadline is None:
            return None
        if isinstance(self._cancel_error, DeadlineExceeded):
            # Passed, as the server's timer found, though uvloop runs a timer up to a
            # millisecond before its time, when the clock may still say otherwise.
            return 0.0
        return max(0.0, self.deadline - time.monotonic())

    @property
    def cancelled(self) -> bool:
        """Whether the call was cancelled or its deadline passed; the answer is already sent.

        Safe to read from any thread: a blocking handler checks it to stop early.
        """
        return self._cancelled

    def wait(self, timeout: float | None = None) -> bool:
        """Block this thread until the call is cancelled or its deadline passes, or for
        ``timeout`` seconds at most (None: no limit); return whether the call is over.

        A blocking handler's ``time.sleep(t)`` that stops when its caller no longer waits:
        ``if context.wait(t): return``. Never call it from an ``async`` handler, which would
        block the event loop; there, ``await asyncio.sleep(t)`` is cancelled with the call.
        """
        wakeup = self._wakeup
        if wakeup is None:
            wakeup = self._wakeup = threading.Event()
        if self._cancelled:  # read after _wakeup is set: _mark_cancelled sees one or the other
            return True
        return wakeup.wait(timeout)

    def _mark_cancelled(self, error: RPCError | None = None) -> None:
        """Record that the call is over, and the error it is to answer (server use only)."""
        if error is not None and self._cancel_error is None:
            self._cancel_error = error  # first: time_remaining() reads it once cancelled is set
        self._cancelled = True
        wakeup = self._wakeup
        if wakeup is not None:
            wakeup.set()

    def __repr__(self) -> str:
        return (
            f"Context(service={self.service!r}, request_id={self.request_id!r}, "
            f"peer={self.peer!r}, time_remaining={self.time_remaining()!r}, "
            f"cancelled={self._cancelled!r})"
        )


ContextOf = Callable[[Any], Context]
"""Returns the :class:`Context` of a call, making it the first time (see :func:`run_handler`)."""


def _is_context_annotation(annotation: Any) -> bool:
    if annotation is Context:
        return True
    return isinstance(annotation, str) and annotation.rsplit(".", 1)[-1] == "Context"


def _introspect(name: str, handler: Handler) -> tuple[bool, bool, str | None]:
    """Return (is_async, takes_response, context parameter) for ``handler``, or raise."""
    if not callable(handler):
        raise RegistrationError(
            f"the handler for {name} must be callable, not {type(handler).__name__}"
        )
    is_async = inspect.iscoroutinefunction(handler) or inspect.iscoroutinefunction(
        getattr(handler, "__call__", None)  # noqa: B004 - an object with an async __call__
    )
    try:
        signature = inspect.signature(handler)
    except (TypeError, ValueError) as exc:
        raise RegistrationError(f"the handler for {name} has no readable signature") from exc
    try:
        hints = typing.get_type_hints(handler)
    except Exception:  # annotations that do not resolve: fall back to their text
        hints = {}
    context_param: str | None = None
    positional: list[inspect.Parameter] = []
    for param in signature.parameters.values():
        annotation = hints.get(param.name, param.annotation)
        if param.name == "context" or _is_context_annotation(annotation):
            if param.kind is inspect.Parameter.POSITIONAL_ONLY:
                raise RegistrationError(
                    f"the handler for {name} takes its context parameter {param.name!r} "
                    "positionally only; it must accept it by keyword"
                )
            context_param = param.name
        elif param.kind in (
            inspect.Parameter.POSITIONAL_ONLY,
            inspect.Parameter.POSITIONAL_OR_KEYWORD,
        ):
            if param.default is inspect.Parameter.empty or len(positional) < 2:
                positional.append(param)
        elif param.kind is inspect.Parameter.KEYWORD_ONLY and param.default is param.empty:
            raise RegistrationError(
                f"the handler for {name} has the keyword-only parameter {param.name!r} "
                "without a default; srvwire passes only the request, the response and a context"
            )
    required = [p for p in positional if p.default is inspect.Parameter.empty]
    if len(required) > 2 or not positional:
        raise RegistrationError(
            f"the handler for {name} must take (request) or (request, response), plus optionally "
            f"a context parameter; it takes {len(required)} required positional parameters"
        )
    return is_async, len(positional) == 2, context_param


@dataclass(frozen=True, slots=True, eq=False)
class ServiceEntry:
    """One registered service: its canonical name, type and handler, introspected once."""

    name: str
    srv_type: type[Service]
    handler: Handler
    is_async: bool
    takes_response: bool
    context_param: str | None
    request_model: type[BaseModel]
    response_model: type[BaseModel]
    field_names: tuple[str, ...]
    write_response: Callable[[BaseModel], bytes]
    """Writes an instance of exactly ``response_model`` as JSON, in the registry's mode."""
    write_reply: Callable[[Id, BaseModel], bytes]
    """Writes the whole response to an id with such an instance as its result, in one pass."""
    inf_nan: InfNan
    scopes: frozenset[str] = frozenset()
    """What a connection's identity must hold to call it (empty: anyone who may connect)."""
    _description: dict[str, Any] = field(default_factory=dict, repr=False)
    limit: ConcurrencyLimit | None = None
    """How many of its handlers may run at once (``max_concurrency``); None for no limit."""
    usual: bool = False
    """Whether its handler is the usual one, ``async def f(request)``, with no limit: what
    :func:`run_handler` calls with no step of its own, and the server's runner itself."""
    _queue_warned: list[float] = field(  # when it was last said, and the calls since
        default_factory=lambda: [-QUEUE_WARNING_INTERVAL, 0], repr=False
    )

    @property
    def type_name(self) -> str:
        """The service type's name, such as ``example_interfaces/srv/AddTwoInts``."""
        return str(getattr(self.srv_type, "type_name", self.srv_type.__name__))

    def validate(self, params: dict[str, Any] | list[Any] | BaseModel | None) -> BaseModel:
        """Build the request from ``params``, or raise :class:`~srvwire.errors.InvalidParams`.

        A request already read in one pass (:meth:`ServiceRegistry.read_call`) is returned as
        it is.
        """
        if type(params) is self.request_model:
            assert isinstance(params, BaseModel)
            return params
        if params is None:
            params = {}
        elif type(params) is list:
            if len(params) > len(self.field_names):
                raise InvalidParams(
                    f"invalid params for {self.name}: {len(params)} positional params, but the "
                    f"request has {len(self.field_names)} fields",
                    {
                        "errors": [
                            {
                                "path": f"[{len(self.field_names)}]",
                                "message": f"expected at most {len(self.field_names)} params",
                                "type": "too_long",
                            }
                        ]
                    },
                    service=self.name,
                )
            params = dict(zip(self.field_names, params, strict=False))
        try:
            return validate_wire(self.request_model, params)
        except ValidationError as exc:
            data = error_data(exc)
            raise InvalidParams(
                f"invalid params for {self.name}: "
                f"{summarize_errors(data['errors'], exc.error_count())}",
                data,
                service=self.name,
            ) from None

    def describe(self) -> dict[str, Any]:
        """Return this service's OpenRPC method object (built once, then cached)."""
        if not self._description:
            self._description.update(_describe(self))
        return self._description


def _inline_refs(schema: Any, defs: dict[str, Any], seen: tuple[str, ...] = ()) -> Any:
    """Replace ``#/$defs/X`` references by the definitions, so each schema stands alone."""
    if isinstance(schema, list):
        return [_inline_refs(item, defs, seen) for item in schema]
    if not isinstance(schema, dict):
        return schema
    ref = schema.get("$ref")
    if isinstance(ref, str) and ref.startswith("#/$defs/"):
        key = ref.removeprefix("#/$defs/")
        if key in defs and key not in seen:
            rest = {k: v for k, v in schema.items() if k != "$ref"}
            return {**_inline_refs(defs[key], defs, (*seen, key)), **rest}
    return {k: _inline_refs(v, defs, seen) for k, v in schema.items() if k != "$defs"}


def _standalone_schema(model: type[BaseModel]) -> dict[str, Any]:
    schema = model.model_json_schema(by_alias=True)
    defs = schema.get("$defs", {})
    inlined: dict[str, Any] = _inline_refs(schema, defs)
    return inlined


def _describe(entry: ServiceEntry) -> dict[str, Any]:
    request_schema = _standalone_schema(entry.request_model)
    properties = request_schema.get("properties", {})
    params = []
    for name in entry.field_names:
        descriptor: dict[str, Any] = {
            "name": name,
            "schema": copy.deepcopy(properties.get(name, {})),
            "required": False,
        }
        description = properties.get(name, {}).get("description")
        if description:
            descriptor["description"] = description
        params.append(descriptor)
    method: dict[str, Any] = {
        "name": entry.name,
        "paramStructure": "by-name",
        "params": params,
        "result": {"name": "response", "schema": _standalone_schema(entry.response_model)},
        "x-srvwire-type": entry.type_name,
        "x-srvwire-srv": str(getattr(entry.srv_type, "text", "")),
        "x-srvwire-definitions": definitions(entry.srv_type),
        "x-srvwire-request-schema": request_schema,
    }
    feedback = getattr(entry.srv_type, "Feedback", None)
    if isinstance(feedback, type) and issubclass(feedback, BaseModel):  # an action's goal
        method["x-srvwire-kind"] = "action"
        method["x-srvwire-feedback-schema"] = _standalone_schema(feedback)
    doc = request_schema.get("description")
    if doc:
        method["description"] = doc
    return method


def nested_messages(srv_type: type[Service]) -> list[type[Message]]:
    """Every message class ``srv_type``'s request and response nest (and an action's
    feedback), at any depth, by name."""
    feedback = getattr(srv_type, "Feedback", None)  # an action's
    if feedback is not None:
        return nested_messages_of(srv_type.Request, srv_type.Response, feedback)
    return nested_messages_of(srv_type.Request, srv_type.Response)


def nested_messages_of(*models: type[BaseModel]) -> list[type[Message]]:
    """Every message class ``models`` nest, at any depth, by name."""
    found: dict[str, type[Message]] = {}
    todo: list[type[BaseModel]] = list(models)
    while todo:
        model = todo.pop()
        for info in model.model_fields.values():
            for nested in _message_classes(info.annotation):
                name = getattr(nested, "type_name", None)
                if isinstance(name, str) and name not in found:
                    found[name] = nested
                    todo.append(nested)
    return [found[name] for name in sorted(found)]


def refuse_large_defaults(
    what: str, model: type[BaseModel], made: str, limit: int | None, *, remedy: str = ""
) -> None:
    """Raise RegistrationError when an instance of ``model`` made without its fields holds
    more values than ``limit`` (the server's ``max_message_size``) can carry.

    The server makes such an instance ``made`` (for each request that leaves them out, ...):
    a peer's message of a few bytes would make it hold them all, once per call in flight. A
    model with no spec (a class written by hand), or nesting one, is not counted.
    """
    spec = getattr(model, "spec", None)
    if limit is None or not isinstance(spec, MessageSpec):
        return
    specs = {
        cls.type_name: cls.spec
        for cls in nested_messages_of(model)
        if isinstance(getattr(cls, "spec", None), MessageSpec)
    }
    try:
        held = values_past(limit, spec, specs.__getitem__, {})
    except KeyError:  # it nests a class with no spec, whose values are not known
        return
    if held is not None:
        raise RegistrationError(
            f"{what}: {getattr(model, 'type_name', model.__name__)} holds {held} when made "
            f"without its fields, more than max_message_size={limit} can carry, and the server "
            f"makes one {made}: a message of a few bytes would make it hold them all. Raise "
            "the server's max_message_size (None lifts this check with the limit), or declare "
            f"the fixed array bounded (T[<=N]) or unbounded (T[]){remedy}"
        )


def refuse_large_service(
    name: str,
    request_model: type[BaseModel],
    response_model: type[BaseModel],
    takes_response: bool,
    limit: int | None,
) -> None:
    """:func:`refuse_large_defaults` for the service ``name``: its request, and its response
    when the handler takes one (made bare for each call)."""
    what = f"cannot serve {name}"
    refuse_large_defaults(what, request_model, "for each request that leaves them out", limit)
    if takes_response:
        remedy = ", or let the handler take the request only and return the response"
        made = "for each call, to give the handler"
        refuse_large_defaults(what, response_model, made, limit, remedy=remedy)


def _message_classes(annotation: Any) -> Iterator[type[Message]]:
    if isinstance(annotation, type) and issubclass(annotation, Message):
        yield annotation
    for argument in typing.get_args(annotation):
        yield from _message_classes(argument)


def definitions(srv_type: type[Service]) -> dict[str, str]:
    """The definition text of a service type and of every message it nests, by full name.

    This is what ``rpc.discover`` tells a client that does not have the types itself
    (``x-srvwire-definitions``). A type whose class carries no text (a class written by hand)
    is left out.
    """
    texts: dict[str, str] = {}
    text = getattr(srv_type, "text", "")
    if isinstance(text, str) and text:
        texts[str(srv_type.type_name)] = text
    for nested in nested_messages(srv_type):
        if "/msg/" not in nested.type_name:  # an action's result, described with the action
            continue
        nested_text: object = getattr(getattr(nested, "spec", None), "text", None)
        if isinstance(nested_text, str) and nested_text:
            texts[nested.type_name] = nested_text
    return texts


def _adopt(srv_type: type[Service], types: TypeRegistry, service: str) -> None:
    """Record the classes a registered service uses as the process's, where they have specs.

    So a client in the same process that builds them from this server's description gets these
    very classes. A conflicting definition is a :class:`~srvwire.errors.RegistrationError`.
    """
    classes: list[Any] = [srv_type, *nested_messages(srv_type)]
    for cls in classes:
        spec = getattr(cls, "spec", None)
        if spec is None or not hasattr(cls, "type_name"):
            continue
        path = getattr(spec, "path", None)
        source = path or f"the class {cls.__module__}.{cls.__qualname__} given for {service}"
        try:
            types.adopt(cls, source)
        except InterfaceConflictError as exc:
            raise RegistrationError(f"cannot register {service}: {exc}") from None


_PROTOCOL_PREFIXES = ("$/", "rpc.")
"""How the names of protocol methods begin: srvwire's own, and those JSON-RPC reserves."""


def service_not_found(name: str, names: Iterable[str]) -> ServiceNotFound:
    """The error for a service ``name`` that is not among ``names``, offering close ones.

    A name that cannot be a service's (empty, or a protocol method: ``$/…``, JSON-RPC's
    ``rpc.…``) is named as it was given, without the ``/`` a service name takes."""
    if not name or name.startswith(_PROTOCOL_PREFIXES):
        return ServiceNotFound(
            f'no method named "{name}"', {"candidates": []}, service=name or None
        )
    wanted = canonical_name(name)
    candidates = difflib.get_close_matches(wanted, list(names), n=3, cutoff=0.6)
    hint = f"; did you mean {', '.join(candidates)}?" if candidates else ""
    return ServiceNotFound(
        f"no service named {wanted}{hint}", {"candidates": candidates}, service=wanted
    )


def _no_reader(data: str | bytes) -> None:
    """A :attr:`ServiceRegistry.read_call` that reads nothing in one pass."""
    return None


class ServiceRegistry:
    """The services one server offers, by canonical name.

    ``inf_nan`` is how their responses write non-finite floats (:data:`~srvwire.models.InfNan`).
    """

    def __init__(
        self, types: TypeRegistry | None = None, *, inf_nan: InfNan = INF_NAN_MODES[0]
    ) -> None:
        if inf_nan not in INF_NAN_MODES:
            raise ValueError(f"inf_nan must be one of {', '.join(INF_NAN_MODES)}, not {inf_nan!r}")
        self.inf_nan: InfNan = inf_nan
        self._entries: dict[str, ServiceEntry] = {}
        self._names: dict[str, ServiceEntry] = {}  # each entry by its name, and without its "/"
        self.get: Callable[[str], ServiceEntry | None] = self._names.get
        """Return the service called ``name`` (the leading ``/`` optional), or None.

        The bound ``get`` of a dictionary that holds both spellings of every name: a call
        is looked up in C, with no Python step of its own."""
        self._discovery: dict[frozenset[str] | None, str] = {}  # by the scopes it shows
        self._fingerprints: dict[str, str] = {}  # of the types that have a definition
        self.topics: TopicBoard[Any] = TopicBoard()
        """The server's topics (their entries are :class:`srvwire.pubsub.TopicEntry`)."""
        self.types = process_types() if types is None else types
        self.read_call: Callable[[str | bytes], ReadRequest | None] = self._read_call
        """Read a request to one of these services in one pass; None: parse it in full.

        What it returns is the request's ``id``, ``method``, ``params`` and ``timeout``
        (:data:`~srvwire.protocol.ReadRequest`): the ``params`` are its service's ``Request``,
        already validated, with ``_meta`` taken out and read into the ``timeout``.
        Only a request that the full parse would read the same way, and whose params would
        validate to an equal instance, is read so; anything else (notifications, batches,
        protocol methods, an invalid message or ``_meta``, params that do not validate, a
        service whose ``Request`` is not one of srvwire's classes) is None, for the full parse
        to answer it (see :class:`~srvwire.models.CallReader`). Its reader is built at the
        first call after the services changed.
        """

    def add(
        self,
        name: str,
        srv_type: type[Service],
        handler: Handler,
        scopes: Iterable[str] = (),
        *,
        max_concurrency: int | None = None,
        max_values: int | None = None,
    ) -> ServiceEntry:
        """Register ``handler`` for ``srv_type`` under ``name``, callable by identities that
        hold every one of ``scopes``; raise RegistrationError.

        ``max_concurrency`` bounds how many calls of this service run their handler at once
        (see :func:`dispatch`). ``max_values`` (the server's ``max_message_size``) refuses a
        request, or a response the handler is given, too large to make bare per call (see
        :func:`refuse_large_defaults`).
        """
        canonical = normalize_name(name)
        if isinstance(scopes, str):
            raise RegistrationError(
                f"the scopes of {canonical} must be a collection of names, such as "
                f"{{{scopes!r}}}, not the string {scopes!r}"
            )
        if max_concurrency is not None and (
            type(max_concurrency) is not int or max_concurrency < 1
        ):
            raise RegistrationError(
                f"max_concurrency for {canonical} must be a whole number at least 1, "
                f"not {max_concurrency!r}"
            )
        existing = self._entries.get(canonical)
        if existing is not None:
            raise RegistrationError(
                f"a service named {canonical} is already registered "
                f"({existing.type_name}); remove it first"
            )
        request_model = getattr(srv_type, "Request", None)
        response_model = getattr(srv_type, "Response", None)
        if not (
            isinstance(request_model, type)
            and issubclass(request_model, BaseModel)
            and isinstance(response_model, type)
            and issubclass(response_model, BaseModel)
        ):
            if hasattr(srv_type, "Goal"):
                raise RegistrationError(
                    f"{canonical}: {srv_type!r} is an action type; serve it with "
                    "server.action(name, Action) (or add_action), not as a service"
                )
            raise RegistrationError(
                f"the type of {canonical} must be a service type with Request and Response "
                f"models (such as load_service('example_interfaces/srv/AddTwoInts')), "
                f"not {srv_type!r}"
            )
        is_async, takes_response, context_param = _introspect(canonical, handler)
        refuse_large_service(canonical, request_model, response_model, takes_response, max_values)
        _adopt(srv_type, self.types, canonical)
        entry = ServiceEntry(
            name=canonical,
            srv_type=srv_type,
            handler=handler,
            is_async=is_async,
            takes_response=takes_response,
            context_param=context_param,
            request_model=request_model,
            response_model=response_model,
            field_names=tuple(
                info.alias or field_name for field_name, info in request_model.model_fields.items()
            ),
            scopes=frozenset(scopes),
            write_response=json_writer(response_model, self.inf_nan, strict=True),
            write_reply=reply_writer(response_model, self.inf_nan, strict=True),
            inf_nan=self.inf_nan,
            limit=None if max_concurrency is None else ConcurrencyLimit(max_concurrency),
            usual=is_async and not takes_response and not context_param and max_concurrency is None,
        )
        self._entries[canonical] = entry
        self._names[canonical] = self._names[canonical[1:]] = entry
        definition = full_definition(srv_type)
        if definition is not None:
            self._fingerprints[canonical] = fingerprint(definition)
        self._discovery.clear()
        self.read_call = self._read_call
        return entry

    def remove(self, name: str) -> ServiceEntry:
        """Unregister the service ``name`` and return its entry; raise RegistrationError."""
        canonical = normalize_name(name)
        entry = self._entries.pop(canonical, None)
        if entry is None:
            raise RegistrationError(f"no service named {canonical} is registered")
        del self._names[canonical], self._names[canonical[1:]]
        self._fingerprints.pop(canonical, None)
        self._discovery.clear()
        self.read_call = self._read_call
        return entry

    def resolve(self, name: str) -> ServiceEntry:
        """Return the service called ``name``, or raise ServiceNotFound listing close names."""
        entry = self.get(name)
        if entry is not None:
            return entry
        raise service_not_found(name, self._entries)

    def _read_call(self, data: str | bytes) -> ReadRequest | None:
        """:attr:`read_call` before its reader is built: build it, then read."""
        requests = {entry.name: entry.request_model for entry in self._entries.values()}
        try:
            self.read_call = CallReader(requests).read
        except Exception:  # a schema pydantic-core will not take: every call takes the full
            self.read_call = _no_reader  # parse, which answers it as it always did
        return self.read_call(data)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self.get(name) is not None

    def __iter__(self) -> Iterator[ServiceEntry]:
        return iter(sorted(self._entries.values(), key=lambda e: e.name))

    def __len__(self) -> int:
        return len(self._entries)

    def visible(self, scopes: frozenset[str] | None = None) -> Iterator[ServiceEntry]:
        """The services a connection holding ``scopes`` may call (None: every service)."""
        for entry in self:
            if scopes is None or entry.scopes <= scopes:
                yield entry

    def services(self, scopes: frozenset[str] | None = None) -> list[tuple[str, str]]:
        """Return ``(name, type name)`` of every service ``scopes`` may call, sorted by name."""
        return [(entry.name, entry.type_name) for entry in self.visible(scopes)]

    def fingerprints(self) -> Mapping[str, str]:
        """The fingerprint of each service's full definition, by service name, for the
        services whose type has one (see :func:`srvwire.typeregistry.fingerprint`)."""
        return self._fingerprints

    def discover(self, scopes: frozenset[str] | None = None) -> dict[str, Any]:
        """Return the OpenRPC 1.3.2 document describing every service ``scopes`` may call."""
        methods = []
        for entry in self.visible(scopes):
            method = entry.describe()
            if entry.name in self._fingerprints:
                method["x-srvwire-fingerprint"] = self._fingerprints[entry.name]
            methods.append(method)
        return {
            "openrpc": "1.3.2",
            "info": {"title": "srvwire", "version": __version__},
            "methods": methods
            + [topic.entry.describe(topic) for topic in self.topics.visible(scopes)],
        }

    def topics_changed(self) -> None:
        """The topics changed: describe them again when asked."""
        self._discovery.clear()

    def discover_json(self, scopes: frozenset[str] | None = None) -> str:
        """Return :meth:`discover` as JSON text, cached until the services change."""
        document = self._discovery.get(scopes)
        if document is None:
            if len(self._discovery) >= _DISCOVERY_CACHE:  # as many as sets of scopes seen
                self._discovery.clear()
            document = self._discovery[scopes] = encode_json(self.discover(scopes))
        return document


def _invalid_return(
    entry: ServiceEntry, result: object, reason: str, logger: logging.Logger | None
) -> InternalError:
    (logger or logging.getLogger(__name__)).error(
        "handler for %s returned %s, which is not a valid %s response: %s",
        entry.name,
        type(result).__name__,
        entry.type_name,
        reason,
    )
    return InternalError(
        f"handler for {entry.name} returned an invalid response", service=entry.name
    )


class _Alone(enum.Enum):
    """:func:`run_handler` returns the result alone, not a whole response (its default)."""

    RESULT = 0


def _encode_response(
    entry: ServiceEntry,
    result: Any,
    prebuilt: BaseModel | None,
    logger: logging.Logger | None,
    reply_id: Id | _Alone = _Alone.RESULT,
) -> bytes:
    model = entry.response_model
    if result is None:
        if prebuilt is not None:
            result = prebuilt
        elif not model.model_fields:
            result = model()
    response = result
    if isinstance(result, dict):
        try:
            response = model.model_validate(result)
        except ValidationError as exc:
            raise _invalid_return(entry, result, _reasons(validation_errors(exc)), logger) from None
    if isinstance(response, model):  # a model the handler built is not validated again
        try:
            if type(response) is model:
                if reply_id is not _Alone.RESULT:
                    return entry.write_reply(reply_id, response)
                return entry.write_response(response)
            # A subclass: by its own class, so that the fields it adds are written too.
            written = json_writer(type(response), entry.inf_nan, strict=True)(response)
            return written if reply_id is _Alone.RESULT else write_response(reply_id, written)
        except PydanticSerializationError as exc:
            # A lone surrogate in a string passes validation and fails here; say where it is.
            reason = _reasons(unencodable_strings(response)) or str(exc)
            raise _invalid_return(entry, result, reason, logger) from None
    raise _invalid_return(entry, result, f"expected {model.__name__} or a dict", logger)


def _reasons(errors: list[dict[str, str]]) -> str:
    return "; ".join(f"{e['path'] or '(response)'}: {e['message']}" for e in errors)


def _invoke(
    entry: ServiceEntry,
    request: BaseModel,
    context_of: ContextOf,
    work: Any,
    executor: Executor | None,
    logger: logging.Logger | None = None,
) -> tuple[Coroutine[Any, Any, Any], BaseModel | None]:
    """Start calling the handler the way it was registered to be called.

    Return the coroutine that runs it (the handler's own, for an async handler) and the
    response built for a handler of the ROS shape ``(request, response)``. The call's context
    is made (``context_of(work)``) only for a handler that takes it or runs in a thread.
    """
    args: tuple[Any, ...]
    prebuilt: BaseModel | None = None
    if entry.takes_response:
        prebuilt = entry.response_model()
        args = (request, prebuilt)
    else:
        args = (request,)
    if entry.is_async:
        if entry.context_param:
            awaitable = entry.handler(*args, **{entry.context_param: context_of(work)})
        else:
            awaitable = entry.handler(*args)
        if type(awaitable) is not CoroutineType:  # a function marked as a coroutine function
            awaitable = _await(awaitable)
        return awaitable, prebuilt
    context = context_of(work)
    kwargs = {entry.context_param: context} if entry.context_param else {}
    job = _Blocking(entry, functools.partial(entry.handler, *args, **kwargs), context, logger)
    return _run_in_executor(job, executor), prebuilt


async def _await(awaitable: Any) -> Any:
    return await awaitable


async def _run_in_executor(job: _Blocking, executor: Executor | None) -> Any:
    try:
        result = await asyncio.get_running_loop().run_in_executor(executor, job)
    except BaseException:  # its caller left, or the executor refused it: if it never ran
        job.leave()
        raise
    if inspect.isawaitable(result):
        result = await result
    return result


class _Blocking(SlotJob):
    """A blocking handler's call, as its thread runs it.

    It holds its service's slot (:attr:`ServiceEntry.limit`) until the handler returns, or, if
    its caller leaves before a thread took it, until then: a job whose caller left never runs
    its handler. A job that waited for its thread past :data:`QUEUE_WARNING_FRACTION` of its
    deadline says so (see :meth:`check_wait`).
    """

    __slots__ = ("context", "entry", "log", "queued")

    def __init__(
        self,
        entry: ServiceEntry,
        call: Callable[[], Any],
        context: Context,
        logger: logging.Logger | None,
    ) -> None:
        super().__init__(call, entry.limit)
        self.entry = entry
        self.context = context
        self.log = logger
        self.queued = time.monotonic()

    def abandoned(self) -> bool:
        return self.context._cancelled  # its caller left: nobody waits for it any more

    def starting(self) -> None:
        self.check_wait(time.monotonic())

    def leaving(self) -> None:
        self.check_wait(time.monotonic())

    def check_wait(self, now: float) -> None:
        """Log, at most once per :data:`QUEUE_WARNING_INTERVAL` and service, a job that waited
        for a thread past :data:`QUEUE_WARNING_FRACTION` of its deadline."""
        deadline = self.context.deadline
        if deadline is None:
            return
        waited = now - self.queued
        if waited <= QUEUE_WARNING_FRACTION * (deadline - self.queued):
            return
        warned = self.entry._queue_warned
        warned[1] += 1
        if now - warned[0] < QUEUE_WARNING_INTERVAL:
            return
        count = warned[1]
        warned[0], warned[1] = now, 0
        (self.log or logging.getLogger(__name__)).warning(
            "a call to %s waited %.3g s for a thread to run its blocking handler, %d%% of its "
            "deadline%s; every thread is busy: give blocking handlers more threads "
            "(Server(executor=HandlerThreads(max_workers=N))), or bound the slow services "
            "(max_concurrency=N)",
            self.entry.name,
            waited,
            min(100, round(100 * waited / max(deadline - self.queued, 1e-9))),
            f" (and {count - 1} more since the last such line)" if count > 1 else "",
        )


async def dispatch(
    entry: ServiceEntry,
    params: dict[str, Any] | list[Any] | None,
    context: Context,
    *,
    executor: Executor | None = None,
    logger: logging.Logger | None = None,
) -> bytes:
    """Validate ``params``, run the handler, and return the response as UTF-8 JSON bytes.

    Raise an :class:`~srvwire.errors.RPCError` for the caller: InvalidParams, InternalError,
    DeadlineExceeded for a deadline that had passed before the handler could start, or
    whatever RPCError the handler raised. Cancelling the task that runs this cancels the
    handler and marks ``context`` cancelled; a deadline that passes later is enforced that
    way, by whoever runs the call.
    """
    return await run_handler(entry, params, context.deadline, _given, context, executor, logger)


def _given(context: Context) -> Context:
    return context


async def run_handler(
    entry: ServiceEntry,
    params: dict[str, Any] | list[Any] | BaseModel | None,
    deadline: float | None,
    context_of: ContextOf,
    work: Any,
    executor: Executor | None,
    logger: logging.Logger | None,
    reply_id: Id | _Alone = _Alone.RESULT,
) -> bytes:
    """:func:`dispatch`, with the call's :class:`Context` made only if something needs it.

    ``context_of(work)`` returns the context of the call ``work`` (making it the first time),
    and ``deadline`` is its deadline: a handler that takes no context, runs on the loop, and
    is neither cancelled nor late never has one made (the server's call runner, which keeps
    the context on the call, passes its own ``context_of``). With a ``reply_id`` (null is one),
    what is returned is the whole response to that id, written with the result in one pass (a large
    result is never a separate copy), rather than the result alone.
    """
    try:  # a request read in one pass is validated already
        request = params if type(params) is entry.request_model else entry.validate(params)
    except InvalidParams:
        raise
    except (Exception, asyncio.CancelledError) as exc:
        # A validator in the model raised something pydantic does not wrap. Validation never
        # awaits, so not even a CancelledError from it can be this task's own cancellation.
        context = context_of(work)
        raise _handler_raised(entry, context, exc, logger, "validating the request") from None
    limit = entry.limit
    try:
        if deadline is not None and deadline <= time.monotonic():
            raise _deadline_exceeded(entry, context_of(work))
        if limit is not None:
            result, prebuilt = await _limited(
                entry, limit, request, context_of, work, executor, logger
            )
        elif entry.usual:
            prebuilt = None  # the usual handler, ``async def f(request)``: _invoke's steps here
            handler = entry.handler(request)
            result = await (handler if type(handler) is CoroutineType else _await(handler))
        else:
            handler, prebuilt = _invoke(entry, request, context_of, work, executor, logger)
            result = await handler
    except (Exception, asyncio.CancelledError) as exc:
        error = handler_error(entry, exc, context_of, work, logger)
        if error is exc:
            raise
        raise error from None
    if type(result) is entry.response_model:  # most handlers: written as _encode_response would
        try:
            if reply_id is _Alone.RESULT:
                return entry.write_response(result)
            return entry.write_reply(reply_id, result)
        except PydanticSerializationError:
            pass  # _encode_response says why, writing it once more
    return _encode_response(entry, result, prebuilt, logger, reply_id)


def handler_error(
    entry: ServiceEntry,
    exc: Exception | asyncio.CancelledError,
    context_of: ContextOf,
    work: Any,
    logger: logging.Logger | None,
) -> BaseException:
    """What a handler's exception, raised while it ran, is to its call: an :class:`RPCError`
    itself, named after the service; the cancellation of the running task itself, the call's
    context marked cancelled; anything else (a cancellation nobody asked of this task
    included: the handler awaited something cancelled under it, and re-raising it would end
    the call without a reply) an ``InternalError``, logged with its traceback.
    """
    if isinstance(exc, RPCError):
        if exc.service is None:
            exc.service = entry.name
        return exc
    if isinstance(exc, asyncio.CancelledError) and _being_cancelled():
        context_of(work)._mark_cancelled()
        return exc
    return _handler_raised(entry, context_of(work), exc, logger)


def write_result(
    entry: ServiceEntry, result: Any, logger: logging.Logger | None, reply_id: Id
) -> bytes:
    """The whole response to ``reply_id`` with what the usual handler returned, as
    :func:`run_handler` writes it."""
    if type(result) is entry.response_model:
        try:
            return entry.write_reply(reply_id, result)
        except PydanticSerializationError:
            pass  # _encode_response says why, writing it once more
    return _encode_response(entry, result, None, logger, reply_id)


async def _limited(
    entry: ServiceEntry,
    limit: ConcurrencyLimit,
    request: BaseModel,
    context_of: ContextOf,
    work: Any,
    executor: Executor | None,
    logger: logging.Logger | None,
) -> tuple[Any, BaseModel | None]:
    """Run the handler once a slot of its service is free; hold it until the handler returns
    (a blocking handler's thread gives it back, since it may run on after its caller left)."""
    await limit.acquire()
    try:
        handler, prebuilt = _invoke(entry, request, context_of, work, executor, logger)
    except BaseException:
        limit.release()
        raise
    if not entry.is_async:
        return await handler, prebuilt
    try:
        return await handler, prebuilt
    finally:
        limit.release()


def _being_cancelled() -> bool:
    """Whether the running task has a cancellation request pending (it is being cancelled)."""
    task = asyncio.current_task()
    return task is not None and task.cancelling() > 0


def _deadline_exceeded(entry: ServiceEntry, context: Context) -> DeadlineExceeded:
    context._mark_cancelled()
    return DeadlineExceeded(
        f"the deadline for {entry.name} passed before the handler finished", service=entry.name
    )


def _handler_raised(
    entry: ServiceEntry,
    context: Context,
    exc: BaseException,
    logger: logging.Logger | None,
    doing: str = "",
) -> InternalError:
    what = f"{doing} for {entry.name}" if doing else f"handler for {entry.name}"
    (logger or logging.getLogger(__name__)).error(
        "%s raised an exception (request id %r)", what, context.request_id, exc_info=exc
    )
    return InternalError(f"{what} raised an exception", service=entry.name)
