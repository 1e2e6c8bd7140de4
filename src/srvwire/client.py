"""The asyncio client: call services over one WebSocket, with deadlines and typed errors.

Theory of operation
-------------------

A :class:`Client` owns at most one WebSocket connection at a time. Opening it means: the TCP
connection, the WebSocket handshake, and the server's first message, the ``$/services``
notification that lists every service and its type, all within ``open_timeout``. From then on
one *reader task* is the only code that receives from the socket.

A call encodes its request once (``model_dump_json``, with ``_meta`` spliced in by
:func:`srvwire.protocol.encode_call`), registers a future under a fresh integer id in
``_pending``, sends the text, and awaits the future under its deadline.

The reader parses a message only when it must. A text message that opens exactly as a srvwire
server writes a response, ``{"jsonrpc":"2.0","id":<id>,"result":`` (see
:func:`srvwire.protocol.peek_reply`), ends with ``}`` and names a call still waiting is handed to
that call unparsed, as a :class:`~srvwire.protocol.RawReply`: routing it costs the same whatever
the size of the result. Every other message (a notification, an error reply, a reply nobody
waits for, a batch, a binary frame) the reader parses with
:func:`srvwire.protocol.parse_replies`, then resolves the future of the call it answers or
updates the advertised services. Messages arrive as text: websockets decodes each text frame,
and closes the connection with code 1007 when one is not UTF-8.

The caller decodes its reply in its own task, so a large or failing decoding never holds up the
other calls on the connection. A typed call validates the text between the opening and the final
``}`` straight into its ``Response``, in one pass (``model_validate_json``). Anything else is
parsed in full with :func:`srvwire.protocol.parse_raw_reply` and then handled as if the reader had
parsed it: the reply of an untyped call, and any result the one pass refuses, whether it does not
match the type (the errors then come from validating the parsed data, as they always have), is
followed by more members (``"result":1,"x":2}``) or is not JSON-RPC at all. Validating JSON text
and validating the data it parses to agree on every type srvwire ships and on ROS 2's test
corpus, valid input or not, save for the wording of some errors and for one input: an integer
literal too large for a double (309 digits or more), in a float field, reads as infinity, as a
float literal such as ``1e400`` always has, where the data it parses to is refused.

Invariants:

* **Every call ends.** Every call has a finite deadline (the client's ``timeout`` unless the call
  gives its own), fixed as a point in loop time when the call starts. ``asyncio.wait_for`` on
  the pending reply future enforces it (on a future it adds a timer and a done callback, no
  task); the send before it is bounded by the same deadline. A send waits only on
  backpressure, so it runs inline up to its first suspension (:func:`srvwire.inline.first_step`)
  and, only if it does wait, finishes under a bare loop timer that cancels the caller's task
  (:func:`srvwire.inline.finish_within`, as the server bounds a handler; ``wait_for`` would
  wrap the coroutine in a task on Python 3.11). Waiting for the connection or the service
  (``wait_for_ready``) spends from the
  same deadline. The remaining time travels to the server in ``params._meta.timeout``. That is
  why calls take a ``timeout`` argument instead of leaving it to an outer ``asyncio.timeout``,
  which the server could not see.
* **A cancelled caller stays cancelled.** Python 3.11's ``wait_for`` returns the reply instead
  of raising ``CancelledError`` when the caller is cancelled just after the reply arrived
  (gh-86296, fixed in 3.12); the call checks ``Task.cancelling()`` and raises it anyway, so a
  ``TaskGroup`` or an outer ``asyncio.timeout`` still works.
* **A pending entry lives exactly as long as its caller waits.** The reader removes an entry when
  its reply arrives; the caller removes it in ``finally`` whatever happened (reply, error,
  deadline, cancellation, dropped connection). So the map is empty whenever no call is in flight.
* **A call the caller gave up on is cancelled on the server too, without waiting.** On a deadline
  or on ``task.cancel()`` the client schedules a ``$/cancel`` notification in a background task
  (best effort: it is dropped if the connection is gone) and raises at once.
* **A reply nobody waits for is harmless.** A reply whose id is not pending (its caller gave up)
  is parsed in full by the reader, like any message that is not routed unparsed, and dropped
  with a debug log.
* **A dropped connection fails every pending call at once** with
  :class:`~srvwire.errors.ConnectionLost`; none waits for its deadline. The pending map is
  swapped for an empty one in the same step, so a reconnected client never sees old entries.
* **Anything the server sends that is not JSON-RPC fails the connection.** It is logged, the
  connection is closed with code 1008, and every pending call fails with ``ConnectionLost``: a
  peer that breaks the protocol cannot be trusted to route the other replies either. The reader
  finds it when it parses a message; a caller finds it when it parses the reply the reader left
  unparsed, and then fails the connection the same way (:meth:`Client._violation`), its own call
  included. A reply that opens as the response to one call but turns out to be another message
  (a second ``id``, or a ``method``) is such a violation. Text that is not UTF-8 is refused by
  websockets, which closes with code 1007. Notifications other than ``$/services`` are ignored,
  for forward compatibility.
* **Waiting for a service is event-driven.** ``wait_for_service`` and ``wait_for_ready`` sleep
  on an :class:`asyncio.Event` that is pulsed when ``$/services`` arrives or the connection
  comes or goes; nothing polls.
* **Reconnection is opt-in.** With ``reconnect=False`` (the default) a dropped connection stays
  dropped: calls fail fast with ``ConnectionLost``. With ``reconnect=True`` a supervisor task
  re-dials with exponential backoff; calls made while it is down fail fast unless they pass
  ``wait_for_ready=True``, which waits (within the call's deadline) for the connection and the
  service. A call in flight when the connection drops is never retried: it may have run.
* **The reader belongs to its connection, not to the supervisor.** The supervisor watches the
  reader with ``asyncio.wait``, which never cancels it, and ``close()`` takes the connection
  before it stops the supervisor; so ``close()`` always closes the socket it owns, whatever the
  supervisor was doing (watching, backing off, or dialling: a dial interrupted half-way closes
  its own socket).
* **The advertised services are replaced, never mutated.** Each ``$/services`` and each end of a
  connection installs a new dict, so :attr:`Client.services` can hand out a read-only view of
  the current one as a snapshot.
* **Only this module knows websockets' exceptions.** Each is translated once, where it is
  raised, into a :mod:`srvwire.errors` class, with ``raise ... from exc``.

Request and response types: a call uses ``srv_type`` when given (a class or a ``pkg/srv/Name``
string), otherwise the type the server advertised for that service, loaded through
:func:`srvwire.loader.load_service` on ``search_path``. With a type, a dict or keyword fields are
validated locally (:class:`~srvwire.errors.InvalidParams` before anything is sent) and the
result is the typed ``Response``. Without one (the type cannot be loaded here), a dict or
keyword fields are sent as they are and the result is the plain ``dict`` the server returned.
Params go by name: a request model that does not serialize to a JSON object (a ``RootModel``
of a list, say) is refused with ``TypeError`` at once, before anything is sent.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import random
from collections.abc import Generator, Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType, TracebackType
from typing import Any, TypeAlias

from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticSerializationError
from websockets.asyncio.client import ClientConnection, connect as ws_connect
from websockets.exceptions import ConnectionClosed, InvalidURI, WebSocketException
from websockets.uri import parse_uri

from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    InterfaceError,
    InternalError,
    InvalidParams,
    InvalidRequest,
    ParseError,
    ServiceUnavailable,
)
from srvwire.inline import Pending, finish_within, first_step
from srvwire.loader import SearchPath, load_service
from srvwire.models import (
    Message,
    Service,
    summarize_errors,
    unencodable_strings,
    validation_errors,
)
from srvwire.protocol import (
    DISCOVER_METHOD,
    SERVICES_METHOD,
    ErrorResponse,
    Notification,
    RawReply,
    Request,
    Response,
    cancel_notification,
    canonical_name,
    describe_value,
    encode_call,
    encode_json,
    parse_raw_reply,
    parse_replies,
    peek_reply,
    timeout_seconds,
)

__all__ = [
    "DEFAULT_TIMEOUT",
    "DEFAULT_URL",
    "Client",
    "Connecting",
    "ServiceInfo",
    "ServiceProxy",
    "connect",
]

DEFAULT_URL = "ws://localhost:8765"
"""Where :func:`connect` goes when no URL is given."""

DEFAULT_TIMEOUT = 10.0
"""The deadline, in seconds, of a call that does not give its own."""

SrvType: TypeAlias = type[Service] | str
"""A service type: the class, or its name (``pkg/srv/Name``) to load from the search path."""

LoggerLike: TypeAlias = logging.Logger | logging.LoggerAdapter[logging.Logger]

# Close code sent when the server breaks the protocol (RFC 6455 "policy violation").
_CLOSE_PROTOCOL_VIOLATION = 1008
# Reconnection backoff: first retry at once, then from this delay, growing to the cap.
_BACKOFF_INITIAL = 0.05
_BACKOFF_FACTOR = 2.0
_BACKOFF_MAX = 5.0
# How many method names a client keeps already written as JSON.
_METHOD_CACHE_SIZE = 256


@dataclass(frozen=True, slots=True)
class ServiceInfo:
    """One service a server offers: its canonical name and its type (``pkg/srv/Name``)."""

    name: str
    type: str


def _check_timeout(timeout: float, what: str = "timeout") -> float:
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


def _backoff() -> Iterator[float]:
    """Yield reconnection delays: 0, then exponential growth to a cap, with jitter."""
    yield 0.0
    delay = _BACKOFF_INITIAL
    while True:
        yield delay * random.uniform(0.8, 1.2)
        delay = min(delay * _BACKOFF_FACTOR, _BACKOFF_MAX)


def _refused(method: str, errors: list[dict[str, str]]) -> InvalidParams:
    """The error for a request the client will not send: it does not validate or encode."""
    return InvalidParams(
        f"invalid params for {method}: {summarize_errors(errors)} "
        "(checked by the client; nothing was sent)",
        {"errors": errors},
        service=method,
    )


def _describe_close(
    connection: ClientConnection, exc: ConnectionClosed | None
) -> tuple[str, dict[str, Any]]:
    """Say how a connection ended: the close frame received, else the one sent, else none."""
    code: int | None
    if exc is not None:
        frame = exc.rcvd or exc.sent
        code, reason = (frame.code, frame.reason) if frame is not None else (None, "")
    else:
        code, reason = connection.close_code, connection.close_reason or ""
    if code is None or code == 1006:
        text = "the connection dropped (no close frame)"
    else:
        text = f"the connection closed with code {code}" + (f" ({reason})" if reason else "")
    return text, {"close_code": None if code is None else int(code), "close_reason": reason}


class Client:
    """A connection to one srvwire server, and the calls made over it.

    Create one with :func:`connect`, which opens it: ``async with connect(url) as client:`` or
    ``client = await connect(url)`` followed by ``await client.close()``. The arguments are
    described there. A client belongs to the event loop it was opened in.
    """

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        open_timeout: float = 10.0,
        max_message_size: int | None = 2**20,
        ping_interval: float | None = 20.0,
        ping_timeout: float | None = 20.0,
        compression: str | None = None,
        reconnect: bool = False,
        search_path: SearchPath | None = None,
        logger: LoggerLike | None = None,
    ) -> None:
        try:
            parse_uri(url)
        except InvalidURI as exc:
            raise ValueError(f"not a WebSocket URL: {url!r} ({exc})") from exc
        self.url = url
        self.timeout = _check_timeout(timeout)
        self.open_timeout = _check_timeout(open_timeout, "open_timeout")
        self.reconnect = reconnect
        self.search_path = search_path
        self.logger: LoggerLike = logger or logging.getLogger("srvwire.client")
        self._ws_options: dict[str, Any] = {
            "max_size": max_message_size,
            "ping_interval": ping_interval,
            "ping_timeout": ping_timeout,
            "compression": compression,
            "open_timeout": None,  # the whole opening is bounded by open_timeout in _dial
        }
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None  # the loop it was opened in
        self._ws: ClientConnection | None = None
        self._reader: asyncio.Task[None] | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._pending: dict[int, asyncio.Future[Response | ErrorResponse | RawReply]] = {}
        self._services: dict[str, str] = {}
        self._types: dict[str, type[Service] | None] = {}
        self._method_json: dict[str, str] = {}  # method names written as JSON, a small cache
        self._changed = asyncio.Event()
        self._background: set[asyncio.Task[None]] = set()
        self._opened = False
        self._closed = False

    # --- opening and closing --------------------------------------------------------------

    async def open(self) -> Client:
        """Open the connection; with ``reconnect=True`` a failed first dial is retried later.

        Raise :class:`~srvwire.errors.ServiceUnavailable` when the server cannot be reached
        (only with ``reconnect=False``). Opening twice is an error.
        """
        if self._opened:
            raise RuntimeError("this client was already opened")
        self._opened = True
        self._loop = asyncio.get_running_loop()
        if not self.reconnect:
            await self._dial()
            return self
        try:
            await self._dial()
        except ServiceUnavailable as exc:
            self.logger.info("%s; will keep trying in the background", exc.message)
        self._supervisor = asyncio.get_running_loop().create_task(self._supervise())
        return self

    async def close(self) -> None:
        """Close the connection; calls still pending fail with ``ConnectionLost``.

        Idempotent. After it, every call fails with ``ConnectionLost``.
        """
        if self._closed:
            return
        self._closed = True
        # Take the connection before stopping the supervisor: nothing that happens to the
        # supervisor may make this client forget a socket it still has to close.
        ws, reader = self._ws, self._reader
        if self._supervisor is not None:
            self._supervisor.cancel()
            await asyncio.gather(self._supervisor, return_exceptions=True)
        if ws is not None:
            await ws.close()
        if reader is not None:
            await asyncio.gather(reader, return_exceptions=True)
        if self._background:
            await asyncio.gather(*self._background, return_exceptions=True)
        self._pulse()

    async def __aenter__(self) -> Client:
        if not self._opened:
            await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        """Whether a connection is open right now (and its services are known)."""
        return self._ws is not None

    @property
    def in_flight(self) -> int:
        """How many calls are waiting for a reply."""
        return len(self._pending)

    @property
    def services(self) -> Mapping[str, str]:
        """The services the server advertised: canonical name -> type (``pkg/srv/Name``).

        A read-only snapshot of the latest ``$/services``, in the server's order; later
        advertisements do not change it, so read the property again for fresh news. Empty
        while not connected. No round trip: :meth:`list_services` asks the server instead.
        """
        return MappingProxyType(self._services)  # a snapshot: the dict is replaced, not mutated

    async def _dial(self) -> None:
        """Open a connection and read the server's ``$/services``; start its reader task."""
        try:
            async with asyncio.timeout(self.open_timeout):
                ws = await ws_connect(self.url, **self._ws_options)
                try:
                    first = await ws.recv()
                except BaseException:
                    self._close_in_background(ws)
                    raise
        except TimeoutError as exc:
            raise ServiceUnavailable(
                f"cannot connect to {self.url}: not ready within {self.open_timeout:g} s",
                {"url": self.url},
            ) from exc
        except (OSError, WebSocketException) as exc:
            raise ServiceUnavailable(
                f"cannot connect to {self.url}: {exc}", {"url": self.url}
            ) from exc
        try:
            messages = parse_replies(first)
            if not (
                len(messages) == 1
                and isinstance(messages[0], Notification)
                and messages[0].method == SERVICES_METHOD
            ):
                raise InvalidRequest(f"the server's first message was not {SERVICES_METHOD}")
            self._services = self._parse_services(messages[0])
        except (ParseError, InvalidRequest) as exc:
            await ws.close(_CLOSE_PROTOCOL_VIOLATION, "not a srvwire server")
            raise ServiceUnavailable(
                f"cannot connect to {self.url}: {exc.message}", {"url": self.url}
            ) from exc
        if self._closed:  # close() ran while this dial was under way
            await ws.close()
            raise ConnectionLost("the client is closed", {"url": self.url})
        self._ws = ws
        self._reader = asyncio.get_running_loop().create_task(self._read(ws))
        self.logger.debug("connected to %s, %d services", self.url, len(self._services))
        self._pulse()

    async def _supervise(self) -> None:
        """Keep a connection open: re-dial with backoff whenever there is none (reconnect=True)."""
        while True:
            reader = self._reader
            if self._ws is not None and reader is not None:
                # asyncio.wait, not gather: cancelling the supervisor must not cancel the
                # reader, which belongs to the connection and ends only when it does.
                await asyncio.wait({reader})
            for delay in _backoff():
                if delay:
                    await asyncio.sleep(delay)
                try:
                    await self._dial()
                except ServiceUnavailable as exc:
                    self.logger.debug("%s; retrying", exc.message)
                else:
                    break

    # --- the reader -------------------------------------------------------------------------

    async def _read(self, ws: ClientConnection) -> None:
        """Receive every message of one connection; on its end, fail what is pending."""
        cause: ConnectionClosed | None = None
        try:
            while True:
                data = await ws.recv()  # not ``async for``: one async generator less per reply
                try:
                    self._receive(data)
                except (ParseError, InvalidRequest) as exc:
                    self._violation(ws, exc)
                    break
        except ConnectionClosed as exc:
            cause = exc
        except Exception:  # a bug here must not leave calls waiting for their deadlines
            self.logger.exception("the reader of %s failed; closing the connection", self.url)
            self._fail(ws, "the client failed to process a message from the server")
        finally:
            self._lost(ws, None, cause)  # nothing to do when this side failed the connection

    def _receive(self, data: str | bytes) -> None:
        """Route one message: a reply a call waits for unparsed (when it can), else parsed."""
        if type(data) is str:
            raw = peek_reply(data)
            if raw is not None:
                future = self._pending.get(raw.id)
                if future is not None and not future.done():
                    del self._pending[raw.id]
                    future.set_result(raw)
                    return
        for message in parse_replies(data):
            if isinstance(message, Notification):
                if message.method == SERVICES_METHOD:
                    self._services = self._parse_services(message)
                    self._pulse()
                else:
                    self.logger.debug("ignoring the notification %s", message.method)
                continue
            request_id = message.id
            future = self._pending.pop(request_id, None) if type(request_id) is int else None
            if future is None:
                if request_id is None and isinstance(message, ErrorResponse):
                    # The server could not read one of our messages; it cannot say which.
                    self.logger.warning("the server could not read a message: %s", message.error)
                    continue
                self.logger.debug("dropping a reply for id %r: no call waits for it", request_id)
            elif not future.done():
                future.set_result(message)

    def _parse_services(self, message: Notification) -> dict[str, str]:
        params = message.params
        listed = params.get("services") if isinstance(params, dict) else None
        if not isinstance(listed, list):
            raise InvalidRequest(f"{SERVICES_METHOD} needs params {{'services': [...]}}")
        services: dict[str, str] = {}
        for entry in listed:
            name = entry.get("name") if isinstance(entry, dict) else None
            type_name = entry.get("type") if isinstance(entry, dict) else None
            if not (isinstance(name, str) and isinstance(type_name, str)):
                raise InvalidRequest(
                    f"{SERVICES_METHOD} entries need a string 'name' and 'type', got {entry!r}"
                )
            services[canonical_name(name)] = type_name
        return services

    def _lost(
        self, ws: ClientConnection, failure: str | None, cause: ConnectionClosed | None
    ) -> None:
        """Forget a connection that ended and fail every call still pending on it.

        ``failure`` says why this side is closing it, when it is; else the close frames (or
        their absence) say how it ended.
        """
        if self._ws is not ws:
            return
        self._ws = None
        self._reader = None
        self._services = {}
        pending, self._pending = self._pending, {}
        if failure is not None:
            text = failure
            data: dict[str, Any] = {"close_code": _CLOSE_PROTOCOL_VIOLATION}
        elif self._closed:
            text, data = "the client was closed", {}
        else:
            text, data = _describe_close(ws, cause)
        data["url"] = self.url
        if pending or not self._closed:
            self.logger.warning(
                "connection to %s lost: %s; failing %d pending calls", self.url, text, len(pending)
            )
        for future in pending.values():
            if not future.done():
                error = ConnectionLost(text, dict(data))
                error.__cause__ = cause
                future.set_exception(error)
        self._pulse()

    def _fail(self, ws: ClientConnection, failure: str) -> ConnectionLost:
        """End a connection from this side: fail every pending call, close with code 1008.

        The calls fail first and the close runs in the background, since it may wait for the
        peer's close frame. Return the error the pending calls got.
        """
        self._lost(ws, failure, None)
        self._close_in_background(ws, _CLOSE_PROTOCOL_VIOLATION, "invalid JSON-RPC")
        return ConnectionLost(failure, {"close_code": _CLOSE_PROTOCOL_VIOLATION, "url": self.url})

    def _violation(self, ws: ClientConnection, exc: ParseError | InvalidRequest) -> ConnectionLost:
        """Fail a connection whose server sent something that is not JSON-RPC; see :meth:`_fail`.

        The reader calls it for a message it parsed, a caller for the reply the reader left
        unparsed.
        """
        self.logger.error(
            "%s sent something that is not JSON-RPC: %s; closing the connection",
            self.url,
            exc.message,
        )
        return self._fail(ws, f"the server broke the protocol: {exc.message}")

    def _pulse(self) -> None:
        """Wake every task waiting for a change in the connection or the services."""
        self._changed.set()
        self._changed.clear()

    # --- calls ------------------------------------------------------------------------------

    async def call(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
        **fields: Any,
    ) -> Any:
        """Call the service ``name`` and return its response.

        ``request`` is a ``Request`` model, a dict, or left out in favour of keyword ``fields``.
        The result is the typed ``Response`` when the service type is known (``srv_type``, or
        the type the server advertised, loaded locally), else the plain dict the server sent.

        ``timeout`` (seconds) overrides the client's default deadline. ``wait_for_ready=True``
        first waits, within that deadline, for the connection and for the service to be
        advertised; it raises :class:`~srvwire.errors.ServiceUnavailable` if they are not
        there in time, and nothing was sent.

        Raise the :class:`~srvwire.errors.RPCError` subclass that matches the failure:
        ``DeadlineExceeded``, ``ConnectionLost``, ``InvalidParams`` (also locally, before
        sending), ``ServiceNotFound``, ``InternalError``, ``ServiceError``, and so on.
        """
        method = canonical_name(name)
        budget = self.timeout if timeout is None else _check_timeout(timeout)
        # The client's own loop, not asyncio.get_running_loop(): on Python 3.11 that asks the
        # kernel for the process id on every call, to notice a fork.
        deadline = (self._loop or asyncio.get_running_loop()).time() + budget
        if wait_for_ready:
            await self._wait_until_ready(method, deadline, budget)
        ws = self._ws
        if ws is None:
            raise self._not_connected(method)
        srv = self._resolve_type(method, srv_type)
        params = self._encode_request(method, srv, request, fields)
        reply = await self._roundtrip(ws, method, params, deadline, budget)
        if srv is not None and isinstance(reply, RawReply):
            response = self._decode_in_one_pass(srv.Response, reply.result)
            if response is not None:
                return response
        result = self._result(ws, method, reply)
        if srv is None:
            return result
        try:
            return srv.Response.model_validate(result)
        except ValidationError as exc:
            errors = validation_errors(exc)
            raise InternalError(
                f"the response does not match {srv.type_name}: {summarize_errors(errors)}",
                {"errors": errors},
                service=method,
            ) from None

    def service(self, name: str, srv_type: SrvType | None = None) -> ServiceProxy:
        """Return a callable for the service ``name``: ``await proxy(a=1, b=2)``."""
        return ServiceProxy(self, name, srv_type)

    async def wait_for_service(
        self,
        name: str,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - gives up with ServiceUnavailable
    ) -> ServiceInfo:
        """Wait until the server advertises ``name``; return its name and type.

        Woken by ``$/services`` (no polling). With ``reconnect=True`` it also waits for the
        connection to come (back). Raise :class:`~srvwire.errors.ServiceUnavailable` when
        ``timeout`` (default: the client's) passes first, and ``ConnectionLost`` at once when
        the connection is down for good.
        """
        method = canonical_name(name)
        budget = self.timeout if timeout is None else _check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        await self._wait_until_ready(method, deadline, budget)
        return ServiceInfo(method, self._services[method])

    async def list_services(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> list[ServiceInfo]:
        """Ask the server for every service it offers (``rpc.discover``), sorted by name."""
        budget = self.timeout if timeout is None else _check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        ws = self._ws
        if ws is None:
            raise self._not_connected(DISCOVER_METHOD)
        reply = await self._roundtrip(ws, DISCOVER_METHOD, None, deadline, budget)
        document = self._result(ws, DISCOVER_METHOD, reply)
        methods = document.get("methods") if isinstance(document, dict) else None
        if not isinstance(methods, list):
            raise InternalError(
                "rpc.discover did not return an OpenRPC document with 'methods'",
                service=DISCOVER_METHOD,
            )
        found = [
            ServiceInfo(canonical_name(entry["name"]), entry["x-srvwire-type"])
            for entry in methods
            if isinstance(entry, dict)
            and isinstance(entry.get("name"), str)
            and isinstance(entry.get("x-srvwire-type"), str)
        ]
        return sorted(found, key=lambda info: info.name)

    def _result(
        self, ws: ClientConnection, method: str, reply: Response | ErrorResponse | RawReply
    ) -> Any:
        """Return the result of ``reply``, parsed in full if it is raw; raise an error reply.

        A raw reply that is not JSON-RPC after all fails the connection, as the reader would
        have (:meth:`_violation`), and raises the ``ConnectionLost`` every pending call got.
        """
        if isinstance(reply, RawReply):
            try:
                reply = parse_raw_reply(reply)
            except (ParseError, InvalidRequest) as exc:
                lost = self._violation(ws, exc)
                lost.service = method
                raise lost from None
        if isinstance(reply, ErrorResponse):
            reply.error.service = method
            raise reply.error
        return reply.result

    def _decode_in_one_pass(self, model: type[Message], text: str) -> Message | None:
        """Validate JSON ``text`` straight into ``model``; None when it does not validate.

        Then only a full parse can tell whether the reply does not match the type or is not even
        JSON-RPC (see the module's theory of operation).
        """
        try:
            # model_validate_json without its Python wrapper: a quarter of it on a small reply
            response: Message = model.__pydantic_validator__.validate_json(text)
        except ValidationError:
            return None
        return response

    def _not_connected(self, method: str) -> ConnectionLost:
        why = "the client is closed" if self._closed else f"not connected to {self.url}"
        return ConnectionLost(why, {"url": self.url}, service=method)

    async def _wait_until_ready(self, method: str, deadline: float, budget: float) -> None:
        """Wait until connected and ``method`` is advertised, or raise ServiceUnavailable."""
        while self._ws is None or method not in self._services:
            if self._closed or (self._ws is None and not self.reconnect):
                raise self._not_connected(method)
            try:
                async with asyncio.timeout_at(deadline):
                    await self._changed.wait()
            except TimeoutError:
                if self._ws is not None and method in self._services:
                    return
                where = "was not advertised" if self._ws is not None else "was not reachable"
                raise ServiceUnavailable(
                    f"the service {where} within {budget:g} s",
                    {"url": self.url, "timeout": budget},
                    service=method,
                ) from None

    def _resolve_type(self, method: str, srv_type: SrvType | None) -> type[Service] | None:
        """Return the service class to use for ``method``, or None to send plain dicts."""
        if srv_type is not None and not isinstance(srv_type, str):
            return srv_type
        named = srv_type is not None
        type_name = srv_type if srv_type is not None else self._services.get(method)
        if type_name is None:
            return None
        if type_name in self._types:
            cached = self._types[type_name]
            if cached is not None or not named:
                return cached
        loaded: type[Service] | None
        try:
            loaded = load_service(type_name, search_path=self.search_path)
        except InterfaceError as exc:
            if named:
                raise  # the caller named a type that cannot be loaded: say so
            self.logger.info(
                "cannot load %s for %s (%s); its calls send and return plain dicts",
                type_name,
                method,
                exc,
            )
            loaded = None
        self._types[type_name] = loaded
        return loaded

    def _encode_request(
        self,
        method: str,
        srv: type[Service] | None,
        request: BaseModel | Mapping[str, Any] | None,
        fields: dict[str, Any],
    ) -> str:
        """Validate the request when its type is known and return its JSON text (an object)."""
        if request is not None and fields:
            raise TypeError("pass the request object or keyword fields, not both")
        value: BaseModel | Mapping[str, Any] = fields if request is None else request
        if srv is not None and not isinstance(value, srv.Request):
            if isinstance(value, BaseModel):
                raise TypeError(
                    f"{method} takes {srv.type_name} requests, not {type(value).__qualname__}"
                )
            try:
                value = srv.Request.model_validate(value)
            except ValidationError as exc:
                raise _refused(method, validation_errors(exc)) from None
        try:
            if not isinstance(value, BaseModel):
                return encode_json(dict(value))
            # model_dump_json(by_alias=True) without its Python wrapper, by the instance's class
            text = type(value).__pydantic_serializer__.to_json(value, by_alias=True).decode()
        except PydanticSerializationError as exc:
            # A string with a lone surrogate validates, but cannot be written as UTF-8.
            errors = unencodable_strings(value) or [
                {"path": "", "message": str(exc), "type": "serialization_error"}
            ]
            raise _refused(method, errors) from None
        if not text.startswith("{"):  # a RootModel or a custom serializer: not params by name
            raise TypeError(
                f"the request for {method} must serialize to a JSON object (params by name); "
                f"{type(value).__qualname__} serializes to {text[:40]!r}"
            )
        return text

    async def _roundtrip(
        self,
        ws: ClientConnection,
        method: str,
        params: str | None,
        deadline: float,
        budget: float,
    ) -> Response | ErrorResponse | RawReply:
        """Send one request and wait for its reply until ``deadline``.

        ``params`` is the request's JSON object text, sent with the remaining time spliced in as
        ``_meta.timeout``; None sends no params (and no deadline).
        """
        loop = self._loop or asyncio.get_running_loop()
        remaining = deadline - loop.time()
        request_id = next(self._ids)
        if remaining <= 0:
            raise DeadlineExceeded(
                f"no time left to send the call ({budget:g} s deadline)",
                {"timeout": budget},
                service=method,
            )
        if params is None:
            text = Request(request_id, method).serialize()
        else:
            text = encode_call(request_id, self._encode_method(method), params, round(remaining, 6))
        future: asyncio.Future[Response | ErrorResponse | RawReply] = loop.create_future()
        pending = self._pending
        pending[request_id] = future
        task = asyncio.current_task(loop)
        cancelling = task.cancelling() if task is not None else 0
        try:
            # The send waits only on backpressure, so it is bounded only if it does wait: by a
            # bare timer (Expired is a TimeoutError), and with no task, where wait_for would
            # wrap the coroutine in one on Python 3.11.
            sending = first_step(ws.send(text))
            if isinstance(sending, Pending):
                await finish_within(sending, deadline - loop.time())
            # On a future, wait_for creates no task: a timer and a done callback.
            reply = await asyncio.wait_for(future, deadline - loop.time())
            if task is not None and task.cancelling() > cancelling:
                # Python 3.11's wait_for returns the result when a cancellation arrives after
                # the reply did (gh-86296); the caller asked to stop, so stop.
                raise asyncio.CancelledError
            return reply
        except TimeoutError:
            self._cancel_remote(ws, method, request_id, pending, future)
            raise DeadlineExceeded(
                f"no response within {budget:g} s", {"timeout": budget}, service=method
            ) from None
        except asyncio.CancelledError:
            self._cancel_remote(ws, method, request_id, pending, future)
            raise
        except ConnectionClosed as exc:
            why, data = _describe_close(ws, exc)
            raise ConnectionLost(why, {**data, "url": self.url}, service=method) from exc
        except ConnectionLost as exc:  # set on the future when the connection dropped
            exc.service = method
            raise
        finally:
            pending.pop(request_id, None)

    def _encode_method(self, method: str) -> str:
        """Return ``method`` written as JSON, from a small cache."""
        cache = self._method_json
        encoded = cache.get(method)
        if encoded is None:
            if len(cache) >= _METHOD_CACHE_SIZE:
                cache.clear()
            encoded = cache[method] = encode_json(method)
        return encoded

    def _cancel_remote(
        self,
        ws: ClientConnection,
        method: str,
        request_id: int,
        pending: dict[int, asyncio.Future[Response | ErrorResponse | RawReply]],
        future: asyncio.Future[Response | ErrorResponse | RawReply],
    ) -> None:
        """Tell the server to cancel a call we gave up on, in the background."""
        # Resolved as we gave up: mark an error seen so asyncio stays quiet, and check a reply
        # the reader left unparsed as the reader would have checked it.
        if future.done() and not future.cancelled() and future.exception() is None:
            reply = future.result()
            if isinstance(reply, RawReply):
                try:
                    parse_raw_reply(reply)
                except (ParseError, InvalidRequest) as exc:
                    self._violation(ws, exc)
        if request_id not in pending or self._ws is not ws:
            return  # answered meanwhile, or the connection is gone: nothing to cancel
        self.logger.debug("cancelling %s (id %d) on the server", method, request_id)
        task = asyncio.get_running_loop().create_task(
            self._send_quietly(ws, cancel_notification(request_id).serialize())
        )
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def _close_in_background(
        self, ws: ClientConnection, code: int = 1000, reason: str = ""
    ) -> None:
        task = asyncio.get_running_loop().create_task(ws.close(code, reason))
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    async def _send_quietly(self, ws: ClientConnection, text: str) -> None:
        try:
            await ws.send(text)
        except ConnectionClosed:
            pass  # best effort: a closed connection has cancelled everything anyway


class ServiceProxy:
    """A callable bound to one service: ``await proxy(request_or_fields, timeout=...)``."""

    def __init__(self, client: Client, name: str, srv_type: SrvType | None = None) -> None:
        self.client = client
        self.name = canonical_name(name)
        self.srv_type = srv_type

    async def __call__(
        self,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
        wait_for_ready: bool = False,
        **fields: Any,
    ) -> Any:
        """Call the service; see :meth:`Client.call`."""
        return await self.client.call(
            self.name,
            request,
            timeout=timeout,
            srv_type=self.srv_type,
            wait_for_ready=wait_for_ready,
            **fields,
        )

    async def wait_for_service(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - gives up with ServiceUnavailable
    ) -> ServiceInfo:
        """Wait until the server advertises this service; see :meth:`Client.wait_for_service`."""
        return await self.client.wait_for_service(self.name, timeout=timeout)

    def __repr__(self) -> str:
        return f"ServiceProxy({self.name!r}, {self.srv_type!r})"


class Connecting:
    """What :func:`connect` returns: await it for an open client, or use it with ``async with``."""

    def __init__(self, client: Client) -> None:
        self.client = client

    def __await__(self) -> Generator[Any, None, Client]:
        return self.client.open().__await__()

    async def __aenter__(self) -> Client:
        return await self.client.open()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.client.close()


def connect(
    url: str = DEFAULT_URL,
    *,
    timeout: float = DEFAULT_TIMEOUT,
    open_timeout: float = 10.0,
    max_message_size: int | None = 2**20,
    ping_interval: float | None = 20.0,
    ping_timeout: float | None = 20.0,
    compression: str | None = None,
    reconnect: bool = False,
    search_path: SearchPath | None = None,
    logger: LoggerLike | None = None,
) -> Connecting:
    """Connect to the srvwire server at ``url``.

    Use it as ``async with connect(url) as client:`` (closed on exit) or as
    ``client = await connect(url)`` (close it with ``await client.close()``).

    * ``timeout``: the default deadline of a call, in seconds; finite.
    * ``open_timeout``: how long opening may take (TCP, handshake, the services list).
    * ``max_message_size``: the largest message accepted from the server, in bytes (``None``:
      no limit). A larger one closes the connection with code 1009.
    * ``ping_interval``/``ping_timeout``: WebSocket keepalive; a peer that stops answering
      pings is treated as a dropped connection.
    * ``compression``: ``"deflate"`` to negotiate per-message compression; off by default,
      since JSON-RPC messages are small and compression costs time on every one.
    * ``reconnect``: re-dial in the background (with backoff) when the connection drops or
      cannot be opened; see :meth:`Client.call`'s ``wait_for_ready``. Opening then never
      raises for an unreachable server.
    * ``search_path``: where to load service types by name (default: the loader's).
    * ``logger``: where to log (default: the ``srvwire.client`` logger).

    Raise :class:`~srvwire.errors.ServiceUnavailable` when the server cannot be reached
    (without ``reconnect``) and ``ValueError`` for a URL that is not ``ws://`` or ``wss://``.
    """
    client = Client(
        url,
        timeout=timeout,
        open_timeout=open_timeout,
        max_message_size=max_message_size,
        ping_interval=ping_interval,
        ping_timeout=ping_timeout,
        compression=compression,
        reconnect=reconnect,
        search_path=search_path,
        logger=logger,
    )
    return Connecting(client)
