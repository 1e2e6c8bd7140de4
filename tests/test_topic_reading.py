"""How a subscriber reads ``$/message``, through a real connection to a scripted server.

The scripted peer (:class:`test_client.FakePeer`) answers ``$/subscribe`` with ``$/subscribed``
and then sends what each test writes: as a srvwire server writes a message (recognised by its
opening and validated in one pass), written otherwise (parsed in full), or what a srvwire server
never sends. Either way the subscriber gets the same typed messages, the same sequence numbers
and gaps, and the same errors.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from websockets.asyncio.server import ServerConnection

from srvwire.client import Client, Subscription, connect
from srvwire.errors import ConnectionLost, InternalError, ResourceExhausted
from srvwire.loader import load_message
from support import scaled
from test_client import FakePeer, Reply, answer_add

String = load_message("std_msgs/msg/String")

Write = Callable[[int], str]
"""One message from the server, written for the subscription with the given id."""


def message(seq: int, text: str = '{"data":"x"}', dropped: int = 0, after: str = "") -> Write:
    """A ``$/message`` as a srvwire server writes it; ``after``: more members after the message."""
    return lambda id: (
        f'{{"jsonrpc":"2.0","method":"$/message","params":{{"subscription":{id},"seq":{seq},'
        f'"dropped":{dropped},"message":{text}{after}}}}}'
    )


def written_otherwise(seq: int, text: str = '{"data":"x"}', dropped: int | None = 0) -> Write:
    """The same message written by another JSON writer: blanks, members in another order."""

    def write(id: int) -> str:
        params: dict[str, Any] = {"message": json.loads(text), "seq": seq, "subscription": id}
        if dropped is not None:
            params["dropped"] = dropped
        return json.dumps({"params": params, "method": "$/message", "jsonrpc": "2.0"})

    return write


def serving(*writes: Write, depth: int = 10, reliability: str = "reliable") -> Reply:
    """Answer ``$/subscribe`` with ``$/subscribed`` (granting ``depth`` and ``reliability``)
    and ``writes``; AddTwoInts calls as usual."""

    async def reply(ws: ServerConnection, request: dict[str, Any]) -> None:
        if request.get("method") != "$/subscribe":
            await answer_add(ws, request)
            return
        id = request["id"]
        granted = {
            "subscription": id,
            "topic": request["params"]["topic"],
            "seq": 0,
            "depth": depth,
            "reliability": reliability,
            "durability": "volatile",
        }
        await ws.send(json.dumps({"jsonrpc": "2.0", "method": "$/subscribed", "params": granted}))
        for write in writes:
            await ws.send(write(id))

    return reply


@pytest.fixture
async def peer() -> AsyncIterator[FakePeer]:
    fake = FakePeer()
    await fake.start()
    yield fake
    await fake.stop()


@pytest.fixture
async def client(peer: FakePeer) -> AsyncIterator[Client]:
    async with connect(peer.url, timeout=scaled(5)) as opened:
        yield opened


async def received(sub: Subscription, count: int) -> list[tuple[str, int | None, int]]:
    """The next ``count`` messages' data, with the ``seq`` and ``missed`` of each."""
    got = []
    for _ in range(count):
        msg = await sub.receive()
        assert type(msg) is String
        got.append((msg.data, sub.seq, sub.missed))
    return got


async def test_messages_as_srvwire_servers_write_them_arrive_typed(
    peer: FakePeer, client: Client
) -> None:
    peer.reply = serving(*(message(n, f'{{"data":"{n}"}}') for n in (1, 2, 3)))
    async with client.subscribe("/chatter", String) as sub:
        assert await received(sub, 3) == [("1", 1, 0), ("2", 2, 0), ("3", 3, 0)]
        assert sub.dropped == 0


async def test_messages_written_otherwise_or_with_more_members_arrive_alike(
    peer: FakePeer, client: Client
) -> None:
    peer.reply = serving(
        message(1, '{"data":"plain"}'),
        message(2, '{"data":"noted"}', after=',"note":"read by the full parse only"'),
        written_otherwise(3, '{"data":"blanks"}'),
        written_otherwise(4, '{"data":"no dropped"}', dropped=None),
        message(5, '{"data":"first"}', after=',"message":{"data":"last"}'),  # the last counts
        message(6, '{"data": "blank inside"}'),
    )
    async with client.subscribe("/chatter", String) as sub:
        assert await received(sub, 6) == [
            ("plain", 1, 0),
            ("noted", 2, 0),
            ("blanks", 3, 0),
            ("no dropped", 4, 0),
            ("last", 5, 0),
            ("blank inside", 6, 0),
        ]
        assert sub.dropped == 0


async def test_gaps_in_the_sequence_are_reported_and_repeats_skipped(
    peer: FakePeer, client: Client
) -> None:
    peer.reply = serving(
        message(3, '{"data":"a"}', dropped=2),  # the first: its own count of what was dropped
        message(4, '{"data":"b"}'),
        written_otherwise(7, '{"data":"c"}', dropped=2),  # seq says 2 were missed
        message(10, '{"data":"d"}', dropped=2),
        message(10, '{"data":"again"}'),  # seen already: skipped
        message(9, '{"data":"older"}'),  # seen already: skipped
        message(11, '{"data":"e"}'),
    )
    async with client.subscribe("/chatter", String) as sub:
        assert await received(sub, 5) == [
            ("a", 3, 2),
            ("b", 4, 0),
            ("c", 7, 2),
            ("d", 10, 2),
            ("e", 11, 0),
        ]
        assert sub.dropped == 6


@pytest.mark.parametrize(
    ("depth", "kept"),
    [
        (1, [("5", 5, 4)]),
        (2, [("4", 4, 3), ("5", 5, 0)]),
        (4, [("2", 2, 1), ("3", 3, 0), ("4", 4, 0), ("5", 5, 0)]),
    ],
)
async def test_a_best_effort_subscriber_that_falls_behind_loses_the_oldest_and_is_told(
    peer: FakePeer, client: Client, depth: int, kept: list[tuple[str, int, int]]
) -> None:
    writes = (message(n, f'{{"data":"{n}"}}') for n in range(1, 6))
    peer.reply = serving(*writes, depth=depth, reliability="best_effort")
    async with client.subscribe("/chatter", String) as sub:
        # The reply comes after the five messages on the one connection: all are in by then.
        assert (await client.call("/add_two_ints", {"a": 1, "b": 1})).sum == 2
        # Each kept message says how many were missed just before it (the first: since the
        # subscription started), as the sequence numbers show.
        assert await received(sub, depth) == kept
        assert sub.dropped == 5 - depth


async def test_a_reliable_subscriber_that_falls_behind_is_ended(
    peer: FakePeer, client: Client
) -> None:
    peer.reply = serving(*(message(n, f'{{"data":"{n}"}}') for n in range(1, 6)), depth=2)
    async with client.subscribe("/chatter", String) as sub:
        assert (await client.call("/add_two_ints", {"a": 1, "b": 1})).sum == 2
        assert await received(sub, 2) == [("1", 1, 0), ("2", 2, 0)]  # what it had
        with pytest.raises(ResourceExhausted) as caught:
            await sub.receive()
        subscribe = await peer.next("$/subscribe")
        assert (await peer.next("$/cancel"))["params"] == {"id": subscribe["id"]}
    assert caught.value.message == (
        "this subscriber to /chatter did not keep up: its queue of 2 messages was full while "
        "the code reading it was busy elsewhere, and the subscription is reliable; take each "
        "message as it comes, or subscribe with a larger depth, or best_effort to drop the "
        "oldest instead"
    )
    assert caught.value.data == {"depth": 2, "seq": 3}


@pytest.mark.parametrize("write", [message, written_otherwise], ids=["recognised", "parsed"])
async def test_a_message_that_does_not_fit_its_type_ends_the_subscription_with_its_path(
    peer: FakePeer, client: Client, write: Callable[..., Write]
) -> None:
    peer.reply = serving(message(1, '{"data":"fits"}'), write(2, '{"data": 5}'))
    async with client.subscribe("/chatter", String) as sub:
        assert (await sub.receive()).data == "fits"
        with pytest.raises(InternalError) as caught:
            await sub.receive()
        subscribe = await peer.next("$/subscribe")
        cancel = await peer.next("$/cancel")  # the server is told to stop sending
    error = caught.value
    assert error.service == "/chatter"
    assert error.message.startswith(
        "a message on /chatter does not match its type: 1 validation error for String\n"
        "data\n  Input should be a valid string [type=string_type, input_value=5, "
        "input_type=int]"
    ), error.message
    assert cancel["params"] == {"id": subscribe["id"]}
    assert not sub.active
    # The connection carries on.
    assert (await client.call("/add_two_ints", {"a": 1, "b": 2})).sum == 3


@pytest.mark.parametrize(
    ("after", "reason"),
    [
        (" and more", "Parse error"),
        (',"seq":5', "'subscription', 'seq' or 'dropped' given twice"),
        (',"subscription":999', "'subscription', 'seq' or 'dropped' given twice"),
        (',"seq":"5"', "needs integers 'seq' and 'dropped'"),
    ],
)
async def test_a_message_that_is_not_what_its_opening_says_fails_the_connection(
    peer: FakePeer, client: Client, after: str, reason: str
) -> None:
    peer.reply = serving(message(1), message(7, after=after))
    async with client.subscribe("/chatter", String) as sub:
        assert (await sub.receive()).data == "x"
        with pytest.raises(ConnectionLost) as caught:
            await sub.receive()
    assert caught.value.message.startswith("the server broke the protocol: ")
    assert reason in caught.value.message
    assert caught.value.data["close_code"] == 1008
    # The broken message was received by nobody: the sequence count does not move for it,
    # so that a replay after reconnecting is not skipped as seen, nor a gap invented.
    assert (sub.gaps.last, sub.gaps.missed) == (1, 0)
    ws = peer.connections[0]
    await ws.wait_closed()
    assert ws.close_code == 1008
    assert not client.connected


async def test_after_a_message_that_breaks_the_protocol_no_other_subscription_gets_one(
    peer: FakePeer, client: Client
) -> None:
    # Both subscriptions' messages come on one connection, the broken one first: what follows
    # it on a connection that failed is not handed to anyone, however soon it arrives.
    ids: list[int] = []

    async def reply(ws: ServerConnection, request: dict[str, Any]) -> None:
        if request.get("method") != "$/subscribe":
            return
        ids.append(request["id"])
        granted = {"subscription": request["id"], "seq": 0, "depth": 10}
        await ws.send(json.dumps({"jsonrpc": "2.0", "method": "$/subscribed", "params": granted}))
        if len(ids) == 2:
            await ws.send(message(1, after=" and more")(ids[0]))  # found by the subscription
            await ws.send(message(1)(ids[1]))

    peer.reply = reply
    first = client.subscribe("/first", String)
    second = client.subscribe("/second", String)
    await first.start()
    await second.start()
    for sub in (first, second):
        with pytest.raises(ConnectionLost) as caught:
            await sub.receive()
        assert "the server broke the protocol" in caught.value.message
