"""The asyncio WebSocket server: connections, concurrency limits, cancellation and shutdown.

Theory of operation
-------------------

A :class:`Server` holds a :class:`~srvwire.dispatch.ServiceRegistry` and its options; it does not
listen by itself. :func:`serve` binds it to a host and port and returns a :class:`RunningServer`.
Each WebSocket connection gets a :class:`_Connection` whose *reader* is the only code that receives
from the socket. For every message the reader calls :func:`~srvwire.protocol.parse_incoming` and
answers what can be answered at once (errors, ``rpc.discover``, ``$/cancel``). A call or a
notification to a service runs inline, on the reader's task, up to its first suspension
(:func:`~srvwire.inline.first_step`): most handlers answer without waiting, and their reply is
sent before the next message is read, with no task of their own. A call that has to wait keeps
the task it started on (so the task it saw as ``asyncio.current_task()``, the one its
``asyncio.timeout`` or deadline cancels, stays its own), and the connection starts a new reader
task. A batch gets a task that starts its calls, each in a task of its own, and sends their
replies as one array.

Invariants:

* **The reader never waits for a handler.** Calls on one connection run concurrently; a handler
  that hangs holds only its own task, since the reader it started on hands the reading to a new
  task the moment the handler has to wait. Single messages start in the order they arrive; a
  batch's calls start in tasks of their own once the whole batch is read (so a ``$/cancel`` in
  the same batch reaches them), which may be after the first step of a message that follows.
  The reader waits only to send a reply, which is what pushes back on a client that writes
  faster than it reads.
* **Each call runs in a context of its own**, a copy of the reader's (as a task would), so
  context variables a handler sets never reach the next call.
* **In flight is bounded per connection.** At most ``max_in_flight`` calls and notifications run at
  once on a connection; past that a call is answered ``RESOURCE_EXHAUSTED`` at once (a notification
  is dropped and logged), and the connection carries on. Messages are bounded by
  ``max_message_size``: websockets closes the connection with 1009 past it. A call that waits
  counts from the moment it takes over its reader's task until it has replied; a call that
  never waits has ended before the reader reads on, so it never counts. A batch's call or
  notification counts from the creation of its task until the task's coroutine settles it in
  its own ``finally`` (after the reply is built); a task the connection's teardown cancels
  before its first step is settled by a done-callback instead, since its coroutine never runs.
  The bookkeeping does not depend on when a task's first step runs: a call is registered
  before its task is created, and a task is counted only if it is not already done, so an
  eager task factory (Python 3.12's ``asyncio.eager_task_factory``), which may run a call to
  its end inside ``create_task``, leaks neither a count nor an id.
* **Replies are sent as they are encoded.** A call's result is the UTF-8 JSON bytes pydantic
  wrote, wrapped in its envelope and sent as a text frame, never copied into a ``str`` and back
  (only a batch, which joins its replies as text, decodes them).
* **Every request gets exactly one reply**, while the connection is open: its result, or an error.
  A call whose ``id`` can be cancelled is listed in ``_Connection.calls`` until its reply is built,
  so ``$/cancel`` finds it only while the handler runs; a call with ``"id": null``, which
  ``$/cancel`` cannot name, is listed in ``_Connection.anonymous`` instead, so that shutdown
  still answers it. The cancel reason (``CANCELLED``, ``UNAVAILABLE``) is recorded in the call's
  :class:`~srvwire.dispatch.Context` *before* the task is cancelled, so the task knows which
  error to send; the first reason wins, and a call's task is cancelled at most once (so the one
  ``uncancel`` it does before replying leaves ``Task.cancelling()`` at 0). A task cancelled
  without a reason (the connection went away) sends nothing. A CancelledError that a handler
  raises by itself, while nothing cancels its task, is turned into ``INTERNAL`` by
  :func:`~srvwire.dispatch.dispatch`, so it cannot end a call silently; so is a cancellation
  of its task that srvwire did not request (the handler cancelled ``asyncio.current_task()``),
  and any other exception that escapes it (a bug in srvwire) is logged and answered
  ``INTERNAL`` too. A handler that cancels its task while running inline, and then returns
  without waiting, cancelled the reader: that request is taken back (and logged), so the
  connection reads on.
* **Nothing a client sends stops the server.** Only this module knows websockets' exceptions; a
  closed connection ends that connection's reader and cancels that connection's calls, nothing
  more. Handler exceptions are turned into replies by :func:`~srvwire.dispatch.dispatch`.
* **Shutdown is graceful and bounded.** :meth:`RunningServer.close` stops listening, answers new
  calls ``UNAVAILABLE``, waits up to ``grace_period`` for calls in flight, cancels the rest (they
  answer ``UNAVAILABLE``), then closes every connection with 1001 (going away).
* **Clients learn of services without polling.** Each connection gets ``$/services`` as its first
  message, and again whenever a service is added or removed.
* **The registry changes on the event loop's thread.** While the server listens,
  :meth:`Server.add_service` and :meth:`Server.remove_service` called from another thread hand
  the change to the loop and wait for it, so the loop never sees the registry half-changed.
* **A notification is never answered.** One with a bad ``params._meta`` is dropped and logged.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable, Coroutine, Generator
from concurrent.futures import Executor
from contextvars import copy_context
from types import TracebackType
from typing import Any, TypeVar

from websockets.asyncio.server import (
    Server as _WebSocketServer,
    ServerConnection,
    serve as _ws_serve,
)
from websockets.exceptions import ConnectionClosed, ConnectionClosedOK

from srvwire.dispatch import Context, Handler, ServiceEntry, ServiceRegistry, dispatch
from srvwire.errors import (
    Cancelled,
    InternalError,
    InvalidRequest,
    ResourceExhausted,
    RPCError,
    ServiceUnavailable,
)
from srvwire.inline import Pending, finish, first_step
from srvwire.models import Service
from srvwire.protocol import (
    CANCEL_METHOD,
    DISCOVER_METHOD,
    ErrorResponse,
    Id,
    Notification,
    RawJSON,
    Request,
    Response,
    encode_result,
    parse_incoming,
    serialize_batch,
    services_notification,
)

__all__ = ["RunningServer", "Server", "serve"]

H = TypeVar("H", bound=Handler)

_PROTOCOL_PREFIX = "$/"
_LOOP_CHECK_INTERVAL = 1.0  # seconds between checks that a loop we wait on still runs


def _running_loop() -> asyncio.AbstractEventLoop | None:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None


class Server:
    """A set of services and the options to serve them with; :func:`serve` makes it listen.

    ``max_in_flight`` bounds the calls running at once on one connection; ``max_message_size``
    the size of one incoming message in bytes (None: no limit); ``grace_period`` how long
    shutdown waits for calls in flight; ``ping_interval``/``ping_timeout`` the keepalive (None
    turns it off); ``compression="deflate"`` turns permessage-deflate on (off by default: it
    slows small calls down); ``executor`` runs sync handlers (default: asyncio's).
    """

    def __init__(
        self,
        *,
        max_in_flight: int = 256,
        max_message_size: int | None = 2**20,
        grace_period: float = 5.0,
        ping_interval: float | None = 20.0,
        ping_timeout: float | None = 20.0,
        compression: str | None = None,
        executor: Executor | None = None,
        logger: logging.Logger | None = None,
    ) -> None:
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be at least 1, not {max_in_flight}")
        if grace_period < 0:
            raise ValueError(f"grace_period must not be negative, not {grace_period}")
        self.registry = ServiceRegistry()
        self.max_in_flight = max_in_flight
        self.max_message_size = max_message_size
        self.grace_period = grace_period
        self.ping_interval = ping_interval
        self.ping_timeout = ping_timeout
        self.compression = compression
        self.executor = executor
        self.logger = logger if logger is not None else logging.getLogger("srvwire.server")
        self._running: set[RunningServer] = set()

    def __repr__(self) -> str:
        return f"<Server with {len(self.registry)} services>"

    # --- services ---------------------------------------------------------------------------

    def add_service(self, name: str, srv_type: type[Service], handler: Handler) -> None:
        """Serve ``handler`` for ``srv_type`` under ``name``; tell connected clients.

        Raise :class:`~srvwire.errors.RegistrationError` for a bad name, a name already taken,
        a type that is not a service type, or a handler that cannot be called as one. Safe to
        call from any thread: while the server listens, the change is made on its event loop.
        """

        def add() -> None:
            self.registry.add(name, srv_type, handler)
            self._services_changed()

        self._change_services(add)

    def remove_service(self, name: str) -> None:
        """Stop serving ``name``; calls already running finish. Tell connected clients.

        Raise :class:`~srvwire.errors.RegistrationError` if no service has that name. Safe to
        call from any thread, as :meth:`add_service` is.
        """

        def remove() -> None:
            self.registry.remove(name)
            self._services_changed()

        self._change_services(remove)

    def service(self, name: str, srv_type: type[Service]) -> Callable[[H], H]:
        """Decorate a handler to serve it under ``name``; the handler is returned unchanged."""

        def register(handler: H) -> H:
            self.add_service(name, srv_type, handler)
            return handler

        return register

    def _change_services(self, change: Callable[[], None]) -> None:
        """Run ``change`` on the thread of the loop the server listens on; wait, and re-raise.

        Not listening, or already on that loop, ``change`` runs at once. If the loop stops
        before it gets to the change, the change is made here instead.
        """
        loop = next((r._loop for r in tuple(self._running) if r._loop is not None), None)
        if loop is None or not loop.is_running() or _running_loop() is loop:
            change()
            return
        done: concurrent.futures.Future[None] = concurrent.futures.Future()

        def on_loop() -> None:
            if not done.set_running_or_notify_cancel():
                return  # the caller gave up on this loop and made the change itself
            try:
                change()
            except BaseException as exc:
                done.set_exception(exc)
                if not isinstance(exc, Exception):
                    raise
            else:
                done.set_result(None)

        try:
            loop.call_soon_threadsafe(on_loop)
        except RuntimeError:  # the loop was closed in the meantime
            change()
            return
        while True:
            try:
                return done.result(timeout=_LOOP_CHECK_INTERVAL)
            except concurrent.futures.TimeoutError:
                if not loop.is_running() and done.cancel():
                    change()
                    return

    def _services_changed(self) -> None:
        if self._running:
            text = services_notification(self.registry.services()).serialize()
            for running in list(self._running):
                running._broadcast(text)

    # --- running ----------------------------------------------------------------------------

    def run(
        self,
        host: str = "127.0.0.1",
        port: int = 8765,
        *,
        ready: Callable[[RunningServer], object] | None = None,
        stopping: Callable[[RunningServer], object] | None = None,
    ) -> None:
        """Serve until Ctrl-C or SIGTERM, then shut down gracefully; for scripts.

        The blocking form of :meth:`serve_forever`, which describes ``ready`` and ``stopping``.
        """
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(self.serve_forever(host, port, ready=ready, stopping=stopping))

    async def serve_forever(
        self,
        host: str = "127.0.0.1",
        port: int = 8765,
        *,
        ready: Callable[[RunningServer], object] | None = None,
        stopping: Callable[[RunningServer], object] | None = None,
    ) -> None:
        """Serve on ``host``:``port`` until SIGINT or SIGTERM, then shut down gracefully.

        ``ready`` is called with the :class:`RunningServer` once it listens (its ``url`` has the
        port really bound, useful with port 0); ``stopping`` once a signal arrived, before the
        graceful shutdown. Signal handlers are installed only in the main thread, and the ones
        they replaced are restored on return; elsewhere (or where the loop cannot handle
        signals) cancel the task, or let Ctrl-C raise KeyboardInterrupt, to stop. An OSError
        means the address could not be bound.
        """
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        replaced: list[tuple[signal.Signals, Any]] = []
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                previous = signal.getsignal(signum)
                try:
                    loop.add_signal_handler(signum, stop.set)
                except (NotImplementedError, RuntimeError):  # Windows: KeyboardInterrupt instead
                    continue
                replaced.append((signum, previous))
        try:
            async with serve(self, host, port) as running:
                count = len(self.registry)
                services = "service" if count == 1 else "services"
                self.logger.info("serving %d %s on %s", count, services, running.url)
                if ready is not None:
                    ready(running)
                await stop.wait()
                self.logger.info("shutting down")
                if stopping is not None:
                    stopping(running)
        finally:
            for signum, previous in replaced:
                loop.remove_signal_handler(signum)
                if previous is not None:  # None: installed outside Python, cannot be restored
                    signal.signal(signum, previous)


class serve:
    """Serve ``server`` on ``host``:``port`` (0 picks a free port).

    Use it as ``async with serve(server) as running: ...`` (closed on exit) or as
    ``running = await serve(server)`` (then ``await running.close()``).
    """

    def __init__(self, server: Server, host: str = "127.0.0.1", port: int = 8765) -> None:
        self._server = server
        self._host = host
        self._port = port
        self._running: RunningServer | None = None

    async def _start(self) -> RunningServer:
        running = RunningServer(self._server)
        await running._start(self._host, self._port)
        self._running = running
        return running

    def __await__(self) -> Generator[Any, None, RunningServer]:
        return self._start().__await__()

    async def __aenter__(self) -> RunningServer:
        return await self._start()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._running is not None:
            await self._running.close()


class RunningServer:
    """A server listening on a socket: where it listens, its connections, and how to stop it."""

    host: str
    port: int

    def __init__(self, server: Server) -> None:
        self.server = server
        self.closing = False
        self._connections: set[_Connection] = set()
        self._ws_server: _WebSocketServer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._close_task: asyncio.Task[None] | None = None

    async def _start(self, host: str, port: int) -> None:
        options = self.server
        self._loop = asyncio.get_running_loop()
        self._ws_server = await _ws_serve(
            self._handle,
            host,
            port,
            compression=options.compression,
            max_size=options.max_message_size,
            ping_interval=options.ping_interval,
            ping_timeout=options.ping_timeout,
        )
        name = self._ws_server.sockets[0].getsockname()
        self.host = host
        self.port = int(name[1])
        options._running.add(self)

    @property
    def url(self) -> str:
        """``ws://host:port``, the address clients connect to."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def __repr__(self) -> str:
        state = "closing" if self.closing else "serving"
        return f"<RunningServer {state} on {self.url}, {len(self._connections)} connections>"

    async def __aenter__(self) -> RunningServer:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Shut down gracefully (see the module's invariants); safe to call more than once."""
        if self._close_task is None:
            self._close_task = asyncio.create_task(self._close())
        await asyncio.shield(self._close_task)

    aclose = close

    async def wait_closed(self) -> None:
        """Wait until the server has been closed by :meth:`close`."""
        assert self._ws_server is not None
        await self._ws_server.wait_closed()

    async def _close(self) -> None:
        assert self._ws_server is not None
        options = self.server
        self.closing = True
        options._running.discard(self)
        self._ws_server.close(close_connections=False)  # stop listening; keep connections
        tasks = {task for conn in self._connections for task in (*conn.tasks, *conn.counted)}
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=options.grace_period)
            if pending:
                options.logger.warning(
                    "cancelling %d calls still running after the %.3g s grace period",
                    len(pending),
                    options.grace_period,
                )
                for conn in list(self._connections):
                    conn.cancel_all(
                        ServiceUnavailable("the server shut down before the call finished")
                    )
                # The cancelled calls reply at once; do not wait on a peer that does not read.
                await asyncio.wait(pending, timeout=1.0)
        closes = [conn.ws.close(1001, "server shutting down") for conn in self._connections]
        if closes:
            await asyncio.gather(*closes, return_exceptions=True)
        await self._ws_server.wait_closed()

    def _broadcast(self, text: str) -> None:
        """Send ``text`` to every connection; callable from any thread."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        if _running_loop() is not loop:
            loop.call_soon_threadsafe(self._broadcast, text)
            return
        for conn in list(self._connections):
            conn.spawn(conn.send(text))

    async def _handle(self, ws: ServerConnection) -> None:
        conn = _Connection(self, ws)
        self._connections.add(conn)
        log = self.server.logger
        if log.isEnabledFor(logging.DEBUG):
            log.debug("connection from %s opened", conn.peer)
        try:
            await ws.send(services_notification(self.server.registry.services()).serialize())
            await conn.serve()
        except ConnectionClosed as exc:
            if log.isEnabledFor(logging.DEBUG):
                log.debug("connection from %s closed: %s", conn.peer, exc)
        finally:
            self._connections.discard(conn)
            conn.cancel_all(None)


class _Call:
    """A call in flight: its task, its context, and whether it has started running.

    ``task`` is None while a call runs inline, on the reader, before it has to wait: nothing
    can cancel it then, since the reader reads nothing else meanwhile.
    """

    __slots__ = ("cancelled", "context", "started", "task")

    def __init__(self, context: Context) -> None:
        self.context = context
        self.started = False
        self.cancelled = False  # whether its task was cancelled (at most once)
        self.task: asyncio.Task[Any] | None = None

    def cancel(self, error: RPCError | None) -> None:
        """Cancel the call; with ``error`` it answers that error, without it stays silent.

        A task cancelled before its first step never runs a line of its coroutine, so it could
        not answer; a call that has not started is only marked, and answers when it starts.
        The first reason recorded wins, and the task is cancelled once at most: the call takes
        back one cancellation (``uncancel``) before it replies, so a second would stay pending.
        """
        self.context._mark_cancelled(error)
        if self.task is not None and not self.cancelled and (self.started or error is None):
            self.cancelled = True
            self.task.cancel()


class _Connection:
    """One client connection: its reader, and the calls it has in flight.

    A reader task that a waiting call took over is in :attr:`counted` until the call is done;
    :attr:`reader` is always the task that reads now. A batch's call or notification task is in
    :attr:`counted` from its creation until its coroutine's own ``finally`` takes it out (no
    done-callback: that would cost the loop one more turn per call). A task cancelled before
    its first step never runs that ``finally``; the only code that cancels tasks which may not
    have started is :meth:`cancel_all` without an error, and it gives each such task a
    done-callback that settles it instead. A task already done when :meth:`spawn_counted` gets
    it back (an eager task factory ran it to its end) settled before it could be counted, and
    is not counted.
    """

    __slots__ = (
        "anonymous",
        "calls",
        "counted",
        "loop",
        "peer",
        "reader",
        "reading",
        "running",
        "tasks",
        "ws",
    )

    def __init__(self, running: RunningServer, ws: ServerConnection) -> None:
        self.running = running
        self.ws = ws
        self.loop = asyncio.get_running_loop()
        self.peer: Any = ws.remote_address
        self.calls: dict[Id, _Call] = {}  # calls that $/cancel can reach, by id
        self.anonymous: set[_Call] = set()  # calls with "id": null, for shutdown to answer
        self.tasks: set[asyncio.Task[Any]] = set()  # other tasks: batches, broadcasts
        self.counted: set[asyncio.Task[Any]] = set()  # calls and notifications in flight
        self.reader: asyncio.Task[None] | None = None  # the task reading the socket now
        self.reading: asyncio.Future[None] = self.loop.create_future()  # done: reading ended

    @property
    def in_flight(self) -> int:
        """How many calls and notifications run on this connection."""
        return len(self.counted)

    def spawn(self, coro: Any) -> asyncio.Task[Any]:
        task: asyncio.Task[Any] = self.loop.create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    def spawn_counted(self, coro: Any) -> asyncio.Task[Any]:
        """Spawn a call or notification task; it counts as in flight until it settles.

        ``coro`` must settle its task itself, last thing, with :meth:`settle`. Under an eager
        task factory it may have done so already, inside ``create_task``: a task that is done
        is not counted.
        """
        task: asyncio.Task[Any] = self.loop.create_task(coro)
        if not task.done():
            self.counted.add(task)
        return task

    def settle(self) -> None:
        """Uncount the running task, a call's or a notification's; its coroutine's last step."""
        try:
            task = asyncio.current_task()
        except RuntimeError:  # closed by the garbage collector after its loop: nothing counts
            return
        if task is not None:
            self.counted.discard(task)

    def forget(self, call: _Call) -> None:
        """Take ``call`` out of :attr:`calls`, so that ``$/cancel`` no longer finds it."""
        id = call.context.request_id
        if id is None:
            self.anonymous.discard(call)
        elif self.calls.get(id) is call:
            del self.calls[id]

    async def send(self, text: str | bytes) -> None:
        """Send a message in a text frame: a ``str``, or UTF-8 bytes as they are."""
        try:
            await self.ws.send(text, text=True)
        except ConnectionClosed:
            pass  # the caller left; its calls are being cancelled

    def cancel_all(self, error: RPCError | None) -> None:
        """Cancel every call in flight; with ``error`` they answer it, without they stay silent.

        Without ``error`` (the connection is gone) every task is cancelled, even one that has
        not started; since such a task never runs its coroutine's ``finally``, each counted
        task gets a done-callback that settles it (a no-op for one that settled itself).
        """
        for call in (*self.calls.values(), *self.anonymous):
            call.cancel(error)
        if error is None:
            self.calls.clear()  # nothing can reach them any more
            self.anonymous.clear()
            for task in list(self.tasks):
                task.cancel()
            for task in list(self.counted):
                task.cancel()
                task.add_done_callback(self.counted.discard)

    async def serve(self) -> None:
        """Read the connection until it ends, one reader task at a time (see :meth:`read`)."""
        self.start_reader()
        try:
            await self.reading
        finally:
            if not self.reading.done():  # this handler was cancelled: stop reading too
                self.reading.cancel()
                if self.reader is not None:
                    self.reader.cancel()

    def start_reader(self) -> None:
        # A plain task, not the loop's task factory: an eager factory would run the new reader
        # inside this call, before it is recorded, and nest one reader in the next.
        self.reader = asyncio.Task(self.read(), loop=self.loop)

    async def read(self) -> None:
        """Read and answer messages until the connection ends or a call has to wait.

        A call runs inline, in this task, up to its first suspension: most calls finish there,
        with no task of their own. A call that has to wait keeps this task, so that whatever
        its handler saw of ``asyncio.current_task()`` stays true, and a new reader takes over.
        """
        try:
            waiting = await self.read_until_a_call_waits()
        except asyncio.CancelledError:
            self.reading.cancel()
            raise
        except BaseException as exc:  # the connection closed, or a bug in srvwire
            if not self.reading.done():
                self.reading.set_exception(exc)
            if not isinstance(exc, ConnectionClosed):
                raise
            return
        if waiting is None:
            if not self.reading.done():
                self.reading.set_result(None)
            return
        call, steps = waiting
        task = asyncio.current_task()
        assert task is not None
        self.counted.add(task)
        if call is not None:
            call.task = task
            call.started = True
            if call.context._cancelled:  # cancelled while its first step ran
                call.cancel(call.context._cancel_error)
        self.start_reader()
        try:
            await finish(steps)
        finally:
            self.counted.discard(task)

    async def read_until_a_call_waits(self) -> tuple[_Call | None, Pending] | None:
        """Answer messages; return a call (None: a notification) that has to wait, and its
        steps; return None when the connection ended.

        Single messages start in the order they arrive. A call or notification runs its first step
        in a context of its own, as a task's would.
        """
        ws = self.ws
        reader = asyncio.current_task(self.loop)
        assert reader is not None
        while True:
            try:
                message = await ws.recv()
            except ConnectionClosedOK:
                return None
            incoming = parse_incoming(message)
            if incoming.is_batch:
                self.spawn(self.batch(incoming.items))
                continue
            item = incoming.items[0]
            if type(item) is Request:
                admitted = self.admit(item)
                if isinstance(admitted, str):
                    await self.send(admitted)
                    continue
                entry, call = admitted
                steps = first_step(self.call(entry, item, call, send=True), copy_context())
                if isinstance(steps, Pending):
                    return call, steps
                if reader.cancelling():
                    await self.ignore_cancellation(entry)
            elif type(item) is Notification:
                notification = self.notify(item)
                if notification is not None:
                    try:
                        steps = first_step(notification, copy_context())
                    except asyncio.CancelledError:  # only the handler can have cancelled it
                        steps = None
                    if isinstance(steps, Pending):
                        return None, steps
                    if reader.cancelling():
                        await self.ignore_cancellation(None)
            else:
                assert isinstance(item, ErrorResponse)
                await self.send(item.serialize())

    async def ignore_cancellation(self, entry: ServiceEntry | None) -> None:
        """Take back a cancellation of the reader that a handler requested while it ran inline.

        Nothing else can cancel the reader while a call runs on it without waiting: the handler
        cancelled what it took for its own task (``asyncio.current_task().cancel()``), and that
        call is over. The request is delivered at the reader's next suspension; it is made here,
        and taken back, so that it can reach neither the reading nor the next call.
        """
        what = f"the handler for {entry.name}" if entry is not None else "a notification handler"
        self.running.server.logger.warning(
            "%s cancelled its own task without waiting for anything; ignored", what
        )
        try:
            await asyncio.sleep(0)
        except asyncio.CancelledError:
            if self.reading.done():  # serve() stopped the reading meanwhile: stop
                raise
        task = asyncio.current_task(self.loop)
        while task is not None and task.cancelling():
            task.uncancel()

    def admit(self, request: Request) -> tuple[ServiceEntry, _Call] | str:
        """Check and register a call; return its entry and call, or the reply text at once.

        Answered at once: a server shutting down, a method that is not a service (discovery,
        ``$/cancel``, an unknown name), too many calls in flight, an id already in use.
        """
        running = self.running
        server = running.server
        id = request.id
        if running.closing:
            return ErrorResponse(id, ServiceUnavailable("the server is shutting down")).serialize()
        entry = server.registry.get(request.method)
        if entry is None:
            return self.special(request)
        if self.in_flight >= server.max_in_flight:
            exhausted = ResourceExhausted(
                f"too many calls in flight on this connection (the limit is "
                f"{server.max_in_flight})",
                {"limit": server.max_in_flight},
                service=entry.name,
            )
            return ErrorResponse(id, exhausted).serialize()
        if id is not None and id in self.calls:
            duplicate = InvalidRequest(
                f"Invalid Request: id {id!r} is already used by a call in flight on this "
                "connection",
                service=entry.name,
            )
            return ErrorResponse(id, duplicate).serialize()
        timeout = request.timeout
        call = _Call(
            Context(
                service=entry.name,
                request_id=id,
                peer=self.peer,
                deadline=None if timeout is None else time.monotonic() + timeout,
            ),
        )
        if id is not None:
            self.calls[id] = call
        else:
            self.anonymous.add(call)
        return entry, call

    def start(self, request: Request) -> str | asyncio.Task[str | None]:
        """Start one call of a batch in a task of its own; return the task, or the reply text.

        The call is registered before its task exists: an eager task factory may run it to its
        end, and forget it, inside ``create_task``.
        """
        admitted = self.admit(request)
        if isinstance(admitted, str):
            return admitted
        entry, call = admitted
        task: asyncio.Task[str | None] = self.spawn_counted(
            self.call_in_batch(entry, request, call)
        )
        call.task = task
        return task

    def special(self, request: Request) -> str:
        """Answer a request for a method that is not a service: discovery, protocol, unknown."""
        server = self.running.server
        if request.method == DISCOVER_METHOD:
            return Response(request.id, RawJSON(server.registry.discover_json())).serialize()
        if request.method == CANCEL_METHOD:
            self.cancel(request.params)
            return Response(request.id, None).serialize()
        try:
            server.registry.resolve(request.method)
        except RPCError as exc:
            return ErrorResponse(request.id, exc).serialize()
        raise AssertionError("unreachable: resolve() found what get() did not")  # pragma: no cover

    async def call(
        self, entry: ServiceEntry, request: Request, call: _Call, *, send: bool
    ) -> str | bytes | None:
        """Run one call; with ``send`` send its reply, else return it (text or UTF-8 bytes).

        Return None when the reply was sent, or when the call was cancelled silently (the
        connection went away). A result is UTF-8 bytes, as pydantic wrote it (no copy into
        a ``str``).
        """
        call.started = True
        context = call.context
        server = self.running.server
        log = server.logger
        reply: str | bytes
        try:
            if context._cancel_error is not None:  # cancelled before it started
                reply = ErrorResponse(request.id, context._cancel_error).serialize()
            else:
                params = request.params
                result = await dispatch(
                    entry,
                    params if not isinstance(params, RawJSON) else None,
                    context,
                    executor=server.executor,
                    logger=log,
                )
                if log.isEnabledFor(logging.DEBUG):
                    log.debug("%s id %r from %s: ok", entry.name, request.id, self.peer)
                reply = encode_result(request.id, result)
                del result  # not held through the send: a large result would be held twice
        except RPCError as exc:
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s id %r from %s: %s", entry.name, request.id, self.peer, exc)
            reply = ErrorResponse(request.id, exc).serialize()
        except asyncio.CancelledError:
            error = context._cancel_error
            task = asyncio.current_task()
            if error is None:
                if call.cancelled:  # the connection went away: nobody to answer
                    raise
                # Nothing in srvwire cancelled it: the handler cancelled its own task.
                log.error("the handler for %s id %r cancelled its own task", entry.name, request.id)
                error = InternalError(
                    f"handler for {entry.name} was cancelled by its own code", service=entry.name
                )
                if call.task is None:
                    task = None  # inline, on the reader: the reader takes the request back
                elif task is not None:
                    # The request may not have been delivered yet (the handler raised by
                    # itself): let it arrive here, or it would end the task after the reply.
                    with contextlib.suppress(asyncio.CancelledError):
                        await asyncio.sleep(0)
            if task is not None:
                task.uncancel()
            reply = ErrorResponse(request.id, error).serialize()
        except Exception:  # a bug in srvwire: still answer, so that the caller is not left waiting
            log.exception(
                "%s id %r from %s failed inside srvwire", entry.name, request.id, self.peer
            )
            internal = InternalError(
                f"the server failed to answer {entry.name}", service=entry.name
            )
            reply = ErrorResponse(request.id, internal).serialize()
        finally:
            self.forget(call)  # from here on, $/cancel no longer finds it
        if not send:
            return reply
        await self.send(reply)
        return None

    async def call_in_batch(self, entry: ServiceEntry, request: Request, call: _Call) -> str | None:
        try:
            reply = await self.call(entry, request, call, send=False)
            return reply.decode() if isinstance(reply, bytes) else reply
        finally:
            self.settle()

    def cancel(self, params: Any) -> None:
        """Handle ``$/cancel``: cancel the call with ``params["id"]``, if it is still running."""
        if not isinstance(params, dict) or "id" not in params:
            return
        try:
            call = self.calls.get(params["id"])
        except TypeError:  # an unhashable id: no call has it
            return
        if call is not None:
            call.cancel(Cancelled("the caller cancelled the call"))

    def notify(self, note: Notification) -> Coroutine[Any, Any, None] | None:
        """Handle a notification; return the coroutine that runs a service's, else None.

        A protocol notification (``$/cancel``) is handled here; one that cannot run is dropped
        (and logged); a notification is never answered.
        """
        method = note.method
        if method.startswith(_PROTOCOL_PREFIX):
            if method == CANCEL_METHOD:
                self.cancel(note.params)
            return None
        running = self.running
        entry = running.server.registry.get(method)
        if entry is None or running.closing:
            return None
        log = running.server.logger
        if note.error is not None:
            log.info("dropped a notification to %s from %s: %s", entry.name, self.peer, note.error)
            return None
        if self.in_flight >= running.server.max_in_flight:
            log.warning(
                "dropped a notification to %s from %s: too many calls in flight",
                entry.name,
                self.peer,
            )
            return None
        timeout = note.timeout
        context = Context(
            service=entry.name,
            peer=self.peer,
            deadline=None if timeout is None else time.monotonic() + timeout,
        )
        return self.run_notification(entry, note, context)

    async def run_notification(
        self, entry: ServiceEntry, note: Notification, context: Context
    ) -> None:
        server = self.running.server
        try:
            await dispatch(
                entry,
                note.params if not isinstance(note.params, RawJSON) else None,
                context,
                executor=server.executor,
                logger=server.logger,
            )
        except RPCError as exc:
            if server.logger.isEnabledFor(logging.INFO):
                server.logger.info("notification to %s failed: %s", entry.name, exc)
        finally:
            self.settle()

    async def batch(self, items: tuple[Request | Notification | ErrorResponse, ...]) -> None:
        """Answer a batch: run its calls concurrently, send their replies as one array."""
        replies: list[str | asyncio.Task[str | None]] = []
        for item in items:
            if type(item) is Request:
                replies.append(self.start(item))
            elif type(item) is Notification:
                notification = self.notify(item)
                if notification is not None:
                    self.spawn_counted(notification)
            else:
                assert isinstance(item, ErrorResponse)
                replies.append(item.serialize())
        if not replies:
            return
        texts: list[str] = []
        for reply in replies:
            text = reply if isinstance(reply, str) else await reply
            if text is not None:
                texts.append(text)
        if texts:
            await self.send(serialize_batch(texts))
