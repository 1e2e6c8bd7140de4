"""JSON-RPC 2.0 without I/O: text in, messages out; messages in, UTF-8 JSON out.

Nothing here awaits, touches a socket or knows about transports; the sessions
(:mod:`srvwire.session`) keep the rules of a conversation, this module the rules of one message.

Invariants:

* **One writer per message.** Every message has one ``serialize()``, which returns compact
  UTF-8 JSON bytes, the form every transport sends as a text message. Data that is not JSON
  (a set, an object) is written with ``str()`` and a non-finite float as ``null`` rather than
  failing, because an error reply must always be sendable; only a request or notification
  whose ``_meta.timeout`` cannot be written (not a finite number, or one beside params that
  are not an object) raises ``ValueError``, since ``null`` would mean "no deadline".
  :class:`RawJSON` is JSON already written (text or UTF-8 bytes, as pydantic writes it); as a
  result or as params it is spliced in as it is, never decoded again, so a large result is
  copied once.
* **One reader per side.** :func:`parse_incoming` reads what a client sends and never raises:
  every item is a :class:`Request`, a :class:`Notification` or an :class:`ErrorResponse` ready
  to be sent back. Input that is not JSON, not UTF-8, or nested deeper than :data:`MAX_DEPTH`
  is one ``PARSE_ERROR``; an empty batch is one ``INVALID_REQUEST``; an invalid item of a batch
  is an ``INVALID_REQUEST`` in its place. :func:`parse_replies` reads what a server sends and
  raises :class:`~srvwire.errors.ParseError` or :class:`~srvwire.errors.InvalidRequest` when it
  is not JSON-RPC: a server that breaks the protocol is a bug to report, not a peer to answer.
* **A reply is decoded in one place.** Each reply has one ``decode(decoder)``: the result, or
  the error it carries raised. A :class:`RawReply` (a response recognised by its opening alone,
  :func:`peek_reply`) validates its result text in one pass and falls back to the full parse
  when that is refused; a message that turns out not to be JSON-RPC raises
  :class:`ProtocolViolation`, never an error a server could have sent.
* **An id is echoed exactly as it came** (string, number or null). An invalid item whose id
  can be read gets its id back; otherwise ``null``. A number id must be finite; a boolean is
  never an id. A message without an ``id`` member is a notification and is never answered,
  unless it is so malformed that it is not a notification at all.
* **``params._meta`` belongs to the protocol, not to the service.** It is taken out of
  ``params`` while parsing: ``{"timeout": seconds}`` becomes :attr:`Request.timeout`; other
  members are ignored so that later versions can add some. A bad ``_meta`` is an
  ``INVALID_PARAMS`` error with the path ``_meta`` or ``_meta.timeout``: a request gets it as
  its reply; a notification carries it in :attr:`Notification.error` and is dropped.

The message classes are plain (not frozen) slotted dataclasses: one is made per message on the
hot path, and a frozen one costs about 2.5 times as much to create. Treat them as values.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, TypeAlias, TypeVar

from pydantic_core import from_json, to_json

from srvwire.errors import (
    InvalidParams,
    InvalidRequest,
    ParseError,
    RPCError,
    error_from_code,
)

__all__ = [
    "CANCEL_METHOD",
    "DISCOVER_METHOD",
    "MAX_DEPTH",
    "REPLY_OPENING",
    "SERVICES_METHOD",
    "WHOLE_REPLY_SIZE",
    "CallWriter",
    "Decoder",
    "ErrorResponse",
    "Id",
    "Incoming",
    "Notification",
    "Params",
    "ProtocolViolation",
    "RawJSON",
    "RawReply",
    "ReadRequest",
    "Reply",
    "Request",
    "Response",
    "cancel_notification",
    "canonical_name",
    "decode_json",
    "describe_value",
    "encode_json",
    "parse_incoming",
    "parse_replies",
    "peek_reply",
    "read_cancel",
    "read_meta",
    "serialize_batch",
    "services_notification",
    "timeout_seconds",
    "valid_id",
    "write_call",
    "write_response",
]

CANCEL_METHOD = "$/cancel"
"""Notification a client sends to cancel one of its calls: ``{"id": <request id>}``."""

SERVICES_METHOD = "$/services"
"""Notification the server sends with the full, sorted list of services it offers."""

DISCOVER_METHOD = "rpc.discover"
"""Method that returns the OpenRPC document describing every service."""

SUBSCRIBE_METHOD = "$/subscribe"
"""A long-lived request to receive a topic; its reply ends the subscription."""

SUBSCRIBED_METHOD = "$/subscribed"
"""The server's notification that a subscription started, with the QoS granted."""

MESSAGE_METHOD = "$/message"
"""One message of a subscription: ``subscription``, ``seq``, ``dropped``, ``message``."""

PUBLISH_METHOD = "$/publish"
"""A message a client publishes on a topic (a notification, or a request to be answered)."""

TOPICS_METHOD = "$/topics"
"""The server's announcement of its topics, as ``$/services`` is of its services."""

MAX_DEPTH = 200
"""How many arrays and objects may enclose a value in one message; deeper input is a parse error.

This is pydantic_core's own recursion limit, which :func:`decode_json` relies on rather than
walking the decoded value again; the tests pin both sides of it. An empty array or object is a
value itself, so it may sit one level deeper than this.
"""

Id: TypeAlias = str | int | float | None
"""A JSON-RPC id: a string, a number, or null."""

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)


@dataclass(slots=True)
class RawJSON:
    """One JSON value already written, as text or UTF-8 bytes; embedded without re-encoding."""

    text: str | bytes


Params: TypeAlias = dict[str, Any] | list[Any] | RawJSON | None
"""What ``params`` may hold: an object, an array, pre-encoded JSON, or nothing."""


class ProtocolViolation(Exception):
    """Raised when what a server sent is not JSON-RPC; ``error`` says what is wrong with it."""

    def __init__(self, error: ParseError | InvalidRequest) -> None:
        super().__init__(error.message)
        self.error = error


class Decoder(Protocol[T_co]):
    """Turns a result into a typed value: from JSON text in one pass, or from parsed data.

    Both raise ``ValueError`` (pydantic's ``ValidationError`` is one) when the result does not
    fit; :mod:`srvwire.models` makes them.
    """

    def from_json(self, text: str) -> T_co: ...

    def from_data(self, data: Any) -> T_co: ...

    def from_reply(self, message: str, id: int) -> T_co:
        """The result of ``message``, a whole response to ``id``, validated with its envelope in
        one pass; ``ValueError`` for anything else (another id, another member)."""
        ...


def encode_json(value: Any) -> str:
    """Return ``value`` as compact JSON text; never fails (see the module's invariants)."""
    if isinstance(value, RawJSON):
        text = value.text
        return text if isinstance(text, str) else text.decode()
    return to_json(value, fallback=str, inf_nan_mode="null").decode()


def decode_json(data: str | bytes) -> Any:
    """Parse one JSON value strictly, or raise :class:`~srvwire.errors.ParseError`.

    Bytes must be UTF-8. Trailing text and nesting deeper than :data:`MAX_DEPTH` are refused.
    Integers of any size are read exactly. The tokens ``NaN``, ``Infinity`` and ``-Infinity``
    are accepted, as Python's ``json`` accepts them, because a peer in the ``"constants"``
    ``inf_nan`` mode writes non-finite floats that way.
    """
    if isinstance(data, memoryview):
        data = data.tobytes()
    try:
        # pydantic_core reads bytes as they are, without a decoded copy; it refuses any byte
        # sequence that is not UTF-8, in a string or outside one.
        return from_json(data, allow_inf_nan=True)
    except (ValueError, TypeError) as exc:
        if not isinstance(data, str):
            try:
                bytes(data).decode("utf-8")  # only on the error path: say where UTF-8 breaks
            except UnicodeDecodeError as bad:
                raise ParseError(
                    f"Parse error: invalid UTF-8 at byte {bad.start}", {"detail": bad.reason}
                ) from None
        # pydantic_core reports nesting past MAX_DEPTH as "recursion limit exceeded", and a
        # str holding a lone surrogate as a TypeError.
        raise ParseError(f"Parse error: {exc}") from None


def _encode_id(id: Id) -> str:
    if type(id) is int:
        return str(id)
    return encode_json(id)


def _encode_method(method: str) -> str:
    """Write a method name as a JSON string; most names need no escaping, so skip the encoder."""
    if method.isascii() and method.isprintable() and '"' not in method and "\\" not in method:
        return f'"{method}"'
    return encode_json(method)


def _encode_timeout(timeout: float) -> str:
    """Write a timeout as a JSON number; raise ``ValueError`` when it is not a finite one."""
    try:
        seconds = float(timeout)
    except OverflowError:
        seconds = math.inf
    if not math.isfinite(seconds):
        raise ValueError(
            f"the timeout must be a finite number of seconds, not {describe_value(timeout)}"
        )
    return repr(seconds)  # repr of a finite float is a JSON number (2.5, 1e-05, 1e+16)


_OBJECT_OPENS = re.compile(r"\s*\{\s*")


def _params_text(params: Params, timeout: float | None) -> str:
    """Return ``,"params":...`` (empty without params) with ``_meta`` spliced in."""
    if timeout is None:
        return "" if params is None else ',"params":' + encode_json(params)
    meta = ',"params":{"_meta":{"timeout":' + _encode_timeout(timeout) + "}"
    if params is None:
        return meta + "}"
    if isinstance(params, RawJSON):
        text = encode_json(params)
        opening = _OBJECT_OPENS.match(text)
        if opening is None:
            raise ValueError("a timeout needs params that are a JSON object")
        start = opening.end()
        text = text.rstrip()
        if not text.endswith("}") or len(text) <= start:
            raise ValueError("a timeout needs params that are a JSON object")
        if text.startswith("}", start):
            return meta + "}"
        return meta + "," + text[start:]
    if isinstance(params, list):
        raise ValueError("a timeout needs params by name, not an array")
    _encode_timeout(timeout)  # refuses a timeout that is not a finite number
    return ',"params":' + encode_json({**params, "_meta": {"timeout": timeout}})


@dataclass(slots=True)
class Request:
    """A call that expects a reply: ``method`` with ``params``, answered under ``id``.

    ``timeout`` is the caller's remaining deadline in seconds, carried as ``params._meta``.
    """

    id: Id
    method: str
    params: Params = None
    timeout: float | None = None

    def serialize(self) -> bytes:
        """Return this request as UTF-8 JSON.

        Raise ``ValueError`` for a timeout with params that are not an object, or that is not
        a finite number. The client's calls are written in one go, by :func:`write_call`.
        """
        params = self.params
        timeout = self.timeout
        id = self.id
        if type(params) is RawJSON and type(params.text) is str and timeout is not None:
            written = write_call(id, self.method, params.text, timeout)  # checks the rest
            if written is not None:
                return written
        return (
            '{"jsonrpc":"2.0","id":'
            + _encode_id(id)
            + ',"method":'
            + _encode_method(self.method)
            + _params_text(params, timeout)
            + "}"
        ).encode()


def write_call(id: Id, method: str, params: str, timeout: float) -> bytes | None:
    """Write a request as the client sends its calls, in one go; None if it is not one.

    ``id`` is an int, ``params`` an object written compactly, as pydantic writes one (``{}``,
    or ``{"`` and the members), and ``timeout`` a finite float; other input is None, for
    :meth:`Request.serialize` to write the long way. The same text as
    ``Request(id, method, RawJSON(params), timeout).serialize()``, which calls this.
    """
    # a finite float less itself is 0.0 (infinity and NaN give NaN)
    if type(id) is not int or type(timeout) is not float or timeout - timeout != 0.0:
        return None
    if params[-1:] != "}":
        return None
    method = _encode_method(method)
    if params[:2] == '{"':
        return (
            f'{{"jsonrpc":"2.0","id":{id},"method":{method},'
            f'"params":{{"_meta":{{"timeout":{timeout!r}}},{params[1:]}}}'
        ).encode()
    if params == "{}":
        return (
            f'{{"jsonrpc":"2.0","id":{id},"method":{method},'
            f'"params":{{"_meta":{{"timeout":{timeout!r}}}}}}}'
        ).encode()
    return None


class CallWriter:
    """Writes the calls of one method as the client sends them, from a template made once.

    For params already written as UTF-8 bytes (an object written compactly, as pydantic writes
    one) and a finite float timeout: the request :func:`write_call` writes with the timeout
    rounded to the microsecond, ``write_call(id, method, params.decode(), round(timeout, 6))``,
    the timeout written with six decimals (``29.999987``, ``30.000000``: the same number,
    without finding its shortest form). Other params are None, for the caller to write the
    long way.
    """

    __slots__ = ("_empty", "_members")

    def __init__(self, method: str) -> None:
        name = _encode_method(method).encode().replace(b"%", b"%%")
        head = b'{"jsonrpc":"2.0","id":%d,"method":' + name + b',"params":{"_meta":{"timeout":%.6f}'
        self._members = head + b",%b}"  # the members of params, their "}", then the message's
        self._empty = head + b"}}"

    def __call__(self, id: int, params: bytes, timeout: float) -> bytes | None:
        # a finite float less itself is 0.0 (infinity and NaN give NaN)
        if type(timeout) is not float or timeout - timeout != 0.0 or params[-1:] != b"}":
            return None
        if params[:2] == b'{"':
            return self._members % (id, timeout, params[1:])
        if params == b"{}":
            return self._empty % (id, timeout)
        return None


@dataclass(slots=True)
class Notification:
    """A message that expects no reply: ``method`` with ``params``.

    ``error`` is set when a notification parsed from a peer cannot run (its ``params._meta`` is
    bad). A notification is never answered, so the error is for the log, not for the wire.
    """

    method: str
    params: Params = None
    timeout: float | None = None
    error: RPCError | None = None

    def serialize(self) -> bytes:
        """Return this notification as UTF-8 JSON."""
        return (
            '{"jsonrpc":"2.0","method":'
            + _encode_method(self.method)
            + _params_text(self.params, self.timeout)
            + "}"
        ).encode()


@dataclass(slots=True)
class Response:
    """A successful reply: the ``result`` of the request with this ``id``."""

    id: Id
    result: Any

    def serialize(self) -> bytes:
        """Return this response as UTF-8 JSON; a :class:`RawJSON` result is spliced in as is."""
        result = self.result
        if type(result) is RawJSON:
            text = result.text
            written = text if isinstance(text, bytes) else text.encode()
        else:
            written = encode_json(result).encode()
        return write_response(self.id, written)

    def decode(self, decoder: Decoder[T] | None = None) -> T | Any:
        """Return the result, through ``decoder`` when given (raising its ``ValueError``)."""
        return self.result if decoder is None else decoder.from_data(self.result)


def write_response(id: Id, result: bytes) -> bytes:
    """Write a response around its result, JSON already written as UTF-8 bytes, in one go.

    The same bytes as ``Response(id, RawJSON(result)).serialize()``, which calls this; the
    server writes the replies of its calls with it, without the two objects.
    """
    if type(id) is int:  # what clients send: formatted in one step
        return b'{"jsonrpc":"2.0","id":%d,"result":%b}' % (id, result)
    return b'{"jsonrpc":"2.0","id":%b,"result":%b}' % (_encode_id(id).encode(), result)


@dataclass(slots=True)
class ErrorResponse:
    """A failed reply: ``error`` for the request with this ``id`` (null if it was unreadable)."""

    id: Id
    error: RPCError

    def serialize(self) -> bytes:
        """Return this error response as UTF-8 JSON."""
        return (
            '{"jsonrpc":"2.0","id":'
            + _encode_id(self.id)
            + ',"error":'
            + encode_json(self.error.to_error_object())
            + "}"
        ).encode()

    def decode(self, decoder: Decoder[Any] | None = None) -> Any:
        """Raise the error this reply carries."""
        raise self.error


Reply: TypeAlias = Response | ErrorResponse
ReadRequest: TypeAlias = tuple[Id, str, Any, float | None]
"""A request read in one pass (:class:`srvwire.models.CallReader`): a :class:`Request`'s
``id``, ``method``, ``params`` and ``timeout``, without the object, which a call the server
admits at once never needs."""
Message: TypeAlias = Request | Notification | Response | ErrorResponse


@dataclass(slots=True)
class Incoming:
    """What one WebSocket message from a client holds, as the server sees it.

    ``items`` keeps the order of the batch. An :class:`ErrorResponse` item is an invalid item,
    already answered; the server sends it back with the replies to the others.
    """

    items: tuple[Request | Notification | ErrorResponse, ...]
    is_batch: bool = False


def canonical_name(method: str) -> str:
    """Return a service name as srvwire keeps it: with its leading ``/`` (optional on the wire)."""
    return method if method.startswith("/") else "/" + method


def serialize_batch(messages: Iterable[Message | bytes]) -> bytes:
    """Return a batch (a JSON array) of messages; a ``bytes`` item is one already serialized."""
    return b"[" + b",".join(m if isinstance(m, bytes) else m.serialize() for m in messages) + b"]"


def cancel_notification(id: Id) -> Notification:
    """Return the ``$/cancel`` notification that cancels the call with this ``id``."""
    return Notification(CANCEL_METHOD, {"id": id})


def services_notification(
    services: Iterable[tuple[str, str]], fingerprints: Mapping[str, str] | None = None
) -> Notification:
    """Return the ``$/services`` notification for ``(name, type)`` pairs, sorted by name;
    an entry whose name has one of ``fingerprints`` carries it as ``"fingerprint"``."""
    known = fingerprints or {}
    listed: list[dict[str, str]] = []
    for name, type_name in sorted(services):
        entry = {"name": name, "type": type_name}
        if name in known:
            entry["fingerprint"] = known[name]
        listed.append(entry)
    return Notification(SERVICES_METHOD, {"services": listed})


# --- server side: parsing what clients send ---------------------------------------------------


_JSON_TYPES = {
    dict: "an object",
    list: "an array",
    str: "a string",
    int: "a number",
    float: "a number",
    bool: "a boolean",
    type(None): "null",
}


def _kind(value: Any) -> str:
    return _JSON_TYPES.get(type(value), type(value).__name__)


def valid_id(value: Any) -> bool:
    """Whether ``value`` can be a JSON-RPC id: a string, a finite number (not a boolean), null."""
    kind = type(value)
    return value is None or kind is str or kind is int or (kind is float and math.isfinite(value))


def _id_kind(value: Any) -> str:
    """Name what an invalid id is, for the error message."""
    if type(value) is float:  # not finite, else it would be valid
        return "NaN" if math.isnan(value) else ("-Infinity" if value < 0 else "Infinity")
    return _kind(value)


def _invalid(id: Id, message: str) -> ErrorResponse:
    return ErrorResponse(id, InvalidRequest(f"Invalid Request: {message}"))


def _bad_meta(path: str, message: str, type_: str) -> InvalidParams:
    error = {"path": path, "message": message, "type": type_}
    return InvalidParams(f"invalid {path}: {message}", {"errors": [error]})


def read_cancel(params: Any) -> Id | InvalidParams:
    """Read the params of a ``$/cancel`` request: the id of the call to cancel (a string or a
    finite number), or the error they are, with the field's path. Left out, they are ``{}``."""
    if params is None:
        params = {}
    if type(params) is not dict:
        return _bad_cancel("", f"must be an object, not {_kind(params)}", "dict_type")
    if "id" not in params:
        return _bad_cancel("id", "missing", "missing")
    id = params["id"]
    if id is None or not valid_id(id):
        return _bad_cancel("id", f"must be a string or a number, not {_id_kind(id)}", "id_type")
    return id  # type: ignore[no-any-return]


def _bad_cancel(path: str, message: str, type_: str) -> InvalidParams:
    error = {"path": path, "message": message, "type": type_}
    return InvalidParams(
        'invalid params: $/cancel needs the id of the call to cancel: {"id": 7}',
        {"errors": [error]},
    )


def timeout_seconds(value: Any) -> float | None:
    """Return ``value`` as a deadline: a finite number of seconds >= 0; None if it is not one.

    A bool is not a number here, and neither is an integer too large for a float (JSON is
    decoded exactly), just as ``1e400`` is not. The server reads ``_meta.timeout`` with it,
    the client its ``timeout`` arguments.
    """
    if type(value) is float:  # what clients send: no conversion to check
        return value if 0.0 <= value < math.inf else None
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        seconds = float(value)
    except OverflowError:
        return None
    return seconds if math.isfinite(seconds) and seconds >= 0 else None


def describe_value(value: Any) -> str:
    """Write a value for an error message: as JSON, or in words where JSON has none."""
    if isinstance(value, float) and not math.isfinite(value):
        return _id_kind(float(value))  # NaN, Infinity or -Infinity
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 1024:
        return "an integer too large for a float"
    return encode_json(value)


def read_meta(meta: Any) -> tuple[float | None, InvalidParams | None]:
    """Read a request's ``params._meta``: its deadline (None for none), or the error it is."""
    if type(meta) is not dict:
        return None, _bad_meta("_meta", f"must be an object, not {_kind(meta)}", "dict_type")
    raw = meta.get("timeout")
    if raw is None:
        return None, None
    timeout = timeout_seconds(raw)
    if timeout is None:
        return None, _bad_meta(
            "_meta.timeout",
            f"must be a number of seconds >= 0, not {describe_value(raw)}",
            "timeout",
        )
    return timeout, None


def _parse_item(item: Any) -> Request | Notification | ErrorResponse:
    """Turn one decoded JSON value into a request, a notification, or the error answering it.

    ``item`` must be freshly decoded and nobody else's: ``_meta`` is popped out of its params.
    """
    if type(item) is not dict:
        return _invalid(None, f"expected an object, got {_kind(item)}")
    has_id = "id" in item
    id = item.get("id")
    if not valid_id(id):
        return _invalid(None, f"'id' must be a string, a number or null, not {_id_kind(id)}")
    if item.get("jsonrpc") != "2.0":
        return _invalid(id, "'jsonrpc' must be exactly \"2.0\"")
    method = item.get("method")
    if type(method) is not str:
        what = "missing" if method is None and "method" not in item else _kind(method)
        return _invalid(id, f"'method' must be a string, not {what}")
    params: Any = item.get("params")
    timeout: float | None = None
    bad_meta: InvalidParams | None = None
    if type(params) is dict:
        if "_meta" in params:
            # a fresh dict from decode_json: no copy needed
            timeout, bad_meta = read_meta(params.pop("_meta"))
    elif type(params) is not list and "params" in item:
        return _invalid(id, f"'params' must be an object or an array, not {_kind(params)}")
    if not has_id:  # a notification is never answered, not even with an error
        return Notification(method, params, timeout, bad_meta)
    if bad_meta is not None:
        return ErrorResponse(id, bad_meta)
    return Request(id, method, params, timeout)


def parse_incoming(data: str | bytes) -> Incoming:
    """Parse one WebSocket message from a client; never raises (see the invariants)."""
    try:
        decoded = decode_json(data)
    except ParseError as exc:
        return Incoming((ErrorResponse(None, exc),))
    if type(decoded) is list:
        if not decoded:
            return Incoming((_invalid(None, "empty batch"),))
        return Incoming(tuple(_parse_item(item) for item in decoded), is_batch=True)
    return Incoming((_parse_item(decoded),))


# --- client side: parsing what servers send ---------------------------------------------------


def _parse_reply(item: Any) -> Response | ErrorResponse | Notification:
    if type(item) is not dict:
        raise InvalidRequest(f"Invalid reply: expected an object, got {_kind(item)}")
    if item.get("jsonrpc") != "2.0":
        raise InvalidRequest("Invalid reply: 'jsonrpc' must be exactly \"2.0\"")
    if "method" in item:
        method = item["method"]
        params = item.get("params")
        if type(method) is not str or not (params is None or type(params) in (dict, list)):
            raise InvalidRequest("Invalid reply: malformed notification")
        return Notification(method, params)
    if "id" not in item or not valid_id(item["id"]):
        raise InvalidRequest("Invalid reply: 'id' missing or not a string, a number or null")
    id = item["id"]
    if "result" in item:
        if "error" in item:
            raise InvalidRequest("Invalid reply: both 'result' and 'error'")
        return Response(id, item["result"])
    error = item.get("error")
    if type(error) is not dict:
        raise InvalidRequest("Invalid reply: neither 'result' nor an 'error' object")
    code = error.get("code")
    message = error.get("message")
    if type(code) is not int or type(message) is not str:
        raise InvalidRequest("Invalid reply: 'error' needs an integer code and a string message")
    return ErrorResponse(id, error_from_code(code, message, error.get("data")))


def parse_replies(data: str | bytes) -> list[Response | ErrorResponse | Notification]:
    """Parse one WebSocket message from a server: a reply, a notification, or a batch of them.

    Raise :class:`~srvwire.errors.ParseError` when it is not JSON and
    :class:`~srvwire.errors.InvalidRequest` when it is not JSON-RPC 2.0.
    """
    decoded = decode_json(data)
    if type(decoded) is list:
        if not decoded:
            raise InvalidRequest("Invalid reply: empty batch")
        return [_parse_reply(item) for item in decoded]
    return [_parse_reply(decoded)]


# The opening of the response a srvwire server writes for one of the client's calls (see
# Response.serialize), up to its result: the id is one the client made, a positive integer.
_RESULT_OPENING = re.compile(r'\{"jsonrpc":"2\.0","id":([1-9][0-9]{0,17}),"result":')

REPLY_OPENING = '{"jsonrpc":"2.0","id":'
"""How every message :func:`peek_reply` recognises begins (a cheap test before it)."""


@dataclass(slots=True)
class RawReply:
    """A response recognised by its opening alone and not parsed yet: see :func:`peek_reply`.

    ``message`` opens with ``{"jsonrpc":"2.0","id":<id>,"result":`` and ends with ``}``;
    ``start`` is where the result begins. Nothing else was checked: a srvwire server puts one
    JSON value between the two, but another server may have written more members after it,
    which only the full parse in :meth:`decode` can tell.
    """

    id: int
    message: str
    start: int

    @property
    def result(self) -> str:
        """The text between the opening and the final ``}``: the result, if nothing follows it."""
        return self.message[self.start : -1]

    def parse(self) -> Response:
        """Parse the whole message, as :func:`parse_replies` would; return the response.

        Raise :class:`ProtocolViolation` when it is not JSON-RPC, or when, for all that it opens
        as the response to ``id``, it is another message: a later ``method`` member makes it a
        notification, a later ``id`` member another reply.
        """
        try:
            (message,) = parse_replies(self.message)  # it opens with "{": not a batch
        except (ParseError, InvalidRequest) as exc:
            raise ProtocolViolation(exc) from None
        if isinstance(message, Notification):
            raise ProtocolViolation(InvalidRequest("Invalid reply: both 'result' and 'method'"))
        # A message with a 'result' is never an error reply; another id means 'id' came twice.
        if (
            not isinstance(message, Response)
            or type(message.id) is not int
            or message.id != self.id
        ):
            raise ProtocolViolation(
                InvalidRequest(f"Invalid reply: 'id' given twice ({self.id} and {message.id!r})")
            )
        return message

    def decode(self, decoder: Decoder[T] | None = None) -> T | Any:
        """Return the result: validated in one pass when it can be, else parsed in full.

        With a ``decoder``, the result text is validated straight into its type; when that is
        refused, only the full parse can tell a result that does not fit (``decoder``'s
        ``ValueError``, from the parsed data) from a message that is not JSON-RPC
        (:class:`ProtocolViolation`).
        """
        if decoder is not None:
            try:
                if len(self.message) < WHOLE_REPLY_SIZE:
                    return decoder.from_json(self.message[self.start : -1])  # self.result
                return decoder.from_reply(self.message, self.id)  # not sliced out: no copy
            except ValueError:
                pass
        return self.parse().decode(decoder)


WHOLE_REPLY_SIZE = 2**16
"""A reply this long or longer (in characters) is validated whole, its envelope with its result,
rather than its result sliced out first: for a large reply the slice is one more copy of it
(docs/performance.md, "Large replies written whole"); for a small one it costs less than the
envelope's validation."""


def peek_reply(message: str) -> RawReply | None:
    """Recognise a response by its opening, without parsing it; None for any other message.

    Only the opening ``{"jsonrpc":"2.0","id":<positive integer>,"result":`` (written exactly
    so, with no blanks) and a final ``}`` are checked, so the cost does not grow with the
    result: the client routes the reply by its id, and its caller decodes the result in one
    pass.
    """
    opening = _RESULT_OPENING.match(message)
    if opening is None or not message.endswith("}"):
        return None
    return RawReply(int(opening[1]), message, opening.end())
