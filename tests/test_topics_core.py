"""The rules of topics without I/O: QoS, sequence numbers, the outbox's order and bounds."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given, settings, strategies as st

from srvwire.errors import InvalidParams
from srvwire.session import RefusedMessage, ServerSession
from srvwire.topics import Gaps, Outbox, QoS, Topic, TopicBoard


class Entry:
    type_name = "std_msgs/msg/String"


class NoServices:
    def get(self, name: str) -> None:
        return None

    def resolve(self, name: str) -> Any:
        raise AssertionError(name)

    def services(self, scopes: Any = None) -> list[tuple[str, str]]:
        return []

    def discover_json(self, scopes: Any = None) -> str:
        return "{}"


DEFAULT = QoS()


def topic(name: str = "/chatter", qos: QoS = DEFAULT, **options: Any) -> Topic[Entry]:
    return Topic(name, Entry(), qos, **options)


def drain(outbox: Outbox) -> list[Any]:
    """Everything the outbox has to write, parsed."""
    messages = []
    while (data := outbox.next()) is not None:
        messages.append(json.loads(data))
    return messages


def data(n: int) -> bytes:
    """Message ``n``: the same size for every ``n`` under 10 000."""
    return json.dumps({"data": f"{n:04d}"}).encode()


# --- QoS -----------------------------------------------------------------------------------------


def test_the_defaults_are_ros_defaults() -> None:
    assert QoS().to_json() == {"depth": 10, "reliability": "reliable", "durability": "volatile"}


@pytest.mark.parametrize(
    ("settings_", "error"),
    [
        ({"depth": 0}, "depth must be an integer from 1 to 10000, not 0"),
        ({"reliability": "sometimes"}, "reliability must be 'reliable' or 'best_effort'"),
        ({"durability": "forever"}, "durability must be 'volatile' or 'transient_local'"),
    ],
)
def test_a_bad_qos_says_what_is_wrong(settings_: dict[str, Any], error: str) -> None:
    with pytest.raises(ValueError, match=error):
        QoS(**settings_)


@pytest.mark.parametrize(
    ("asked", "path"),
    [
        ({"depth": "5"}, "qos.depth"),
        ({"depth": 0}, "qos.depth"),
        ({"reliability": 1}, "qos.reliability"),
        ({"durability": "x"}, "qos.durability"),
        ({"history": "keep_all"}, "qos.history"),
        ([], "qos"),
    ],
)
def test_a_subscriber_asking_for_a_bad_qos_gets_the_field_path(asked: Any, path: str) -> None:
    with pytest.raises(InvalidParams) as caught:
        QoS().grant(asked)
    assert caught.value.data["errors"][0]["path"] == path


def test_a_volatile_topic_grants_no_history() -> None:
    granted = QoS(durability="volatile").grant({"durability": "transient_local", "depth": 3})
    assert granted == QoS(depth=3, reliability="reliable", durability="volatile")
    kept = QoS(durability="transient_local").grant({"reliability": "best_effort"})
    assert kept == QoS(depth=10, reliability="best_effort", durability="transient_local")


# --- the outbox ----------------------------------------------------------------------------------


def test_subscribed_comes_before_the_messages_and_a_message_is_written_once() -> None:
    chatter = topic()
    first, second = Outbox(), Outbox()
    first.subscribe(1, chatter, QoS())
    second.subscribe("a", chatter, QoS())
    shared = data(1)
    assert chatter.publish(shared) == 2
    assert chatter.history.maxlen == 0  # volatile: nothing kept
    assert first.subscriptions[1].queue[0][1] is shared
    assert second.subscriptions["a"].queue[0][1] is shared
    assert drain(first) == [
        {
            "jsonrpc": "2.0",
            "method": "$/subscribed",
            "params": {
                "subscription": 1,
                "topic": "/chatter",
                "seq": 0,
                "epoch": chatter.epoch,
                "depth": 10,
                "reliability": "reliable",
                "durability": "volatile",
            },
        },
        {
            "jsonrpc": "2.0",
            "method": "$/message",
            "params": {"subscription": 1, "seq": 1, "dropped": 0, "message": {"data": "0001"}},
        },
    ]
    assert [m["params"]["subscription"] for m in drain(second)] == ["a", "a"]


def test_control_goes_ahead_of_queued_data() -> None:
    chatter = topic()
    outbox = Outbox()
    outbox.subscribe(1, chatter, QoS())
    drain(outbox)
    chatter.publish(data(1))
    outbox.push(b'{"jsonrpc":"2.0","id":5,"result":null}')
    assert [m.get("id", m.get("method")) for m in drain(outbox)] == [5, "$/message"]


def test_subscriptions_take_turns() -> None:
    flooded, quiet = topic("/flooded"), topic("/quiet")
    outbox = Outbox()
    outbox.subscribe(1, flooded, QoS(depth=100))
    outbox.subscribe(2, quiet, QoS())
    drain(outbox)
    for n in range(50):
        flooded.publish(data(n))
    quiet.publish(data(999))
    order = [m["params"]["subscription"] for m in drain(outbox)]
    assert order[:3] == [1, 2, 1]  # the quiet topic's message is second, not 51st
    assert len(order) == 51


def test_best_effort_drops_the_oldest_and_says_how_many() -> None:
    chatter = topic(qos=QoS(depth=3, reliability="best_effort"))
    outbox = Outbox()
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    for n in range(1, 8):
        chatter.publish(data(n))
    messages = [m["params"] for m in drain(outbox)]
    assert [(m["seq"], m["dropped"]) for m in messages] == [(5, 4), (6, 0), (7, 0)]


def test_reliable_ends_a_subscriber_that_cannot_keep_up() -> None:
    chatter = topic(qos=QoS(depth=2))
    outbox = Outbox()
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    assert chatter.publish(data(1)) == 1
    assert chatter.publish(data(2)) == 1
    assert chatter.publish(data(3)) == 0  # ended, not reached
    assert not chatter.subscriptions and not outbox.subscriptions
    assert outbox.queued == 0
    [ended] = drain(outbox)
    assert ended["id"] == 1
    assert ended["error"]["data"]["status"] == "RESOURCE_EXHAUSTED"
    assert ended["error"]["message"].startswith(
        "the subscriber to /chatter did not keep up: its queue of 2 messages"
    )


@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
def test_depth_bounds_a_queue_only_while_the_connection_takes_no_more(reliability: str) -> None:
    writable = True
    chatter = topic(qos=QoS(depth=3, reliability=reliability))
    outbox = Outbox(writable=lambda: writable)
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    # A burst while the connection takes more: queued whole, whatever the depth.
    assert [chatter.publish(data(n)) for n in range(1, 11)] == [1] * 10
    assert len(outbox.subscriptions[1].queue) == 10
    assert [m["params"]["seq"] for m in drain(outbox)] == list(range(1, 11))
    for n in range(11, 16):  # five more wait for the writer's turn...
        chatter.publish(data(n))
    writable = False  # ...when the connection congests: the peer stopped reading
    chatter.publish(data(16))  # past the depth, on a connection that takes no more
    messages = drain(outbox)
    if reliability == "best_effort":  # the oldest go, down to the depth, counted
        assert [(m["params"]["seq"], m["params"]["dropped"]) for m in messages] == [
            (14, 3),
            (15, 0),
            (16, 0),
        ]
    else:  # never silently: ended, with what to do about it
        [ended] = messages
        assert ended["error"]["data"]["status"] == "RESOURCE_EXHAUSTED"
        assert ended["error"]["message"] == (
            "the subscriber to /chatter did not keep up: its queue of 3 messages was full while "
            "its connection took no more (the peer did not read what was sent), and the "
            "subscription is reliable; read faster, or subscribe with a larger depth, or "
            "best_effort to drop the oldest instead"
        )
        assert not chatter.subscriptions


def test_the_bytes_queued_on_a_connection_are_bounded() -> None:
    chatter = topic(qos=QoS(depth=100, reliability="best_effort"))
    outbox = Outbox(budget=10 * len(data(0)))
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    for n in range(50):
        chatter.publish(data(n))
        assert outbox.queued <= outbox.budget
    messages = [m["params"] for m in drain(outbox)]
    assert len(messages) == 10
    assert messages[0]["dropped"] == 40


class Transport:
    """What a connection's transport holds: bytes sent, not yet read by the peer."""

    def __init__(self) -> None:
        self.held = 0

    def buffered(self) -> int:
        return self.held


def test_topic_data_takes_what_the_transport_leaves_of_the_budget() -> None:
    size = len(data(0))
    transport = Transport()
    chatter = topic(qos=QoS(depth=100, reliability="best_effort"))
    outbox = Outbox(budget=10 * size, buffered=transport.buffered)
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    transport.held = 6 * size  # replies, and data sent already, that the client has not read
    for n in range(50):
        chatter.publish(data(n))
        assert outbox.queued + transport.held <= outbox.budget
    messages = [m["params"] for m in drain(outbox)]
    assert [(m["seq"], m["dropped"]) for m in messages] == [(47, 46), (48, 0), (49, 0), (50, 0)]
    transport.held = 20 * size  # past the budget: one message at a time, the latest
    for n in range(5):
        chatter.publish(data(n))
    assert [(m["params"]["seq"], m["params"]["dropped"]) for m in drain(outbox)] == [(55, 4)]


def test_a_reliable_subscriber_is_ended_where_the_budget_is_spent() -> None:
    size = len(data(0))
    transport = Transport()
    chatter = topic(qos=QoS(depth=100))
    outbox = Outbox(budget=10 * size, buffered=transport.buffered)
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    transport.held = 7 * size
    assert [chatter.publish(data(n)) for n in range(5)] == [1, 1, 1, 0, 0]
    assert outbox.queued == 0 and not outbox.subscriptions
    [ended] = drain(outbox)
    assert ended["error"]["message"] == (
        "the subscriber to /chatter did not keep up: 48 bytes of topic data queued and 112 "
        "bytes waiting to be sent spent the connection's budget of 160 bytes "
        "(max_queued_bytes), and the subscription is reliable; read faster, or subscribe with "
        "best_effort to drop the oldest instead, or give the server a larger max_queued_bytes"
    )
    assert ended["error"]["data"] == {
        "status": "RESOURCE_EXHAUSTED",
        "depth": 100,
        "seq": 4,
        "max_queued_bytes": 160,
    }


def test_a_reply_takes_its_room_from_topic_data_best_effort_first() -> None:
    size = len(data(0))
    transport = Transport()
    lossy = topic("/lossy", QoS(depth=100, reliability="best_effort"))
    steady = topic("/steady", QoS(depth=100))
    outbox = Outbox(budget=10 * size, buffered=transport.buffered)
    outbox.subscribe(1, lossy, lossy.qos)
    outbox.subscribe(2, steady, steady.qos)
    drain(outbox)
    for n in range(4):
        lossy.publish(data(n))
        steady.publish(data(n))
    outbox.fit()  # everything fits: nothing changes
    assert outbox.queued == 8 * size
    transport.held = 5 * size  # a reply was queued: 3 messages too many
    outbox.fit()
    assert outbox.queued == 5 * size and len(outbox.subscriptions) == 2
    transport.held = 8 * size  # another: best effort has one left to give, then reliable ends
    outbox.fit()
    assert outbox.queued == 0 and list(outbox.subscriptions) == [1]
    messages = drain(outbox)
    assert messages[0]["id"] == 2
    assert messages[0]["error"]["data"]["status"] == "RESOURCE_EXHAUSTED"
    lossy.publish(data(9))
    transport.held = 0
    assert [(m["params"]["seq"], m["params"]["dropped"]) for m in drain(outbox)] == [(5, 4)]


def test_a_reply_leaves_a_message_queued_alone_to_go_out() -> None:
    # One message always gets into an empty outbox, whatever its size; a reply queued next to
    # it does not take it back: a reliable subscription is not ended for it, nor is a best
    # effort message dropped.
    size = len(data(0))
    for qos in (QoS(depth=10), QoS(depth=10, reliability="best_effort")):
        transport = Transport()
        chatter = topic(qos=qos)
        outbox = Outbox(budget=size, buffered=transport.buffered)
        outbox.subscribe(1, chatter, chatter.qos)
        drain(outbox)
        chatter.publish(data(1))
        transport.held = size  # a reply as large as the budget was queued
        outbox.fit()
        assert list(outbox.subscriptions) == [1]
        transport.held = 0
        assert [(m["params"]["seq"], m["params"]["dropped"]) for m in drain(outbox)] == [(1, 0)]


def test_a_message_larger_than_the_budget_still_passes_alone() -> None:
    chatter = topic()
    outbox = Outbox(budget=4)
    outbox.subscribe(1, chatter, chatter.qos)
    drain(outbox)
    chatter.publish(data(1))
    assert [m["params"]["seq"] for m in drain(outbox)] == [1]


def test_transient_local_replays_the_last_depth_messages() -> None:
    chatter = topic(qos=QoS(depth=3, durability="transient_local"))
    for n in range(1, 6):
        chatter.publish(data(n))
    outbox = Outbox()
    outbox.subscribe(1, chatter, chatter.qos)
    late = Outbox()
    late.subscribe(2, chatter, chatter.qos.grant({"depth": 2}))
    assert [m["params"].get("seq") for m in drain(outbox)] == [5, 3, 4, 5]
    assert [m["params"].get("seq") for m in drain(late)] == [5, 4, 5]


def test_ending_a_subscription_drops_its_queue_and_answers_once() -> None:
    chatter = topic()
    woken: list[int] = []
    outbox = Outbox(lambda: woken.append(1))
    outbox.subscribe(1, chatter, QoS())
    assert woken == [1]
    chatter.publish(data(1))
    assert woken == [1]  # woken once until the writer finds it empty
    assert outbox.cancel(1)
    assert not outbox.cancel(1)
    assert outbox.queued == 0 and not outbox.ready and not chatter.subscriptions
    messages = drain(outbox)
    assert [m.get("method") for m in messages] == ["$/subscribed", None]
    assert messages[1]["error"]["data"]["status"] == "CANCELLED"
    chatter.publish(data(2))
    assert outbox.next() is None


def test_removing_a_topic_ends_its_subscriptions_with_a_reply() -> None:
    board: TopicBoard[Entry] = TopicBoard()
    board.add(topic())
    outbox = Outbox()
    subscription = board.subscribe(outbox, 4, {"topic": "chatter"}, frozenset())
    assert not isinstance(subscription, bytes)
    board.remove("/chatter")
    messages = drain(outbox)
    assert messages[-1]["id"] == 4
    assert messages[-1]["error"]["message"] == "the topic /chatter was removed"
    assert messages[-1]["error"]["data"]["status"] == "SERVICE_NOT_FOUND"


def test_the_board_refuses_what_a_connection_may_not_do() -> None:
    board: TopicBoard[Entry] = TopicBoard()
    board.add(topic("/secret", scopes=frozenset({"admin"})))
    outbox = Outbox()

    def refused(params: Any) -> Any:
        reply = board.subscribe(outbox, 1, params, frozenset())
        assert isinstance(reply, bytes)
        return json.loads(reply)["error"]

    assert refused({"topic": "/secret"})["data"]["status"] == "PERMISSION_DENIED"
    assert refused({"topic": "/nothing"})["message"] == "no topic named /nothing (topics: none)"
    assert refused({"topic": 3})["data"]["errors"][0]["path"] == "topic"
    assert refused(["/secret"])["data"]["status"] == "INVALID_PARAMS"
    assert [t.name for t in board.visible(frozenset())] == []
    assert [t.name for t in board.visible(frozenset({"admin"}))] == ["/secret"]


def test_the_session_hands_topic_requests_to_the_board() -> None:
    board: TopicBoard[Entry] = TopicBoard()
    board.add(topic())
    outbox = Outbox()
    session = ServerSession(NoServices(), topics=board, outbox=outbox)
    subscribe = {
        "jsonrpc": "2.0",
        "id": 3,
        "method": "$/subscribe",
        "params": {"topic": "/chatter"},
    }
    assert session.receive(json.dumps(subscribe)) == []
    assert 3 in outbox.subscriptions
    again = json.loads(session.receive(json.dumps(subscribe))[0])
    assert again["error"]["data"]["status"] == "INVALID_REQUEST"
    in_a_batch = json.loads(session.receive(json.dumps([{**subscribe, "id": 4}]))[0])
    assert in_a_batch[0]["error"]["message"] == (
        "Invalid Request: $/subscribe is read only on its own, with an id"
    )
    publish = {"jsonrpc": "2.0", "method": "$/publish", "params": {"topic": "/chatter"}}
    # A notification: never answered, only logged.
    assert session.receive(json.dumps(publish)) == [
        RefusedMessage(
            "/chatter", "invalid params: $/publish needs params {'topic': name, 'message': {...}}"
        )
    ]
    refused = json.loads(session.receive(json.dumps({**publish, "id": 9}))[0])
    assert refused["error"]["data"]["status"] == "INVALID_PARAMS"
    publish["params"]["message"] = {}
    denied = json.loads(session.receive(json.dumps({**publish, "id": 10}))[0])
    assert denied["error"]["message"] == (
        "the server does not take messages on /chatter; only subscribe to it"
    )
    cancel = {"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 3}}
    assert session.receive(json.dumps(cancel)) == []
    assert not outbox.subscriptions
    [subscribed, cancelled] = drain(outbox)
    assert subscribed["method"] == "$/subscribed"
    assert cancelled == {
        "jsonrpc": "2.0",
        "id": 3,
        "error": {
            "code": cancelled["error"]["code"],
            "message": "the subscriber cancelled the subscription",
            "data": {"status": "CANCELLED"},
        },
    }


# --- what a subscriber counts --------------------------------------------------------------------


def test_gaps_count_what_was_missed_across_a_reconnection() -> None:
    gaps = Gaps()
    gaps.subscribed(0)
    assert gaps.accept(1, 0) == 0
    assert gaps.accept(4, 2) == 2
    gaps.subscribed(9)  # reconnected: the topic went on meanwhile, and replays 8 and 9
    assert gaps.resumed == 1
    assert gaps.accept(3, 0) is None  # seen already
    assert gaps.accept(8, 0) == 3  # 5, 6, 7
    assert gaps.missed == 5
    gaps.subscribed(2)  # the server restarted: numbers cannot be compared
    assert gaps.restarts == 1
    assert gaps.accept(1, 0) == 0


def test_gaps_take_another_epoch_for_a_restart_though_the_numbers_went_on() -> None:
    gaps = Gaps()
    gaps.subscribed(0, "a")
    assert [gaps.accept(seq, 0) for seq in (1, 2, 3)] == [0, 0, 0]
    gaps.subscribed(3, "a")  # the same topic: 3 is seen already
    assert gaps.accept(3, 0) is None and gaps.restarts == 0
    gaps.subscribed(4, "b")  # another server, whose history replays 2, 3 and 4
    assert gaps.restarts == 1 and gaps.resumed == 2
    assert [gaps.accept(seq, 0) for seq in (2, 3, 4)] == [0, 0, 0]
    assert gaps.missed == 0
    gaps.subscribed(9)  # a server that says no epoch: the numbers alone decide
    assert gaps.restarts == 1 and gaps.accept(4, 0) is None
    assert Topic("/x", None).epoch != Topic("/x", None).epoch  # each instance its own


@settings(max_examples=200, deadline=None)
@given(
    depth=st.integers(min_value=1, max_value=8),
    best_effort=st.booleans(),
    steps=st.lists(st.integers(min_value=0, max_value=5), min_size=1, max_size=60),
)
def test_order_and_sequence_numbers_hold_under_any_depth(
    depth: int, best_effort: bool, steps: list[int]
) -> None:
    """Publish bursts and take a few messages in turn: a subscriber sees increasing sequence
    numbers, whose gaps are exactly what was said dropped; a reliable one sees every message
    or is ended, never a gap; no queue ever holds more than its depth."""
    qos = QoS(depth=depth, reliability="best_effort" if best_effort else "reliable")
    chatter = topic(qos=qos)
    outbox = Outbox()
    subscription = outbox.subscribe(1, chatter, qos)
    drain(outbox)
    seen: list[dict[str, Any]] = []
    ended = False
    for burst in steps:
        for _ in range(burst):
            chatter.publish(data(chatter.seq + 1))
            assert len(subscription.queue) <= depth
        for _ in range(2):
            taken = outbox.next()
            if taken is None:
                break
            message = json.loads(taken)
            if "error" in message:
                ended = True
                assert message["error"]["data"]["status"] == "RESOURCE_EXHAUSTED"
            else:
                seen.append(message["params"])
    for message in drain(outbox):
        if "error" in message:
            ended = True
        else:
            seen.append(message["params"])
    previous = 0
    for params in seen:
        assert params["seq"] > previous
        assert params["seq"] - previous - 1 == params["dropped"]
        assert params["message"] == json.loads(data(params["seq"]))
        if not best_effort:
            assert params["dropped"] == 0
        previous = params["seq"]
    if best_effort:
        assert not ended
        assert previous == chatter.seq  # the last one is never dropped
    elif not ended:
        assert previous == chatter.seq
    assert outbox.queued == 0


def ready_holds_exactly_what_has_data(outbox: Outbox) -> None:
    """The outbox's invariant: a subscription is in the round-robin, once, exactly when its
    queue holds something, and ``queued`` counts the bytes the queues hold."""
    ready = list(outbox.ready)
    assert len(ready) == len(set(map(id, ready)))
    for subscription in outbox.subscriptions.values():
        assert subscription.ready == bool(subscription.queue) == (subscription in ready)
    assert all(subscription.id in outbox.subscriptions for subscription in ready)
    queued = sum(len(m) for s in outbox.subscriptions.values() for _, m in s.queue)
    assert outbox.queued == queued


def test_a_best_effort_subscription_that_gives_up_its_last_message_leaves_the_round_robin() -> None:
    # Two best-effort subscriptions hold a message each when the transport's bytes grow (a
    # reply): the next publication leaves no room, and each drops its old message and the new
    # one. Neither may stay in the round-robin with nothing queued: the writer would take
    # from an empty queue, and the close would end nothing after it.
    size = len(data(0))
    transport = Transport()
    chatter = topic(qos=QoS(depth=5))
    lossy = QoS(depth=5, reliability="best_effort")
    outbox = Outbox(budget=3 * size, buffered=transport.buffered, writable=lambda: True)
    pair = [outbox.subscribe(name, chatter, lossy) for name in "ab"]
    drain(outbox)
    chatter.publish(data(1))
    transport.held = 2 * size
    chatter.publish(data(2))  # the first of them in the topic's order gives up everything
    assert sorted(len(subscription.queue) for subscription in pair) == [0, 1]
    ready_holds_exactly_what_has_data(outbox)
    messages = drain(outbox)  # the other kept the new message: it goes out, nothing fails
    assert [m["params"]["seq"] for m in messages] == [2]
    transport.held = 0
    chatter.publish(data(3))
    assert sorted((m["params"]["subscription"], m["params"]["seq"]) for m in drain(outbox))[
        -2:
    ] == [("a", 3), ("b", 3)]
    outbox.close()
    assert not chatter.subscriptions and not outbox.ready and outbox.queued == 0


def test_a_congested_connection_with_two_best_effort_subscriptions_keeps_the_invariant() -> None:
    # A writer that sends a message at a time between publications, 30 000 bytes of replies
    # written beside them, a peer that reads 20 000 bytes in between, a budget of 4 MiB.
    budget = 4 * 2**20
    transport = Transport()
    chatter = topic(qos=QoS(depth=1))
    outbox = Outbox(
        budget=budget, buffered=transport.buffered, writable=lambda: transport.held <= budget
    )
    lossy = QoS(depth=1, reliability="best_effort")
    for n in range(2):
        outbox.subscribe(n, chatter, lossy)
    drain(outbox)
    payload = b'"' + b"x" * 9_998 + b'"'
    for _ in range(2000):
        chatter.publish(payload)
        ready_holds_exactly_what_has_data(outbox)
        if transport.held <= budget and (taken := outbox.next()) is not None:
            transport.held += len(taken)
        transport.held = max(0, transport.held + 30_000 - 20_000)
    outbox.close()
    assert not chatter.subscriptions and not outbox.ready and outbox.queued == 0


@settings(max_examples=300, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.sampled_from(["publish", "take", "fit", "held"]),
            st.integers(min_value=0, max_value=3),
            st.integers(min_value=0, max_value=12),
        ),
        min_size=1,
        max_size=80,
    ),
    reliable=st.lists(st.booleans(), min_size=1, max_size=4),
    depth=st.integers(min_value=1, max_value=4),
)
def test_the_round_robin_holds_exactly_the_subscriptions_with_data(
    steps: list[tuple[str, int, int]], reliable: list[bool], depth: int
) -> None:
    """Whatever the transport holds, whatever is published, taken or fitted: a subscription
    is ready exactly when it has data, and closing leaves nothing on any topic."""
    size = len(data(0))
    transport = Transport()
    topics = [topic(f"/t{n}", QoS(depth=depth)) for n in range(2)]
    outbox = Outbox(
        budget=6 * size,
        buffered=transport.buffered,
        writable=lambda: transport.held <= 6 * size,
    )
    for n, steady in enumerate(reliable):
        qos = QoS(depth=depth, reliability="reliable" if steady else "best_effort")
        outbox.subscribe(n, topics[n % 2], qos)
    drain(outbox)
    for action, which, amount in steps:
        if action == "publish":
            topics[which % 2].publish(data(amount))
        elif action == "take":
            for _ in range(which):
                outbox.next()
        elif action == "fit":
            outbox.fit()
        else:
            transport.held = amount * size
        ready_holds_exactly_what_has_data(outbox)
    outbox.close()
    assert not any(t.subscriptions for t in topics)
    assert not outbox.ready and outbox.queued == 0


def test_closing_ends_every_subscription_even_when_ending_one_fails() -> None:
    class Failing(Outbox):
        def end(self, subscription: Any, error: Any) -> bool:
            ended = super().end(subscription, error)
            if subscription.id == "a":
                raise RuntimeError("a bug")
            return ended

    chatter = topic(qos=QoS(depth=5))
    outbox = Failing()
    for name in "abc":
        outbox.subscribe(name, chatter, chatter.qos)
    chatter.publish(data(1))
    with pytest.raises(RuntimeError, match="a bug"):
        outbox.close()
    assert not chatter.subscriptions and not outbox.subscriptions
    assert not outbox.ready and outbox.queued == 0 and not outbox.control
