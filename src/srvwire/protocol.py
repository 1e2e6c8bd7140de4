"""JSON-RPC 2.0 without I/O: text in, messages out; messages in, text out.

Nothing here awaits, touches a socket or knows about WebSockets. The server and the client move
text between the network and the functions below, which makes every rule of the protocol testable
without an event loop.

Invariants:

* **Parsing never raises on input from a peer** (server side). :func:`parse_incoming` turns any
  text or bytes into an :class:`Incoming`: every item is a :class:`Request`, a
  :class:`Notification` or an :class:`ErrorResponse` ready to be sent back. Input that is not JSON,
  not UTF-8, or nested deeper than :data:`MAX_DEPTH` is one ``PARSE_ERROR``; an empty batch is one
  ``INVALID_REQUEST`` (not a batch, as the specification says); an invalid item of a batch is an
  ``INVALID_REQUEST`` in its place.
* **An id is echoed exactly as it came** (string, number or null). An invalid item whose id can be
  read gets its id back; otherwise ``null``. A number id must be finite: ``NaN``, ``Infinity`` and
  numbers too large for a double (``1e400``) cannot be echoed, so they make the item an
  ``INVALID_REQUEST`` with a ``null`` id. A fractional id is accepted (the specification only
  advises against it). A message without an ``id`` member is a notification and is never
  answered, unless it is so malformed that it is not a notification at all.
* **``params._meta`` belongs to the protocol, not to the service.** It is taken out of ``params``
  while parsing: ``{"timeout": seconds}`` becomes :attr:`Request.timeout`; other members of
  ``_meta`` are ignored so that later versions can add some. A bad ``_meta`` is an
  ``INVALID_PARAMS`` error with the path ``_meta`` or ``_meta.timeout``: a request gets it as its
  reply; a notification carries it in :attr:`Notification.error`, so the server drops it (and logs
  why) without running it or answering.
* **Serializing is total.** Every message serializes to compact JSON text; data that is not JSON
  (a set, an object) is written with ``str()`` and a non-finite float as ``null`` rather than
  failing, because an error reply must always be sendable.
* **Pre-encoded JSON is embedded, never decoded again.** :class:`RawJSON` wraps text that already
  is JSON (a pydantic ``model_dump_json``); as a result or as params it is spliced into the
  envelope as it is. The hot paths do the same without the objects: :func:`encode_result`
  (the server's replies, as UTF-8 bytes, so a large result is never decoded) and
  :func:`encode_call` (the client's requests: compact params that are a JSON object and a
  finite timeout, which it checks, raising ``ValueError`` otherwise).

:func:`parse_replies` is the client's side: it parses what a server sends and raises
:class:`~srvwire.errors.ParseError` or :class:`~srvwire.errors.InvalidRequest` when that is not
JSON-RPC, since a server that breaks the protocol is a bug to report, not a peer to answer.
:func:`peek_reply` recognises a response as :func:`encode_result` writes it by its opening alone,
so that the client can route it by id and decode its result in one pass; :func:`parse_raw_reply`
checks such a reply in full when the one pass is not enough.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, TypeAlias

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
    "SERVICES_METHOD",
    "ErrorResponse",
    "Id",
    "Incoming",
    "Notification",
    "Params",
    "RawJSON",
    "RawReply",
    "Reply",
    "Request",
    "Response",
    "cancel_notification",
    "canonical_name",
    "decode_json",
    "describe_value",
    "encode_call",
    "encode_json",
    "encode_result",
    "parse_incoming",
    "parse_raw_reply",
    "parse_replies",
    "peek_reply",
    "serialize",
    "serialize_batch",
    "services_notification",
    "timeout_seconds",
]

CANCEL_METHOD = "$/cancel"
"""Notification a client sends to cancel one of its calls: ``{"id": <request id>}``."""

SERVICES_METHOD = "$/services"
"""Notification the server sends with the full, sorted list of services it offers."""

DISCOVER_METHOD = "rpc.discover"
"""Method that returns the OpenRPC document describing every service."""

MAX_DEPTH = 200
"""How many arrays and objects may enclose a value in one message; deeper input is a parse error.

This is pydantic_core's own recursion limit, which :func:`decode_json` relies on rather than
walking the decoded value again; the tests pin both sides of it. An empty array or object is a
value itself, so it may sit one level deeper than this.
"""

Id: TypeAlias = str | int | float | None
"""A JSON-RPC id: a string, a number, or null."""


@dataclass(frozen=True, slots=True)
class RawJSON:
    """Text that already is one JSON value, embedded into a message without re-encoding."""

    text: str


Params: TypeAlias = dict[str, Any] | list[Any] | RawJSON | None
"""What ``params`` may hold: an object, an array, pre-encoded JSON, or nothing."""


def encode_json(value: Any) -> str:
    """Return ``value`` as compact JSON text; never fails (see the module's invariants)."""
    if isinstance(value, RawJSON):
        return value.text
    return to_json(value, fallback=str, inf_nan_mode="null").decode()


def decode_json(data: str | bytes) -> Any:
    """Parse one JSON value strictly, or raise :class:`~srvwire.errors.ParseError`.

    Bytes must be UTF-8. Trailing text and nesting deeper than :data:`MAX_DEPTH` are refused.
    Integers of any size are read exactly. The tokens ``NaN``, ``Infinity`` and ``-Infinity``
    are accepted, as Python's ``json`` accepts them, because srvwire's models write non-finite
    floats that way.
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


_OBJECT_OPENS = re.compile(r"\s*\{\s*")


def _params_parts(params: Params, timeout: float | None) -> tuple[str, ...]:
    """Return the pieces of ``,"params":...`` (nothing without params), ``_meta`` spliced in.

    The caller joins them with the rest of the message in one go, so the text of a
    :class:`RawJSON` body is copied once, not once per concatenation.
    """
    if timeout is None:
        return () if params is None else (',"params":', encode_json(params))
    meta = ',"params":{"_meta":{"timeout":' + encode_json(timeout) + "}"
    if params is None:
        return (meta, "}")
    if isinstance(params, RawJSON):
        text = params.text
        opening = _OBJECT_OPENS.match(text)
        if opening is None:
            raise ValueError("a timeout needs params that are a JSON object")
        start = opening.end()
        if text.startswith("}", start):
            return (meta, "}")
        end = len(text)
        while end > start and text[end - 1].isspace():
            end -= 1
        return (meta, ",", text[start:end])
    if isinstance(params, list):
        raise ValueError("a timeout needs params by name, not an array")
    return (',"params":', encode_json({**params, "_meta": {"timeout": timeout}}))


@dataclass(frozen=True, slots=True)
class Request:
    """A call that expects a reply: ``method`` with ``params``, answered under ``id``.

    ``timeout`` is the caller's remaining deadline in seconds, carried as ``params._meta``.
    """

    id: Id
    method: str
    params: Params = None
    timeout: float | None = None

    def serialize(self) -> str:
        """Return this request as JSON text."""
        return "".join(
            (
                '{"jsonrpc":"2.0","id":',
                _encode_id(self.id),
                ',"method":',
                encode_json(self.method),
                *_params_parts(self.params, self.timeout),
                "}",
            )
        )


@dataclass(frozen=True, slots=True)
class Notification:
    """A message that expects no reply: ``method`` with ``params``.

    ``error`` is set when a notification parsed from a peer cannot run (its ``params._meta`` is
    bad). A notification is never answered, so the error is for the log, not for the wire.
    """

    method: str
    params: Params = None
    timeout: float | None = None
    error: RPCError | None = None

    def serialize(self) -> str:
        """Return this notification as JSON text."""
        return "".join(
            (
                '{"jsonrpc":"2.0","method":',
                encode_json(self.method),
                *_params_parts(self.params, self.timeout),
                "}",
            )
        )


@dataclass(frozen=True, slots=True)
class Response:
    """A successful reply: the ``result`` of the request with this ``id``."""

    id: Id
    result: Any

    def serialize(self) -> str:
        """Return this response as JSON text; a :class:`RawJSON` result is embedded as is."""
        return (
            '{"jsonrpc":"2.0","id":' + _encode_id(self.id) + ',"result":'
            f"{encode_json(self.result)}}}"
        )


@dataclass(frozen=True, slots=True)
class ErrorResponse:
    """A failed reply: ``error`` for the request with this ``id`` (null if it was unreadable)."""

    id: Id
    error: RPCError

    def serialize(self) -> str:
        """Return this error response as JSON text."""
        return (
            '{"jsonrpc":"2.0","id":' + _encode_id(self.id) + ',"error":'
            f"{encode_json(self.error.to_error_object())}}}"
        )


Reply: TypeAlias = Response | ErrorResponse
Message: TypeAlias = Request | Notification | Response | ErrorResponse


@dataclass(frozen=True, slots=True)
class Incoming:
    """What one WebSocket message from a client holds, as the server sees it.

    ``items`` keeps the order of the batch. An :class:`ErrorResponse` item is an invalid item,
    already answered; the server sends it back with the replies to the others.
    """

    items: tuple[Request | Notification | ErrorResponse, ...]
    is_batch: bool = False


def encode_result(id: Id, result_json: bytes) -> bytes:
    """Return a response whose result is ``result_json``, UTF-8 JSON bytes, spliced in as it is.

    The same as ``Response(id, RawJSON(result)).serialize()`` encoded as UTF-8, without the
    objects: the server's hot path. A large result is copied once, into the reply, and never
    decoded.
    """
    return b"".join(
        (b'{"jsonrpc":"2.0","id":', _encode_id(id).encode(), b',"result":', result_json, b"}")
    )


def encode_call(id: int, method_json: str, params_json: str, timeout: float) -> str:
    """Return a request with ``_meta.timeout`` spliced into its params: the client's hot path.

    The same text as ``Request(id, method, RawJSON(params_json), timeout).serialize()``, built
    in one go: ``method_json`` is the method already written as JSON (:func:`encode_json`),
    ``params_json`` a compact JSON object as pydantic writes it (``{`` first, no blanks), and
    ``timeout`` a finite float >= 0, written by ``repr``, which is a JSON number for every
    finite float (``2.5``, ``1e-05``, ``1e+16``). Raise ValueError for params that are not
    a JSON object or a timeout that is not finite, rather than write invalid JSON.
    """
    if not (params_json[:1] == "{" and params_json[-1:] == "}"):
        raise ValueError(f"params must be a JSON object, not {params_json[:20]!r}")
    if not math.isfinite(timeout):
        raise ValueError(f"the timeout must be a finite number of seconds, not {timeout!r}")
    # One f-string: a little cheaper than joining the pieces.
    if params_json == "{}":
        return (
            f'{{"jsonrpc":"2.0","id":{id},"method":{method_json},'
            f'"params":{{"_meta":{{"timeout":{timeout!r}}}}}}}'
        )
    return (
        f'{{"jsonrpc":"2.0","id":{id},"method":{method_json},'
        f'"params":{{"_meta":{{"timeout":{timeout!r}}},{params_json[1:]}}}'
    )


def canonical_name(method: str) -> str:
    """Return a service name as srvwire keeps it: with its leading ``/`` (optional on the wire)."""
    return method if method.startswith("/") else "/" + method


def serialize(message: Message) -> str:
    """Return one message as JSON text."""
    return message.serialize()


def serialize_batch(messages: Iterable[Message | str]) -> str:
    """Return a batch (a JSON array) of messages; a ``str`` item is already-serialized text."""
    return "[" + ",".join(m if isinstance(m, str) else m.serialize() for m in messages) + "]"


def cancel_notification(id: Id) -> Notification:
    """Return the ``$/cancel`` notification that cancels the call with this ``id``."""
    return Notification(CANCEL_METHOD, {"id": id})


def services_notification(services: Iterable[tuple[str, str]]) -> Notification:
    """Return the ``$/services`` notification for ``(name, type)`` pairs, sorted by name."""
    listed = [{"name": name, "type": type_name} for name, type_name in sorted(services)]
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


def _valid_id(value: Any) -> bool:
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


def timeout_seconds(value: Any) -> float | None:
    """Return ``value`` as a deadline: a finite number of seconds >= 0; None if it is not one.

    A bool is not a number here, and neither is an integer too large for a float (JSON is
    decoded exactly), just as ``1e400`` is not. The server reads ``_meta.timeout`` with it,
    the client its ``timeout`` arguments.
    """
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


def _parse_item(item: Any) -> Request | Notification | ErrorResponse:
    """Turn one decoded JSON value into a request, a notification, or the error answering it.

    ``item`` must be freshly decoded and nobody else's: ``_meta`` is popped out of its params.
    """
    if type(item) is not dict:
        return _invalid(None, f"expected an object, got {_kind(item)}")
    has_id = "id" in item
    id = item.get("id")
    if not _valid_id(id):
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
            meta = params.pop("_meta")  # a fresh dict from decode_json: no copy needed
            if type(meta) is not dict:
                bad_meta = _bad_meta("_meta", f"must be an object, not {_kind(meta)}", "dict_type")
            elif (raw := meta.get("timeout")) is not None:
                timeout = timeout_seconds(raw)
                if timeout is None:
                    bad_meta = _bad_meta(
                        "_meta.timeout",
                        f"must be a number of seconds >= 0, not {describe_value(raw)}",
                        "timeout",
                    )
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
    if "id" not in item or not _valid_id(item["id"]):
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
# encode_result), up to its result: the id is one the client made, a positive integer.
_RESULT_OPENING = re.compile(r'\{"jsonrpc":"2\.0","id":([1-9][0-9]{0,17}),"result":')


@dataclass(slots=True)  # not frozen: one is made per reply, and frozen ones cost 3x as much
class RawReply:
    """A response recognised by its opening alone and not parsed: see :func:`peek_reply`.

    ``message`` opens with ``{"jsonrpc":"2.0","id":<id>,"result":`` and ends with ``}``;
    ``start`` is where the result begins. Nothing else was checked: a srvwire server puts one
    JSON value between the two, but another server may have written more members after it,
    which only :func:`parse_raw_reply` can tell.
    """

    id: int
    message: str
    start: int

    @property
    def result(self) -> str:
        """The text between the opening and the final ``}``: the result, if nothing follows it."""
        return self.message[self.start : -1]


def peek_reply(message: str) -> RawReply | None:
    """Recognise a response by its opening, without parsing it; None for any other message.

    Only the opening ``{"jsonrpc":"2.0","id":<positive integer>,"result":`` (written exactly
    so, with no blanks) and a final ``}`` are checked, so the cost does not grow with the
    result: the reader routes the reply by its id, and its caller decodes the result in one
    pass. Whether the message really is that response, :func:`parse_raw_reply` finds out.
    """
    opening = _RESULT_OPENING.match(message)
    if opening is None or not message.endswith("}"):
        return None
    return RawReply(int(opening[1]), message, opening.end())


def parse_raw_reply(reply: RawReply) -> Response:
    """Parse the whole message of ``reply``, as :func:`parse_replies` does, and return it.

    Raise what :func:`parse_replies` raises, and :class:`~srvwire.errors.InvalidRequest` when
    the message, for all that it opens as the response to ``reply.id``, is not that response:
    a later ``method`` member makes it a notification, a later ``id`` member another reply.
    """
    (message,) = parse_replies(reply.message)  # it opens with "{": one message, not a batch
    if isinstance(message, Notification):
        raise InvalidRequest("Invalid reply: both 'result' and 'method'")
    # A message with a 'result' is never an error reply; another id means 'id' came twice.
    if not isinstance(message, Response) or type(message.id) is not int or message.id != reply.id:
        raise InvalidRequest(f"Invalid reply: 'id' given twice ({reply.id} and {message.id!r})")
    return message
