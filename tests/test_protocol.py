"""The sans-I/O JSON-RPC layer: text in, messages out, and back. No event loop here."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import example, given, settings, strategies as st

from srvwire.errors import (
    DeadlineExceeded,
    InvalidParams,
    InvalidRequest,
    ParseError,
    ServiceError,
    ServiceNotFound,
)
from srvwire.protocol import (
    MAX_DEPTH,
    CallWriter,
    ErrorResponse,
    Incoming,
    Notification,
    RawJSON,
    Request,
    Response,
    cancel_notification,
    canonical_name,
    decode_json,
    encode_json,
    parse_incoming,
    parse_replies,
    serialize_batch,
    services_notification,
)


def error_of(incoming: Incoming, index: int = 0) -> dict[str, Any]:
    item = incoming.items[index]
    assert isinstance(item, ErrorResponse), item
    decoded: dict[str, Any] = json.loads(item.serialize())
    return decoded


# --- parsing what clients send ------------------------------------------------------------------


def test_a_request_by_name() -> None:
    text = '{"jsonrpc": "2.0", "method": "subtract", "params": {"minuend": 42}, "id": 3}'
    assert parse_incoming(text) == Incoming((Request(3, "subtract", {"minuend": 42}),))


def test_a_request_by_position_and_without_params() -> None:
    assert parse_incoming('{"jsonrpc":"2.0","method":"s","params":[42,23],"id":"a"}').items == (
        Request("a", "s", [42, 23]),
    )
    assert parse_incoming(b'{"jsonrpc":"2.0","method":"s","id":null}').items == (
        Request(None, "s", None),
    )


def test_a_notification_has_no_id_member() -> None:
    assert parse_incoming('{"jsonrpc":"2.0","method":"update","params":[1,2]}').items == (
        Notification("update", [1, 2]),
    )


def test_meta_timeout_is_taken_out_of_params() -> None:
    text = '{"jsonrpc":"2.0","id":1,"method":"m","params":{"a":1,"_meta":{"timeout":2.5,"x":0}}}'
    assert parse_incoming(text).items == (Request(1, "m", {"a": 1}, timeout=2.5),)
    note = '{"jsonrpc":"2.0","method":"m","params":{"_meta":{}}}'
    assert parse_incoming(note).items == (Notification("m", {}),)


@pytest.mark.parametrize(
    ("meta", "path", "message"),
    [
        ('"soon"', "_meta", "invalid _meta: must be an object, not a string"),
        (
            '{"timeout":-1}',
            "_meta.timeout",
            "invalid _meta.timeout: must be a number of seconds >= 0, not -1",
        ),
        (
            '{"timeout":"1"}',
            "_meta.timeout",
            'invalid _meta.timeout: must be a number of seconds >= 0, not "1"',
        ),
        (
            '{"timeout":true}',
            "_meta.timeout",
            "invalid _meta.timeout: must be a number of seconds >= 0, not true",
        ),
        (
            '{"timeout":Infinity}',
            "_meta.timeout",
            "invalid _meta.timeout: must be a number of seconds >= 0, not Infinity",
        ),
        (
            '{"timeout":1e400}',  # read as infinity
            "_meta.timeout",
            "invalid _meta.timeout: must be a number of seconds >= 0, not Infinity",
        ),
        (
            '{"timeout":NaN}',
            "_meta.timeout",
            "invalid _meta.timeout: must be a number of seconds >= 0, not NaN",
        ),
        (
            '{"timeout":1' + "0" * 400 + "}",  # an exact integer no float can hold
            "_meta.timeout",
            "invalid _meta.timeout: must be a number of seconds >= 0, "
            "not an integer too large for a float",
        ),
    ],
)
def test_a_bad_meta_is_invalid_params(meta: str, path: str, message: str) -> None:
    reply = error_of(
        parse_incoming('{"jsonrpc":"2.0","id":7,"method":"m","params":{"_meta":' + meta + "}}")
    )
    assert reply["id"] == 7
    assert reply["error"]["code"] == -32602
    assert reply["error"]["message"] == message
    assert reply["error"]["data"]["errors"][0]["path"] == path


@pytest.mark.parametrize(
    ("meta", "message"),
    [
        ("5", "invalid _meta: must be an object, not a number"),
        ('{"timeout":-0.5}', "invalid _meta.timeout: must be a number of seconds >= 0, not -0.5"),
        (
            '{"timeout":-1' + "0" * 400 + "}",
            "invalid _meta.timeout: must be a number of seconds >= 0, "
            "not an integer too large for a float",
        ),
    ],
)
def test_a_notification_with_a_bad_meta_carries_the_error_and_is_never_answered(
    meta: str, message: str
) -> None:
    text = '{"jsonrpc":"2.0","method":"echo","params":{"text":"x","_meta":' + meta + "}}"
    for incoming in (parse_incoming(text), parse_incoming("[" + text + "]")):
        (item,) = incoming.items
        assert isinstance(item, Notification), item
        assert (item.method, item.params, item.timeout) == ("echo", {"text": "x"}, None)
        assert isinstance(item.error, InvalidParams)
        assert item.error.message == message


def test_not_json_is_a_parse_error_with_a_null_id() -> None:
    reply = error_of(parse_incoming('{"jsonrpc": "2.0", "method": "foobar, "params": "bar", "baz]'))
    assert reply == {
        "jsonrpc": "2.0",
        "id": None,
        "error": {
            "code": -32700,
            "message": "Parse error: expected `,` or `}` at line 1 column 40",
            "data": {"status": "PARSE_ERROR"},
        },
    }


def test_binary_input_is_read_as_utf8_json() -> None:
    text = '{"jsonrpc":"2.0","method":"m","params":["é"],"id":1}'
    for data in (text.encode(), bytearray(text.encode()), memoryview(text.encode())):
        assert parse_incoming(data).items == (Request(1, "m", ["é"]),)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b'{"a":"\xff"}', "Parse error: invalid UTF-8 at byte 6"),
        (b"\xc0\xaf", "Parse error: invalid UTF-8 at byte 0"),
        (b"\xed\xa0\x80", "Parse error: invalid UTF-8 at byte 0"),  # an encoded surrogate
        ("", "Parse error: EOF while parsing a value at line 1 column 0"),
        ("{} {}", "Parse error: trailing characters at line 1 column 4"),
        ('"\\ud800"', "Parse error: unexpected end of hex escape at line 1 column 8"),
        ("\ud800", "Parse error: Expected bytes, bytearray or str"),
        (b'{"a":1} \xff', "Parse error: invalid UTF-8 at byte 8"),  # UTF-8 is checked first
        (b'{"\xc3\xa9":x}', "Parse error: expected value at line 1 column 7"),
    ],
)
def test_parse_errors(data: str | bytes, message: str) -> None:
    assert error_of(parse_incoming(data))["error"]["message"] == message


@pytest.mark.parametrize("opener", ["[", '{"a":'])
def test_deep_nesting_is_a_parse_error_not_a_recursion_error(opener: str) -> None:
    closer = "]" if opener == "[" else "}"
    text = opener * 100_000 + closer * 100_000
    reply = error_of(parse_incoming(text))
    assert reply["error"]["code"] == -32700
    assert "recursion limit exceeded" in reply["error"]["message"]
    assert parse_incoming("[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1)).is_batch


@pytest.mark.parametrize("opener", ["[", '{"a":'])
def test_max_depth_is_exactly_where_nesting_stops(opener: str) -> None:
    closer = "]" if opener == "[" else "}"

    def nested(depth: int) -> str:
        return opener * depth + "1" + closer * depth

    value = decode_json(nested(MAX_DEPTH))
    for _ in range(MAX_DEPTH):
        value = value[0] if opener == "[" else value["a"]
    assert value == 1
    with pytest.raises(ParseError, match="recursion limit exceeded"):
        decode_json(nested(MAX_DEPTH + 1))


@pytest.mark.parametrize(
    ("text", "id", "message"),
    [
        (
            '{"jsonrpc":"2.0","method":1,"params":"bar"}',
            None,
            "Invalid Request: 'method' must be a string, not a number",
        ),
        ('{"jsonrpc":"2.0","id":4}', 4, "Invalid Request: 'method' must be a string, not missing"),
        (
            '{"jsonrpc":"2.0","id":4,"method":null}',
            4,
            "Invalid Request: 'method' must be a string, not null",
        ),
        ('{"method":"m","id":"x"}', "x", "Invalid Request: 'jsonrpc' must be exactly \"2.0\""),
        (
            '{"jsonrpc":2.0,"method":"m","id":1}',
            1,
            "Invalid Request: 'jsonrpc' must be exactly \"2.0\"",
        ),
        (
            '{"jsonrpc":"2.0","method":"m","id":{"a":1}}',
            None,
            "Invalid Request: 'id' must be a string, a number or null, not an object",
        ),
        (
            '{"jsonrpc":"2.0","method":"m","id":true}',
            None,
            "Invalid Request: 'id' must be a string, a number or null, not a boolean",
        ),
        (
            '{"jsonrpc":"2.0","method":"m","id":2,"params":"p"}',
            2,
            "Invalid Request: 'params' must be an object or an array, not a string",
        ),
        (
            '{"jsonrpc":"2.0","method":"m","id":2,"params":null}',
            2,
            "Invalid Request: 'params' must be an object or an array, not null",
        ),
        ('"hello"', None, "Invalid Request: expected an object, got a string"),
        ("[]", None, "Invalid Request: empty batch"),
    ],
)
def test_invalid_requests(text: str, id: Any, message: str) -> None:
    incoming = parse_incoming(text)
    assert not incoming.is_batch
    reply = error_of(incoming)
    assert reply == {
        "jsonrpc": "2.0",
        "id": id,
        "error": {"code": -32600, "message": message, "data": {"status": "INVALID_REQUEST"}},
    }


def test_a_batch_keeps_its_order_and_answers_invalid_items_in_place() -> None:
    text = """[
        {"jsonrpc": "2.0", "method": "sum", "params": [1,2,4], "id": "1"},
        {"jsonrpc": "2.0", "method": "notify_hello", "params": [7]},
        {"foo": "boo"},
        1
    ]"""
    incoming = parse_incoming(text)
    assert incoming.is_batch
    first, second, third, fourth = incoming.items
    assert first == Request("1", "sum", [1, 2, 4])
    assert second == Notification("notify_hello", [7])
    assert isinstance(third, ErrorResponse) and third.id is None
    assert isinstance(fourth, ErrorResponse) and isinstance(fourth.error, InvalidRequest)


@pytest.mark.parametrize(
    ("id", "what"),
    [
        ("Infinity", "Infinity"),
        ("-Infinity", "-Infinity"),
        ("NaN", "NaN"),
        ("1e400", "Infinity"),  # too large for a double: read as infinity
        ("-1e400", "-Infinity"),
    ],
)
def test_a_non_finite_id_is_invalid_with_a_null_id(id: str, what: str) -> None:
    message = f"Invalid Request: 'id' must be a string, a number or null, not {what}"
    text = '{"jsonrpc":"2.0","method":"m","id":' + id + "}"
    assert error_of(parse_incoming(text)) == {
        "jsonrpc": "2.0",
        "id": None,
        "error": {"code": -32600, "message": message, "data": {"status": "INVALID_REQUEST"}},
    }
    batch = parse_incoming("[" + text + ',{"jsonrpc":"2.0","method":"m","id":2}]')
    assert error_of(batch, 0)["id"] is None
    assert batch.items[1] == Request(2, "m")
    with pytest.raises(InvalidRequest):
        parse_replies('{"jsonrpc":"2.0","id":' + id + ',"result":1}')


def test_a_fractional_id_is_accepted_and_echoed() -> None:
    # The specification says numbers SHOULD NOT have fractions; a server still answers them.
    assert parse_incoming('{"jsonrpc":"2.0","method":"m","id":2.5}').items == (Request(2.5, "m"),)
    assert Response(2.5, RawJSON(b"0")).serialize() == b'{"jsonrpc":"2.0","id":2.5,"result":0}'


def test_ids_come_back_exactly() -> None:
    big = 2**64 - 1
    request = parse_incoming(f'{{"jsonrpc":"2.0","id":{big},"method":"m"}}').items[0]
    assert isinstance(request, Request) and request.id == big
    expected = f'{{"jsonrpc":"2.0","id":{big},"result":0}}'.encode()
    assert Response(big, RawJSON(b"0")).serialize() == expected
    assert Response(1.5, RawJSON(b"0")).serialize() == b'{"jsonrpc":"2.0","id":1.5,"result":0}'
    assert Response('a"b', RawJSON(b"0")).serialize() == (
        b'{"jsonrpc":"2.0","id":"a\\"b","result":0}'
    )


# --- building what servers and clients send ----------------------------------------------------


def test_responses_embed_raw_json_as_it_is() -> None:
    raw = '{"sum": 3, "spacing" : [ ]}'
    assert Response(5, RawJSON(raw)).serialize() == (
        b'{"jsonrpc":"2.0","id":5,"result":{"sum": 3, "spacing" : [ ]}}'
    )
    assert Response("x", {"a": [1, None]}).serialize() == (
        b'{"jsonrpc":"2.0","id":"x","result":{"a":[1,null]}}'
    )
    assert Response(5, RawJSON(raw.encode())).serialize() == Response(5, RawJSON(raw)).serialize()


def test_error_responses_carry_status_and_data() -> None:
    reply = ErrorResponse(9, ServiceError(42, "out of paper", {"tray": 2})).serialize()
    assert reply == (
        b'{"jsonrpc":"2.0","id":9,"error":{"code":42,"message":"out of paper","data":{"tray":2}}}'
    )
    missing = ErrorResponse(None, ServiceNotFound("no service named /x", {"candidates": []}))
    assert json.loads(missing.serialize())["error"] == {
        "code": -32601,
        "message": "no service named /x",
        "data": {"status": "SERVICE_NOT_FOUND", "candidates": []},
    }


def test_serializing_never_fails_on_odd_data() -> None:
    error = ServiceError(1, "odd", {"set": {1}, "nan": float("nan"), "obj": object})
    data = json.loads(error_response_text(error))["error"]["data"]
    assert data["set"] == [1]
    assert data["nan"] is None
    assert data["obj"].startswith("<class")


def error_response_text(error: Any) -> bytes:
    return ErrorResponse(1, error).serialize()


@pytest.mark.parametrize(
    ("id", "id_json"), [(1, b"1"), ("é", '"é"'.encode()), (None, b"null"), (2.5, b"2.5")]
)
def test_a_raw_result_is_spliced_in_as_utf8_from_text_or_bytes_alike(
    id: Any, id_json: bytes
) -> None:
    result = '{"text":"ünï","values":[1.0,2.5]}'
    expected = b'{"jsonrpc":"2.0","id":' + id_json + b',"result":' + result.encode() + b"}"
    assert Response(id, RawJSON(result)).serialize() == expected
    assert Response(id, RawJSON(result.encode())).serialize() == expected


def test_the_clients_calls_are_written_in_one_go() -> None:
    # An int id, params as pydantic writes them (a compact object), a finite float timeout.
    assert Request(7, "/m", RawJSON('{"a":1,"b":"x"}'), 2.5).serialize() == (
        b'{"jsonrpc":"2.0","id":7,"method":"/m","params":{"_meta":{"timeout":2.5},"a":1,"b":"x"}}'
    )
    assert Request(8, "/m", RawJSON("{}"), 0.5).serialize() == (
        b'{"jsonrpc":"2.0","id":8,"method":"/m","params":{"_meta":{"timeout":0.5}}}'
    )
    assert Request(9, '/a"b', RawJSON("{}"), 1e-05).serialize() == (
        b'{"jsonrpc":"2.0","id":9,"method":"/a\\"b","params":{"_meta":{"timeout":1e-05}}}'
    )
    assert Request(10, "/m", RawJSON("{}"), 1e16).serialize() == (
        b'{"jsonrpc":"2.0","id":10,"method":"/m","params":{"_meta":{"timeout":1e+16}}}'
    )


@given(
    timeout=st.floats(min_value=0, allow_nan=False, allow_infinity=False),
    params=st.dictionaries(st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True), st.integers()),
)
def test_a_call_written_in_one_go_is_the_request_the_general_path_writes(
    timeout: float, params: dict[str, int]
) -> None:
    text = encode_json(params)
    written = Request(3, "/m", RawJSON(text), timeout).serialize()
    # Params as bytes, or as a dict (whose _meta goes last), take the general path.
    assert written == Request(3, "/m", RawJSON(text.encode()), timeout).serialize()
    assert json.loads(written) == json.loads(Request(3, "/m", params, timeout).serialize())
    (item,) = parse_incoming(written).items
    assert item == Request(3, "/m", params, timeout)


@settings(max_examples=200)
@given(
    method=st.text(),
    timeout=st.floats(min_value=0, allow_nan=False, allow_infinity=False),
    params=st.dictionaries(st.text(), st.integers() | st.text()),
)
@example(method="/m%d%r%b%%", timeout=1.5, params={"%s": "%d"})
@example(method='/a"b', timeout=1e16, params={})
def test_a_call_writer_writes_what_the_general_path_writes(
    method: str, timeout: float, params: dict[str, Any]
) -> None:
    # The template made once per method: the bytes Request.serialize writes with the timeout
    # rounded to the microsecond, but for the timeout's text (six decimals: the same number),
    # whatever the name and params hold (a % in either is text, not a format).
    text = encode_json(params)
    written = CallWriter(method)(5, text.encode(), timeout)
    rounded = round(timeout, 6)
    general = Request(5, method, RawJSON(text), rounded).serialize()
    six_decimals = b'"timeout":%s}' % f"{timeout:.6f}".encode()
    assert written == general.replace(b'"timeout":%s}' % repr(rounded).encode(), six_decimals, 1)
    assert json.loads(written) == json.loads(general)  # the same timeout, to the bit


def test_a_call_writer_leaves_what_is_not_a_call_to_the_general_path() -> None:
    write = CallWriter("/m")
    assert write(1, b"[1]", 1.0) is None  # not an object
    assert write(1, b"{ }", 1.0) is None  # not written compactly
    assert write(1, b'{"a":1', 1.0) is None  # cut short
    assert write(1, b"{}", math.inf) is None and write(1, b"{}", math.nan) is None
    assert write(1, b"{}", 1) is None  # an int timeout: the general path writes it as 1.0
    assert write(1, b"{}", 0.25) == (
        b'{"jsonrpc":"2.0","id":1,"method":"/m","params":{"_meta":{"timeout":0.250000}}}'
    )
    assert write(2, b'{"a":1}', 29.99998749) == (  # rounded to the microsecond
        b'{"jsonrpc":"2.0","id":2,"method":"/m","params":{"_meta":{"timeout":29.999987},"a":1}}'
    )


@settings(max_examples=200)
@given(st.text())
@example("/m")
@example('/a"b')
@example("/a\\b")
@example("/é")
@example("/ロボット")
@example("/😀")
@example("/a\nb")
@example("/a\x00b")
@example("/a\x7fb")
@example("/a\u2028b")
@example("/a/b<>&'")
@example("")
def test_a_method_name_is_written_as_json_writes_it(method: str) -> None:
    # Most names skip the encoder; the ones that need escaping (or are not ASCII) must not.
    name = encode_json(method).encode()
    call = Request(1, method, RawJSON("{}"), 1.0).serialize()
    assert (
        call
        == b'{"jsonrpc":"2.0","id":1,"method":' + name + b',"params":{"_meta":{"timeout":1.0}}}'
    )
    assert Request("x", method).serialize() == b'{"jsonrpc":"2.0","id":"x","method":' + name + b"}"
    assert Notification(method).serialize() == b'{"jsonrpc":"2.0","method":' + name + b"}"
    assert parse_incoming(call).items == (Request(1, method, {}, 1.0),)


def test_requests_carry_the_timeout_in_meta() -> None:
    assert Request(1, "/m").serialize() == b'{"jsonrpc":"2.0","id":1,"method":"/m"}'
    assert Request(1, "/m", {"a": 1}, timeout=2).serialize() == (
        b'{"jsonrpc":"2.0","id":1,"method":"/m","params":{"a":1,"_meta":{"timeout":2}}}'
    )
    assert Request(2, "/m", RawJSON(' {"a": 1}'), timeout=0.5).serialize() == (
        b'{"jsonrpc":"2.0","id":2,"method":"/m","params":{"_meta":{"timeout":0.5},"a": 1}}'
    )
    # Beside raw params or none, an int timeout is written as the float it is read as.
    assert Request(3, "/m", RawJSON('\n{\t"a": {"b": []} }\n '), timeout=1).serialize() == (
        b'{"jsonrpc":"2.0","id":3,"method":"/m","params":{"_meta":{"timeout":1.0},"a": {"b": []} }}'
    )
    assert Notification("/n", RawJSON('{"a":1}'), timeout=2).serialize() == (
        b'{"jsonrpc":"2.0","method":"/n","params":{"_meta":{"timeout":2.0},"a":1}}'
    )
    assert Request(4, "/m", timeout=1.0).serialize() == (
        b'{"jsonrpc":"2.0","id":4,"method":"/m","params":{"_meta":{"timeout":1.0}}}'
    )
    assert Notification("/n", [1]).serialize() == b'{"jsonrpc":"2.0","method":"/n","params":[1]}'
    with pytest.raises(ValueError, match="params by name"):
        Request(5, "/m", [1], timeout=1.0).serialize()


@pytest.mark.parametrize(
    ("params", "spliced"),
    [
        ("{ }", b'{"_meta":{"timeout":1.0}}'),
        ("{\n}", b'{"_meta":{"timeout":1.0}}'),
        (" { } ", b'{"_meta":{"timeout":1.0}}'),
        ('{ "a": 1}', b'{"_meta":{"timeout":1.0},"a": 1}'),
        (' {"a": 1}', b'{"_meta":{"timeout":1.0},"a": 1}'),
        ('{"a": 1}\n', b'{"_meta":{"timeout":1.0},"a": 1}'),
    ],
)
def test_raw_params_with_blanks_take_the_timeout(params: str, spliced: bytes) -> None:
    written = Request(3, "/m", RawJSON(params), timeout=1.0).serialize()
    assert written == b'{"jsonrpc":"2.0","id":3,"method":"/m","params":' + spliced + b"}"
    for text in (params, params.encode()):
        message = Request(3, "/m", RawJSON(text), timeout=1.0).serialize()
        assert parse_incoming(message).items == (Request(3, "/m", json.loads(params), 1.0),)


@pytest.mark.parametrize("params", ["[1]", "[1,2]", "", '"x"', "1", "null", "{"])
def test_a_timeout_refuses_raw_params_that_are_not_an_object(params: str) -> None:
    # Spliced in, they would make invalid JSON (the server answers PARSE_ERROR with id null).
    for text in (params, params.encode()):
        with pytest.raises(ValueError, match="a timeout needs params that are a JSON object"):
            Request(1, "/m", RawJSON(text), timeout=1.0).serialize()


@pytest.mark.parametrize("params", [None, {}, RawJSON("{}"), RawJSON(b"{}")])
@pytest.mark.parametrize(
    ("timeout", "named"),
    [(math.inf, "Infinity"), (-math.inf, "-Infinity"), (math.nan, "NaN"), (10**400, "an integer")],
)
def test_a_timeout_that_is_not_a_finite_number_is_refused(
    params: Any, timeout: float, named: str
) -> None:
    # Python would write inf or nan, which is not JSON, and null would mean "no deadline".
    with pytest.raises(ValueError, match=f"finite number of seconds, not {named}"):
        Request(1, "/m", params, timeout).serialize()


@pytest.mark.parametrize(
    "message",
    [
        Request(1, "/m", {"a": [1, 2]}, timeout=3.0),
        Request("id", "/m", [1, "x"]),
        Notification("/m", {"a": 1}),
        Notification("/m"),
    ],
)
def test_what_a_client_sends_the_server_reads_back(message: Request | Notification) -> None:
    assert parse_incoming(message.serialize()).items == (message,)


def test_batches_and_protocol_notifications() -> None:
    assert serialize_batch([Response(1, 2), b'{"pre":"made"}']) == (
        b'[{"jsonrpc":"2.0","id":1,"result":2},{"pre":"made"}]'
    )
    assert cancel_notification(7).serialize() == (
        b'{"jsonrpc":"2.0","method":"$/cancel","params":{"id":7}}'
    )
    assert services_notification([("/b", "p/srv/B"), ("/a", "p/srv/A")]).serialize() == (
        b'{"jsonrpc":"2.0","method":"$/services","params":{"services":'
        b'[{"name":"/a","type":"p/srv/A"},{"name":"/b","type":"p/srv/B"}]}}'
    )
    assert encode_json(RawJSON("[1]")) == "[1]"
    assert encode_json(RawJSON(b"[1]")) == "[1]"


# --- parsing what servers send -------------------------------------------------------------------


def test_parse_replies() -> None:
    replies = parse_replies(
        '[{"jsonrpc":"2.0","id":1,"result":{"sum":3}},'
        '{"jsonrpc":"2.0","id":2,"error":{"code":-32001,"message":"late",'
        '"data":{"status":"DEADLINE_EXCEEDED"}}},'
        '{"jsonrpc":"2.0","method":"$/services","params":{"services":[]}}]'
    )
    assert replies[0] == Response(1, {"sum": 3})
    error = replies[1]
    assert isinstance(error, ErrorResponse) and isinstance(error.error, DeadlineExceeded)
    assert error.error.message == "late" and error.error.data is None
    assert replies[2] == Notification("$/services", {"services": []})


def test_parse_replies_round_trips_every_error() -> None:
    for error in (
        InvalidParams("bad", {"errors": [{"path": "a", "message": "m", "type": "t"}]}),
        ServiceError(12, "app", [1, 2]),
    ):
        (reply,) = parse_replies(ErrorResponse(3, error).serialize())
        assert isinstance(reply, ErrorResponse)
        assert type(reply.error) is type(error)
        assert (reply.error.code, reply.error.message, reply.error.data) == (
            error.code,
            error.message,
            error.data,
        )


@pytest.mark.parametrize(
    ("text", "error", "message"),
    [
        ("nope", ParseError, "Parse error: expected ident at line 1 column 2"),
        ("[]", InvalidRequest, "Invalid reply: empty batch"),
        ("3", InvalidRequest, "Invalid reply: expected an object, got a number"),
        ('{"id":1,"result":1}', InvalidRequest, "Invalid reply: 'jsonrpc' must be exactly \"2.0\""),
        (
            '{"jsonrpc":"2.0","result":1}',
            InvalidRequest,
            "Invalid reply: 'id' missing or not a string, a number or null",
        ),
        (
            '{"jsonrpc":"2.0","id":1,"result":1,"error":{}}',
            InvalidRequest,
            "Invalid reply: both 'result' and 'error'",
        ),
        (
            '{"jsonrpc":"2.0","id":1}',
            InvalidRequest,
            "Invalid reply: neither 'result' nor an 'error' object",
        ),
        (
            '{"jsonrpc":"2.0","id":1,"error":{"code":"1","message":"m"}}',
            InvalidRequest,
            "Invalid reply: 'error' needs an integer code and a string message",
        ),
        ('{"jsonrpc":"2.0","method":5}', InvalidRequest, "Invalid reply: malformed notification"),
    ],
)
def test_parse_replies_refuses_what_is_not_json_rpc(
    text: str, error: type[Exception], message: str
) -> None:
    with pytest.raises(error) as caught:
        parse_replies(text)
    assert caught.value.args[0] == message


# --- nothing a peer sends makes parsing raise ----------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda children: st.lists(children) | st.dictionaries(st.text(), children),
    max_leaves=20,
)


@settings(max_examples=200)
@given(st.one_of(st.text(), st.binary(), json_values.map(json.dumps)))
def test_parse_incoming_never_raises_and_every_error_serializes(data: str | bytes) -> None:
    incoming = parse_incoming(data)
    assert incoming.items
    for item in incoming.items:
        if isinstance(item, ErrorResponse):
            reply = json.loads(item.serialize())
            assert set(reply) == {"jsonrpc", "id", "error"}
            assert isinstance(reply["error"]["code"], int)
        else:
            assert isinstance(item, Request | Notification)


def test_a_service_name_is_kept_with_one_leading_slash() -> None:
    assert canonical_name("get_robot_state") == "/get_robot_state"
    assert canonical_name("/robot1/get_robot_state") == "/robot1/get_robot_state"
    assert canonical_name("") == "/"
