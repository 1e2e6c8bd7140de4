"""The blocking client (``srvwire.sync``), and the async client outside its event loop.

The server runs on an event loop in a thread of its own (a :class:`LoopThread`, the same
machinery the blocking client stands on), so that the test's thread can block in a call, or
run ``asyncio.run`` as a script would, while the server answers.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import gc
import inspect
import json
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from websockets.asyncio.server import ServerConnection, serve as ws_serve

import srvwire
import srvwire.sync
from srvwire.dispatch import Context
from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    InvalidParams,
    ServiceNotFound,
    ServiceUnavailable,
)
from srvwire.loader import load_service
from srvwire.server import RunningServer, Server, serve
from srvwire.sync import LoopThread
from support import Lines, scaled, serve_goal_server, start_interruptible

AddTwoInts = load_service("example_interfaces/srv/AddTwoInts")
Trigger = load_service("std_srvs/srv/Trigger")

ADD = "/add_two_ints"
THREADS = 4


class Handlers:
    """The test server's handlers, and what they saw."""

    def __init__(self) -> None:
        self.peers: set[Any] = set()
        self.barrier: asyncio.Barrier | None = None  # made on the server's loop
        self.hanging = threading.Event()  # set once a call to /hang has started
        self.hung_up = threading.Event()  # set once that call has ended

    async def add(self, request: Any, context: Context) -> Any:
        self.peers.add(context.peer)
        return AddTwoInts.Response(sum=request.a + request.b)

    async def together(self, request: Any) -> Any:
        """Answer only once THREADS calls are in it at the same time."""
        if self.barrier is None:
            self.barrier = asyncio.Barrier(THREADS)
        await self.barrier.wait()
        return {"sum": request.a + request.b}

    async def hang(self, request: Any) -> Any:
        self.hanging.set()
        try:
            await asyncio.Event().wait()  # never set: only a deadline or a cancel ends it
        finally:
            self.hung_up.set()


def build_server(handlers: Handlers) -> Server:
    server = Server(grace_period=0)
    server.add_service(ADD, AddTwoInts, handlers.add)
    server.add_service("/together", AddTwoInts, handlers.together)
    server.add_service("/hang", Trigger, handlers.hang)
    return server


@contextlib.contextmanager
def served_in_a_thread(server: Server, port: int = 0) -> Iterator[RunningServer]:
    """Serve ``server`` on 127.0.0.1 from an event loop in a thread of its own."""
    thread = LoopThread("test server")
    serving = serve(server, "127.0.0.1", port)
    try:
        running = thread.run(serving.__aenter__(), scaled(10))
        try:
            yield running
        finally:
            thread.run(serving.__aexit__(None, None, None), scaled(10))
    finally:
        thread.stop()


@pytest.fixture
def handlers() -> Handlers:
    return Handlers()


@pytest.fixture
def running(handlers: Handlers) -> Iterator[RunningServer]:
    with served_in_a_thread(build_server(handlers)) as value:
        yield value


@pytest.fixture
def client(running: RunningServer) -> Iterator[srvwire.sync.Client]:
    with srvwire.sync.connect(running.url, timeout=scaled(5)) as value:
        yield value


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port


def client_threads() -> set[str]:
    return {t.name for t in threading.enumerate() if t.name.startswith("srvwire client of")}


# --- the blocking client ----------------------------------------------------------------------


def test_a_typed_call(client: srvwire.sync.Client) -> None:
    response = client.call(ADD, {"a": 2, "b": 3})
    assert type(response) is AddTwoInts.Response
    assert response.sum == 5
    assert client.call(ADD, AddTwoInts.Request(a=1, b=1)).sum == 2


def test_fields_as_keywords_through_a_proxy(client: srvwire.sync.Client) -> None:
    add = client.proxy(ADD, timeout=scaled(5))
    assert add(a=40, b=2).sum == 42
    assert add({"a": 1, "b": 2}).sum == 3
    with pytest.raises(TypeError, match="pass the request object or keyword fields, not both"):
        add({"a": 1}, b=2)
    assert add.wait_for_service() == srvwire.ServiceInfo(ADD, "example_interfaces/srv/AddTwoInts")
    assert repr(add) == "srvwire.sync.ServiceProxy('/add_two_ints', None)"


def test_the_services_the_server_offers(client: srvwire.sync.Client) -> None:
    assert client.connected
    assert dict(client.services) == {
        ADD: "example_interfaces/srv/AddTwoInts",
        "/together": "example_interfaces/srv/AddTwoInts",
        "/hang": "std_srvs/srv/Trigger",
    }
    assert [info.name for info in client.list_services()] == [ADD, "/hang", "/together"]
    assert client.wait_for_service("hang").type == "std_srvs/srv/Trigger"
    with pytest.raises(ServiceUnavailable, match=r"was not advertised within 0\.1 s"):
        client.wait_for_service("/not_there", timeout=0.1)


def test_errors_are_the_async_clients_classes(client: srvwire.sync.Client) -> None:
    with pytest.raises(ServiceNotFound) as not_found:
        client.call("/add_two_int", {"a": 1, "b": 2})
    assert not_found.value.service == "/add_two_int"
    assert not_found.value.data == {"candidates": [ADD]}
    with pytest.raises(InvalidParams, match="checked by the client; nothing was sent"):
        client.call(ADD, {"a": "one", "b": 2})
    with pytest.raises(TypeError, match="timeout must be a number of seconds, not str"):
        client.call(ADD, {"a": 1, "b": 2}, timeout="soon")


def test_a_deadline_against_a_handler_that_never_answers(
    client: srvwire.sync.Client, handlers: Handlers
) -> None:
    with pytest.raises(DeadlineExceeded) as exceeded:
        client.call("/hang", timeout=0.2)
    # The async client's deadline (or the server's, which got the time left with the call),
    # not the blocking wait's backstop.
    assert exceeded.value.message in {
        "no response within 0.2 s",
        "the deadline for /hang passed before the handler finished",
    }
    assert exceeded.value.service == "/hang"
    assert client.in_flight == 0
    assert client.call(ADD, {"a": 1, "b": 2}).sum == 3


def test_calls_from_several_threads_share_one_connection(
    client: srvwire.sync.Client, handlers: Handlers
) -> None:
    # /together answers only when THREADS calls wait in it at once: each thread's call is in
    # flight at the same time as the others', on the client's one connection.
    with concurrent.futures.ThreadPoolExecutor(THREADS) as pool:
        together = list(
            pool.map(lambda i: client.call("/together", {"a": i, "b": 1}).sum, range(THREADS))
        )
        sums = list(pool.map(lambda i: client.call(ADD, {"a": i, "b": i}).sum, range(200)))
    assert together == [1, 2, 3, 4]
    assert sums == [2 * i for i in range(200)]
    assert len(handlers.peers) == 1


def test_closing_fails_the_calls_other_threads_wait_on(
    client: srvwire.sync.Client, handlers: Handlers
) -> None:
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        pending = pool.submit(client.call, "/hang", timeout=scaled(30))
        assert handlers.hanging.wait(scaled(5))
        client.close()
        with pytest.raises(ConnectionLost, match=r"the client (was|is) closed"):
            pending.result(scaled(5))  # at once, not after the call's 30 s deadline
    assert client.closed
    with pytest.raises(ConnectionLost, match="the client is closed"):
        client.call(ADD, {"a": 1, "b": 2})
    client.close()  # idempotent
    assert repr(client).startswith("<srvwire.sync.Client closed to ws://127.0.0.1:")


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_call_fails_at_once_when_the_loop_thread_dies(
    client: srvwire.sync.Client, handlers: Handlers
) -> None:
    def die() -> None:
        raise SystemExit  # ends run_forever, and the thread, quietly

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        pending = pool.submit(client.call, "/hang", timeout=scaled(30))
        assert handlers.hanging.wait(scaled(5))
        client._loop.loop.call_soon_threadsafe(die)
        with pytest.raises(ConnectionLost, match="the client's event loop ended"):
            pending.result(scaled(5))
    client._loop.thread.join(scaled(5))
    with pytest.raises(ConnectionLost, match="the client's event loop ended"):
        client.call(ADD, {"a": 1, "b": 2})


def test_a_stuck_loop_cannot_make_a_call_wait_forever(client: srvwire.sync.Client) -> None:
    release = threading.Event()
    client._loop.loop.call_soon_threadsafe(release.wait)  # blocks the client's loop
    try:
        with pytest.raises(DeadlineExceeded) as exceeded:
            client.call(ADD, {"a": 1, "b": 2}, timeout=0.1)
        assert exceeded.value.message == (
            "no answer within 0.1 s: the client's event loop did not finish the call"
        )
    finally:
        release.set()
    assert client.call(ADD, {"a": 1, "b": 2}).sum == 3


def test_wait_for_service_on_a_stuck_loop_gives_up_as_its_timeout_says(
    client: srvwire.sync.Client,
) -> None:
    release = threading.Event()
    client._loop.loop.call_soon_threadsafe(release.wait)  # blocks the client's loop
    try:
        with pytest.raises(ServiceUnavailable) as unavailable:
            client.wait_for_service("/not_there", timeout=0.1)
        assert unavailable.value.message == (
            "/not_there was not advertised within 0.1 s: the client's event loop did not "
            "finish the wait"
        )
        assert unavailable.value.service == "/not_there"
    finally:
        release.set()
    assert client.wait_for_service(ADD).name == ADD


def test_ctrl_c_in_a_blocking_call_cancels_it_on_the_server(
    client: srvwire.sync.Client, handlers: Handlers
) -> None:
    # Ctrl-C once the handler runs, however long the call takes to reach it: bounded well
    # within the call's own deadline (30 s), so that the signal never lands after the call
    # ended, and not a guess of a few seconds, past which nothing would press and the call
    # would end at its deadline instead. Whether it pressed is kept, to say so if it did not.
    pressed = threading.Event()

    def press_ctrl_c() -> None:
        if handlers.hanging.wait(scaled(20)):
            pressed.set()
            # To the main thread, where the call waits, as a terminal's Ctrl-C reaches it: sent
            # to the process from this thread, the kernel may hand it to this thread instead,
            # whose handling does not wake the main thread's wait until the call's deadline.
            main = threading.main_thread().ident
            assert main is not None
            signal.pthread_kill(main, signal.SIGINT)

    presser = threading.Thread(target=press_ctrl_c)
    presser.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            try:
                client.call("/hang", timeout=scaled(30))
            except DeadlineExceeded:
                assert pressed.is_set(), "the /hang handler did not start within 20 s"
                raise
    finally:
        presser.join()
    assert handlers.hung_up.wait(scaled(5))  # the server was told: its handler was cancelled
    assert client.in_flight == 0
    assert client.call(ADD, {"a": 1, "b": 2}).sum == 3


def test_a_call_from_the_clients_own_loop_thread_is_refused(client: srvwire.sync.Client) -> None:
    outcome: concurrent.futures.Future[Any] = concurrent.futures.Future()

    def call_from_the_loop() -> None:
        try:
            outcome.set_result(client.call(ADD, {"a": 1, "b": 2}))
        except BaseException as exc:
            outcome.set_exception(exc)

    client._loop.loop.call_soon_threadsafe(call_from_the_loop)
    with pytest.raises(RuntimeError, match="would wait for itself; await the async client there"):
        outcome.result(scaled(5))


def test_a_blocking_call_from_a_thread_that_runs_an_event_loop(
    client: srvwire.sync.Client,
) -> None:
    # Jupyter's case: the caller's thread runs a loop, which the client's own does not need.
    async def main() -> int:
        response = client.call(ADD, {"a": 20, "b": 22})
        return int(response.sum)

    assert asyncio.run(main()) == 42


def test_the_reconnect_option(handlers: Handlers) -> None:
    port = free_port()
    with srvwire.sync.connect(
        f"ws://127.0.0.1:{port}", reconnect=True, timeout=scaled(10)
    ) as client:
        assert not client.connected  # nothing listens yet, and opening did not raise
        with served_in_a_thread(build_server(handlers), port):
            response = client.call(ADD, {"a": 1, "b": 2}, wait_for_ready=True)
            assert response.sum == 3


def test_a_server_that_is_not_there_leaves_no_thread_behind() -> None:
    before = client_threads()
    with pytest.raises(ServiceUnavailable, match=r"cannot connect to ws://127\.0\.0\.1:"):
        srvwire.sync.connect(f"ws://127.0.0.1:{free_port()}")
    assert client_threads() == before


def test_closing_ends_the_loop_thread(running: RunningServer) -> None:
    before = client_threads()
    with srvwire.sync.connect(running.url):
        assert client_threads() - before == {f"srvwire client of {running.url}"}
    assert client_threads() == before


def test_a_client_collected_unclosed_ends_its_loop_thread(running: RunningServer) -> None:
    before = client_threads()
    client = srvwire.sync.connect(running.url)
    assert client_threads() - before == {f"srvwire client of {running.url}"}
    del client  # no cycle holds it: collected here, which stops its loop and joins the thread
    assert client_threads() == before


def test_the_options_are_srvwire_connects() -> None:
    assert inspect.signature(srvwire.sync.connect) == inspect.signature(srvwire.connect)
    with pytest.raises(ValueError, match="http://localhost"):
        srvwire.sync.connect("http://localhost")
    with pytest.raises(TypeError, match="unexpected keyword argument 'retries'"):
        srvwire.sync.connect("ws://localhost:1", retries=3)


UNCLOSED = """
import sys
import srvwire.sync

client = srvwire.sync.connect(sys.argv[1])
print(client.call("/add_two_ints", {"a": 1, "b": 2}).sum)
"""


async def test_a_client_left_open_does_not_keep_the_process_alive() -> None:
    # A bare WebSocket peer that answers one call, to see how the connection ends.
    ended: asyncio.Future[tuple[int | None, str]] = asyncio.get_running_loop().create_future()

    async def handle(ws: ServerConnection) -> None:
        services = [{"name": ADD, "type": "example_interfaces/srv/AddTwoInts"}]
        await ws.send(
            json.dumps({"jsonrpc": "2.0", "method": "$/services", "params": {"services": services}})
        )
        async for text in ws:
            call = json.loads(text)
            await ws.send(json.dumps({"jsonrpc": "2.0", "id": call["id"], "result": {"sum": 3}}))
        ended.set_result((ws.close_code, ws.close_reason))

    async with ws_serve(handle, "127.0.0.1", 0) as peer:
        port = peer.sockets[0].getsockname()[1]
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-c",
            UNCLOSED,
            f"ws://127.0.0.1:{port}",
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        stdout, stderr = await asyncio.wait_for(process.communicate(), scaled(30))
        assert (process.returncode, stdout) == (0, b"3\n"), stderr
        # At exit the client's loop was stopped, which closed its connection properly.
        code = await asyncio.wait_for(ended, scaled(5))
    assert code == (1001, "the client's event loop ended")


# --- the async client and event loops -------------------------------------------------------


def test_asyncio_run_of_connect_opens_a_client_that_ends_with_its_loop(
    running: RunningServer,
) -> None:
    client = asyncio.run(srvwire.connect(running.url))
    assert isinstance(client, srvwire.Client)
    assert not client.connected  # asyncio.run ended the loop, and the connection with it
    with pytest.raises(RuntimeError) as used_again:
        asyncio.run(client.call(ADD, {"a": 1, "b": 2}))
    assert str(used_again.value) == (
        "this client was opened in an event loop that has ended (asyncio.run() ends its loop "
        "when it returns): open the client in the coroutine that uses it, with "
        "'async with srvwire.connect(url) as client', or use srvwire.sync.connect(url) from "
        "blocking code"
    )
    del client
    gc.collect()  # a socket left open would warn here, and filterwarnings makes that an error


def test_a_runner_keeps_the_client_between_its_runs(running: RunningServer) -> None:
    with asyncio.Runner() as runner:
        client = runner.run(srvwire.connect(running.url))
        assert runner.run(client.call(ADD, {"a": 1, "b": 2})).sum == 3
        runner.run(client.close())


def test_a_client_used_from_another_event_loop_says_so(running: RunningServer) -> None:
    with asyncio.Runner() as runner:
        client = runner.run(srvwire.connect(running.url))
        try:
            with pytest.raises(RuntimeError) as elsewhere:
                asyncio.run(client.call(ADD, {"a": 1, "b": 2}))
            assert str(elsewhere.value) == (
                "this client belongs to another event loop: call it from the loop it was "
                "opened in, or use srvwire.sync.connect(url), which any thread can call"
            )
            assert runner.run(client.call(ADD, {"a": 1, "b": 2})).sum == 3  # nothing was sent
        finally:
            runner.run(client.close())


async def test_connect_is_still_awaited_as_before(running: RunningServer) -> None:
    one, two = await asyncio.gather(srvwire.connect(running.url), srvwire.connect(running.url))
    opened = await asyncio.wait_for(srvwire.connect(running.url), scaled(5))
    task = asyncio.create_task(srvwire.connect(running.url))
    for client in (one, two, opened, await task):
        async with client:
            assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
    assert asyncio.iscoroutine(srvwire.connect(running.url))


# --- goals ------------------------------------------------------------------------------------


def test_a_goal_with_feedback_result_and_cancel() -> None:
    fibonacci = srvwire.load_action("example_interfaces/action/Fibonacci")
    server = Server(grace_period=0)

    @server.action("/fibonacci", fibonacci)
    async def run(goal: Any, handle: srvwire.GoalHandle) -> Any:
        sequence = [0, 1]
        for _ in range(goal.order - 1):
            sequence.append(sequence[-1] + sequence[-2])
            await handle.feedback({"sequence": sequence})  # returns once it went out
        if goal.order > 10:  # a long one: until cancelled
            await handle.cancelled()
        return {"sequence": sequence}

    with (
        served_in_a_thread(server) as running,
        srvwire.sync.connect(running.url, timeout=scaled(5)) as client,
    ):
        goal = client.send_goal("/fibonacci", {"order": 4})
        assert len(goal.goal_id or "") == 36
        seen = [fb.sequence for fb in goal.feedback()]
        assert seen[-1] == [0, 1, 1, 2, 3]  # the last one went out before the result
        assert goal.result() == srvwire.GoalResult(
            "succeeded", fibonacci.Result(sequence=[0, 1, 1, 2, 3])
        )
        assert goal.status == "succeeded"

        long = client.send_goal("/fibonacci", {"order": 11})
        first = next(long.feedback())  # the latest when it is read
        assert first.sequence[:3] == [0, 1, 1]
        assert long.cancel() is True
        outcome = long.result()
        assert outcome.status == "canceled" and len(outcome.result.sequence) == 12


# --- topics -----------------------------------------------------------------------------------

JointState = srvwire.load_message("sensor_msgs/msg/JointState")


class Robot:
    """A server with a topic, kept for late subscribers, and services that act on it from
    the server's loop: what the blocking client's topic tests talk to."""

    def __init__(self) -> None:
        self.server = Server(grace_period=0)
        self.received: list[Any] = []  # what clients published, in order
        self.notified = threading.Event()
        self.joints = self.server.topic(
            "/joint_states", JointState, qos={"durability": "transient_local"}
        )
        self.server.subscription("/joint_states", JointState)(self.received.append)
        self.server.add_service(ADD, AddTwoInts, self.add)
        self.server.add_service("/publish_three", Trigger, self.publish_three)
        self.server.add_service("/remove_topic", Trigger, self.remove_topic)

    async def add(self, request: Any) -> Any:
        self.notified.set()
        return {"sum": request.a + request.b}

    async def publish_three(self, request: Any) -> Any:
        for n in range(3):
            self.joints.publish(JointState(name=["elbow"], position=[float(n)]))
        return {"success": True}

    async def remove_topic(self, request: Any) -> Any:
        self.server.remove_topic("/joint_states")
        return {"success": True}


@pytest.fixture
def robot() -> Iterator[tuple[Robot, srvwire.sync.Client]]:
    robot = Robot()
    with (
        served_in_a_thread(robot.server) as running,
        srvwire.sync.connect(running.url, timeout=scaled(5)) as client,
    ):
        yield robot, client


def settled(client: srvwire.sync.Client) -> None:
    """Return once the server read what the client sent before: a call after it is answered."""
    assert client.call(ADD, {"a": 1, "b": 1}).sum == 2


def test_a_subscription_is_a_plain_iterator_that_ends_when_the_loop_is_left(
    robot: tuple[Robot, srvwire.sync.Client],
) -> None:
    server, client = robot
    info = client.wait_for_topic("/joint_states")
    assert (info.name, info.type, info.publish) == (
        "/joint_states",
        "sensor_msgs/msg/JointState",
        True,
    )
    assert client.topics == {"/joint_states": "sensor_msgs/msg/JointState"}
    assert [t.name for t in client.list_topics()] == ["/joint_states"]
    client.call("/publish_three")  # kept for late subscribers (transient_local)
    positions = []
    for msg in client.subscribe("/joint_states", JointState):
        assert type(msg) is JointState  # typed, and so for a type checker
        positions.append(msg.position)
        if len(positions) == 3:
            assert server.joints.subscription_count == 1
            break
    assert positions == [[0.0], [1.0], [2.0]]
    settled(client)
    assert server.joints.subscription_count == 0  # leaving the loop ended it on the server


def test_a_subscription_as_a_context_manager_with_a_timeout_per_message(
    robot: tuple[Robot, srvwire.sync.Client],
) -> None:
    server, client = robot
    with client.subscribe("joint_states") as sub:  # typed by the server's announcement
        assert sub.active and server.joints.subscription_count == 1
        with pytest.raises(DeadlineExceeded) as caught:
            sub.get(timeout=scaled(0.1))  # nothing published yet: give up, and go on
        assert isinstance(caught.value, TimeoutError) and caught.value.service == "/joint_states"
        client.call("/publish_three")
        first = next(sub)
        assert type(first).__name__ == "JointState" and first.position == [0.0]
        for msg in sub:  # leaving this loop keeps the subscription: the block holds it
            assert msg.position == [1.0]
            break
        assert sub.active
        assert sub.get(timeout=scaled(5)).position == [2.0] and sub.seq == 3
    assert not sub.active
    with pytest.raises(StopIteration):
        next(sub)
    settled(client)
    assert server.joints.subscription_count == 0
    quiet = client.subscribe("/joint_states", message_timeout=scaled(0.1)).start()
    assert [next(quiet).position for _ in range(3)] == [[0.0], [1.0], [2.0]]  # the stored ones
    with pytest.raises(DeadlineExceeded):
        next(quiet)  # the subscription's own timeout per message
    client.call("/remove_topic")
    with pytest.raises(ServiceNotFound) as removed:  # the error that ended it, as async
        next(quiet)
    assert removed.value.message == "the topic /joint_states was removed"


def test_a_subscription_with_a_duration_ends_with_deadline_exceeded(
    robot: tuple[Robot, srvwire.sync.Client],
) -> None:
    server, client = robot
    with client.subscribe("/joint_states", JointState, duration=0.25) as sub:
        assert server.joints.subscription_count == 1
        with pytest.raises(DeadlineExceeded) as caught:
            for _ in sub:  # whatever is stored, then the end the server sent
                pass
        assert caught.value.message == (
            "the subscription to /joint_states reached its deadline (0.25 s)"
        )
        assert not sub.active
    settled(client)
    assert server.joints.subscription_count == 0


def test_a_subscription_iterated_in_another_thread_and_closed_from_this_one(
    robot: tuple[Robot, srvwire.sync.Client],
) -> None:
    server, client = robot
    with client.subscribe("/joint_states", JointState) as sub:
        three = threading.Event()

        def read() -> list[list[float]]:
            seen = []
            for msg in sub:  # ends when the subscription is closed
                seen.append(msg.position)
                if len(seen) == 3:
                    three.set()
            return seen

        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            reading = pool.submit(read)
            client.call("/publish_three")
            assert three.wait(scaled(5))  # the reader waits for a fourth now
            sub.close()  # from this thread: the reader's loop ends
            assert reading.result(scaled(5)) == [[0.0], [1.0], [2.0]]
    settled(client)
    assert server.joints.subscription_count == 0


def test_publish_with_and_without_an_ack_and_notify(
    robot: tuple[Robot, srvwire.sync.Client],
) -> None:
    server, client = robot
    client.publish("/joint_states", {"name": ["wrist"], "position": [0.5]}, ack=True)
    assert [m.name for m in server.received] == [["wrist"]]  # taken once it returns
    client.publish("/joint_states", JointState(name=["elbow"], position=[1.5]))
    settled(client)
    assert [m.name for m in server.received] == [["wrist"], ["elbow"]]
    with pytest.raises(InvalidParams) as caught:  # refused here, before sending
        client.publish("/joint_states", {"position": ["high"]}, ack=True)
    assert caught.value.data["errors"][0]["path"] == "message.position[0]"
    with pytest.raises(ServiceNotFound):  # refused by the server
        client.publish("/no_such_topic", {"name": ["x"]}, msg_type=JointState, ack=True)
    assert len(server.received) == 2
    server.notified.clear()
    assert client.notify(ADD, {"a": 1, "b": 2}) is None  # nothing comes back
    assert server.notified.wait(scaled(5))  # yet the handler ran
    with pytest.raises(InvalidParams):  # typed and validated as a call is
        client.notify(ADD, {"a": "one"})


def test_a_goals_result_waited_for_a_while_then_cancelled() -> None:
    fibonacci = srvwire.load_action("example_interfaces/action/Fibonacci")
    server = Server(grace_period=0)

    @server.action("/fibonacci", fibonacci)
    async def run(goal: Any, handle: srvwire.GoalHandle) -> Any:
        await handle.feedback({"sequence": [0, 1]})
        await handle.cancelled()  # only a cancel ends it
        return {"sequence": [0, 1]}

    with (
        served_in_a_thread(server) as running,
        srvwire.sync.connect(running.url, timeout=scaled(5)) as client,
    ):
        goal = client.send_goal("/fibonacci", {"order": 3})
        assert next(goal.feedback()).sequence == [0, 1]
        with pytest.raises(DeadlineExceeded) as caught:
            goal.result(timeout=scaled(0.1))
        assert caught.value.service == "/fibonacci"
        assert goal.status == "executing" and not goal.done  # it goes on
        assert goal.cancel() is True
        assert goal.result(timeout=scaled(5)) == srvwire.GoalResult(
            "canceled", fibonacci.Result(sequence=[0, 1])
        )
        assert goal.done and goal.cancel() is False


def test_a_subscription_left_on_the_clients_own_loop_thread_still_ends(
    robot: tuple[Robot, srvwire.sync.Client],
) -> None:
    server, client = robot
    client.call("/publish_three")
    messages = iter(client.subscribe("/joint_states"))
    assert next(messages).position == [0.0]
    assert server.joints.subscription_count == 1

    async def collected_there() -> None:
        messages.close()  # as when the loop thread collects it: it cannot wait for itself
        await asyncio.gather(*client._client._background)  # the close it handed over

    client._loop.run(collected_there(), scaled(5))
    settled(client)
    assert server.joints.subscription_count == 0


# --- Ctrl-C while a goal runs -------------------------------------------------------------

# A script with a blocking client that presses Ctrl-C on itself (a real SIGINT) while
# result() or feedback() waits, outside a `with` block, or elsewhere in a `with` block. It
# knows the wait began when the client's loop starts the goal's coroutine (a SIGINT sent when
# the server's handler started could reach the script before it entered the wait), and sends
# the signal to the main thread, as a terminal's Ctrl-C reaches it. It prints
# the goal's status once KeyboardInterrupt reached it: "canceled" when the goal's outcome
# arrived, "executing" or "aborted" when the connection closed first.
GOAL_SCRIPT = """
import signal, sys, threading
import srvwire.sync
from srvwire.actions import ClientGoal

url, where = sys.argv[1], sys.argv[2]
waiting = threading.Event()
result, feedback = ClientGoal.result, ClientGoal.feedback

async def result_noticed(self):
    waiting.set()
    return await result(self)

async def feedback_noticed(self):
    waiting.set()
    async for item in feedback(self):
        yield item

ClientGoal.result, ClientGoal.feedback = result_noticed, feedback_noticed

def press_ctrl_c():
    waiting.wait()
    signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

if where != "with":
    threading.Thread(target=press_ctrl_c, daemon=True).start()
client = srvwire.sync.connect(url, timeout=600)
try:
    if where == "with":
        with client:
            goal = client.send_goal("/patient", {"order": 1})
            print("accepted", flush=True)
            signal.raise_signal(signal.SIGINT)  # Ctrl-C while the program does its own work
    goal = client.send_goal("/patient", {"order": 1})
    print("accepted", flush=True)
    if where == "result":
        goal.result()
    else:
        for item in goal.feedback():
            pass
except KeyboardInterrupt:
    print("interrupted:", goal.status, flush=True)
finally:
    client.close()
"""


@pytest.mark.parametrize("where", ["result", "feedback", "with"])
def test_ctrl_c_asks_the_server_to_cancel_a_goal_before_the_connection_closes(where: str) -> None:
    with serve_goal_server() as (url, served):
        process = start_interruptible("-c", GOAL_SCRIPT, url, where)
        assert process.stdout is not None and process.stderr is not None
        out = Lines(process.stdout)
        try:
            served.expect("started 1")
            served.expect("cancel requested 1")  # the handler was asked, not cut
            out.expect("interrupted:")
            code = process.wait(timeout=scaled(60))
        finally:
            process.kill()
            process.wait()
            printed = out.close()
            err = process.stderr.read()
            process.stderr.close()
        assert (code, err) == (0, "")
        assert printed == "accepted\ninterrupted: canceled\n"


async def test_ctrl_c_waits_for_a_goal_cancelled_already_without_asking_again() -> None:
    # What a Ctrl-C does to the goals still running: each not yet cancelled is asked once, and
    # every one of them, the ones cancelled already by the program included, is waited for.
    class Goal:
        def __init__(self, done: bool, cancel_sent: bool) -> None:
            self.done, self.cancel_sent = done, cancel_sent
            self.asked = self.waited = 0

        async def cancel(self) -> None:
            self.asked += 1
            self.cancel_sent = True

        async def result(self) -> None:
            self.waited += 1

    running, cancelled, finished = Goal(False, False), Goal(False, True), Goal(True, False)
    await srvwire.sync._cancel_and_wait([running, cancelled, finished])  # type: ignore[list-item]
    assert [(goal.asked, goal.waited) for goal in (running, cancelled, finished)] == [
        (1, 1), (0, 1), (0, 0)
    ]  # fmt: skip


@pytest.mark.parametrize("transport", ["websockets", "picows"])
def test_calls_handed_to_the_loop_as_close_ends_it_fail_at_once(
    running: RunningServer, transport: str
) -> None:
    # The loop thread is held after its last sweep of tasks, before it closes the loop: the
    # moment a call from another thread could be handed over and dropped with the loop.
    client = srvwire.sync.connect(running.url, timeout=scaled(30), transport=transport)
    assert client.call(ADD, {"a": 1, "b": 2}).sum == 3
    loop = client._loop.loop
    held, go_on = threading.Event(), threading.Event()
    ending = loop.shutdown_asyncgens

    async def hold() -> None:
        held.set()
        go_on.wait(scaled(30))
        await ending()

    loop.shutdown_asyncgens = hold  # type: ignore[method-assign]
    with concurrent.futures.ThreadPoolExecutor(THREADS * 2) as pool:
        closing = pool.submit(client.close)
        try:
            assert held.wait(scaled(10))
            calls = [pool.submit(client.call, ADD, {"a": i, "b": 1}) for i in range(THREADS * 20)]
            # At once, while the loop thread is still held: not at the calls' 30 s deadline.
            _, waiting = concurrent.futures.wait(calls, timeout=scaled(5))
        finally:
            go_on.set()
        assert not waiting
        for call in calls:
            with pytest.raises(ConnectionLost, match="the client is closed"):
                call.result()
        closing.result(scaled(10))
    assert not client._loop.running


# A script whose blocking client waits for a goal whose handler goes on after its cancellation
# (order 2), in a `with` block: Ctrl-C while result() waits, and a second one while the client
# waits for the cancelled goal's outcome. It prints "waiting for the cancelled goals" each time
# the client begins that wait.
SECOND_CTRL_C_SCRIPT = """
import signal, sys, threading
import srvwire.sync
from srvwire.actions import ClientGoal

url = sys.argv[1]
waiting, stopping = threading.Event(), threading.Event()
result, cancel_and_wait = ClientGoal.result, srvwire.sync._cancel_and_wait

async def result_noticed(self):
    waiting.set()
    return await result(self)

async def cancel_and_wait_noticed(handles):
    print("waiting for the cancelled goals", flush=True)
    stopping.set()
    await cancel_and_wait(handles)

ClientGoal.result, srvwire.sync._cancel_and_wait = result_noticed, cancel_and_wait_noticed

def press_ctrl_c_twice():
    for event in (waiting, stopping):
        event.wait()
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

threading.Thread(target=press_ctrl_c_twice, daemon=True).start()
try:
    with srvwire.sync.connect(url, timeout=600) as client:
        goal = client.send_goal("/patient", {"order": 2})
        print("accepted", flush=True)
        goal.result()
except KeyboardInterrupt:
    print("interrupted", flush=True)
"""


def test_a_second_ctrl_c_ends_the_wait_for_a_cancelled_goal_and_the_exit_does_not_wait_again() -> (
    None
):
    with serve_goal_server() as (url, served):
        process = start_interruptible("-c", SECOND_CTRL_C_SCRIPT, url)
        assert process.stdout is not None and process.stderr is not None
        out = Lines(process.stdout)
        try:
            served.expect("started 2")
            served.expect("cancel requested 2")  # asked; it goes on for its 60 s cancel_grace
            code = process.wait(timeout=scaled(30))
        finally:
            process.kill()
            process.wait()
            printed = out.close()
            err = process.stderr.read()
            process.stderr.close()
        assert code == 0, err
        # The goal still running when the connection closed is failed, and said so.
        assert err.endswith("the client was closed; failing 1 pending calls\n"), err
        assert "Traceback" not in err
        assert printed == "accepted\nwaiting for the cancelled goals\ninterrupted\n"
