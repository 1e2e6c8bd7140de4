"""What a call sends and gets back, on the client's side: types, requests, deadlines.

A client resolves a service's type by name through a :data:`TypeResolver` (by default the
interface loader), validates and writes a request with :func:`encode_request`, and decodes a
reply with the :class:`~srvwire.models.ModelDecoder` of the type's ``Response``; the
:class:`ServiceTypes` of a client keeps both, one per type, for the client's life.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeAlias

from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticSerializationError

from srvwire.errors import InterfaceError, InvalidParams
from srvwire.models import (
    INF_NAN_MODES,
    InfNan,
    Message,
    ModelDecoder,
    Service,
    dump_json,
    error_data,
    json_writer,
    listed_errors,
    summarize_errors,
    unencodable_strings,
    validate_python,
)
from srvwire.protocol import describe_value, encode_json, timeout_seconds

__all__ = [
    "ServiceCodec",
    "ServiceInfo",
    "ServiceTypes",
    "SrvType",
    "TypeResolver",
    "check_timeout",
    "encode_request",
    "validate_request",
]

SrvType: TypeAlias = type[Service] | str
"""A service type: the class, or its name (``pkg/srv/Name``) to resolve."""

TypeResolver: TypeAlias = Callable[[str], type[Service]]
"""Turns a service type name into its class, or raises InterfaceError; default: the loader."""


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


def encode_request(
    method: str, codec: ServiceCodec | None, request: BaseModel | Mapping[str, Any] | None
) -> str:
    """Validate ``request`` when its type is known and return its JSON text (an object).

    Raise :class:`~srvwire.errors.InvalidParams` for a request that does not validate or
    cannot be written (nothing is sent then), ``TypeError`` for a model of another type or
    one that is not written as a JSON object.
    """
    srv = None if codec is None else codec.service
    if codec is not None and type(request) is codec.service.Request:  # the common case
        try:
            text = codec.write(request).decode()
        except PydanticSerializationError:
            pass  # said below, with the field
        else:
            if text[:1] == "{":
                return text
    value: BaseModel | Mapping[str, Any] = {} if request is None else request
    if srv is not None and not isinstance(value, srv.Request):
        if isinstance(value, BaseModel):
            raise TypeError(
                f"{method} takes {srv.type_name} requests, not {type(value).__qualname__}"
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

    __slots__ = ("decoder", "inf_nan", "service", "write")

    def __init__(self, service: type[Service], inf_nan: InfNan = INF_NAN_MODES[0]) -> None:
        self.service = service
        self.inf_nan: InfNan = inf_nan
        self.decoder: ModelDecoder[Message] = ModelDecoder(service.Response)
        self.write: Callable[[Any], bytes] = json_writer(service.Request, inf_nan)


class ServiceTypes:
    """Which type a call's messages have, given or advertised, each made ready once.

    A type given by name that cannot be resolved is an error; one the server advertised is
    logged once, and its calls send and return plain dicts.
    """

    def __init__(
        self,
        resolve: TypeResolver,
        logger: logging.Logger | logging.LoggerAdapter[Any],
        inf_nan: InfNan = INF_NAN_MODES[0],
    ) -> None:
        self._resolve = resolve
        self._logger = logger
        self._inf_nan: InfNan = inf_nan
        self._by_name: dict[str, ServiceCodec | None] = {}
        self._by_class: dict[type[Service], ServiceCodec] = {}

    def service(
        self, method: str, srv_type: SrvType | None, advertised: str | None
    ) -> ServiceCodec | None:
        """Return the type of ``method``'s messages, or None to send and return plain dicts."""
        if srv_type is not None and not isinstance(srv_type, str):
            return self._codec(srv_type)
        named = srv_type is not None
        type_name = srv_type if srv_type is not None else advertised
        if type_name is None:
            return None
        if type_name in self._by_name:
            cached = self._by_name[type_name]
            if cached is not None or not named:
                return cached
        codec: ServiceCodec | None
        try:
            codec = self._codec(self._resolve(type_name))
        except InterfaceError as exc:
            if named:
                raise  # the caller named a type that cannot be resolved: say so
            self._logger.info(
                "cannot load %s for %s (%s); its calls send and return plain dicts",
                type_name,
                method,
                exc,
            )
            codec = None
        self._by_name[type_name] = codec
        return codec

    def _codec(self, service: type[Service]) -> ServiceCodec:
        codec = self._by_class.get(service)
        if codec is None:
            codec = self._by_class[service] = ServiceCodec(service, self._inf_nan)
        return codec
