"""The client's fast path for replies, without I/O: recognise a response now, parse it later.

:func:`peek_reply` must recognise what srvwire servers write and nothing that could mean
something else; :func:`parse_raw_reply` must read the whole message as :func:`parse_replies`
does, and refuse one that opens as a response to a call but is not that response.
"""

from __future__ import annotations

import pytest

from srvwire.errors import InvalidRequest, ParseError
from srvwire.protocol import (
    RawReply,
    Response,
    encode_result,
    parse_raw_reply,
    parse_replies,
    peek_reply,
)


def test_what_srvwire_servers_write_is_recognised() -> None:
    message = encode_result(42, b'{"sum":3}').decode()
    assert peek_reply(message) == RawReply(42, message, len('{"jsonrpc":"2.0","id":42,"result":'))
    raw = peek_reply(message)
    assert raw is not None and raw.result == '{"sum":3}'
    text = Response(7, [1, "ハ"]).serialize()
    raw = peek_reply(text)
    assert raw is not None and (raw.id, raw.result) == (7, '[1,"ハ"]')
    largest = peek_reply('{"jsonrpc":"2.0","id":999999999999999999,"result":null}')
    assert largest is not None and largest.id == 10**18 - 1


@pytest.mark.parametrize(
    "message",
    [
        '{"jsonrpc": "2.0", "id": 1, "result": {}}',  # blanks: not how srvwire writes it
        '{"id":1,"jsonrpc":"2.0","result":{}}',  # another order
        '{"jsonrpc":"2.0","id":0,"result":{}}',  # no call of this client has id 0
        '{"jsonrpc":"2.0","id":-1,"result":{}}',
        '{"jsonrpc":"2.0","id":01,"result":{}}',  # not JSON
        '{"jsonrpc":"2.0","id":1.0,"result":{}}',
        '{"jsonrpc":"2.0","id":1e0,"result":{}}',
        '{"jsonrpc":"2.0","id":"1","result":{}}',
        '{"jsonrpc":"2.0","id":\u0661,"result":{}}',  # an Arabic-Indic one: int() would take it
        '{"jsonrpc":"2.0","id":1000000000000000000,"result":{}}',  # more digits than an id has
        '{"jsonrpc":"2.0","id":1,"result":{}} ',  # something after the final brace
        '{"jsonrpc":"2.0","id":1,"result":{}}\n',
        '{"jsonrpc":"2.0","id":1,"result":',
        '{"jsonrpc":"2.0","id":1,"error":{"code":1,"message":"m"}}',
        '{"jsonrpc":"2.0","method":"$/services","params":{"services":[]}}',
        '[{"jsonrpc":"2.0","id":1,"result":{}}]',
        '{"jsonrpc":"2.0","id":1,"result" :{}}',
        '{"jsonrpc":"1.0","id":1,"result":{}}',
    ],
)
def test_nothing_else_is_recognised(message: str) -> None:
    assert peek_reply(message) is None


def raw(message: str) -> RawReply:
    recognised = peek_reply(message)
    assert recognised is not None, message
    return recognised


@pytest.mark.parametrize(
    ("message", "result"),
    [
        ('{"jsonrpc":"2.0","id":3,"result":{"sum":3}}', {"sum": 3}),
        ('{"jsonrpc":"2.0","id":3,"result":1,"x":2}', 1),  # more members: ignored, as always
        ('{"jsonrpc":"2.0","id":3,"result":1,"result":2}', 2),  # the last one counts
        ('{"jsonrpc":"2.0","id":3,"result":[1.5],"id":3}', [1.5]),  # the same id again
        ('{"jsonrpc":"2.0","id":3,"result":{} }', {}),
    ],
)
def test_a_raw_reply_parses_as_any_reply_does(message: str, result: object) -> None:
    assert parse_raw_reply(raw(message)) == Response(3, result)
    assert parse_replies(message) == [Response(3, result)]


@pytest.mark.parametrize(
    ("message", "error"),
    [
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"error":{"code":1,"message":"m"}}',
            "Invalid reply: both 'result' and 'error'",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"method":"$/services","params":{}}',
            "Invalid reply: both 'result' and 'method'",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"id":4}',
            "Invalid reply: 'id' given twice (3 and 4)",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"id":"3"}',
            "Invalid reply: 'id' given twice (3 and '3')",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"id":3.0}',
            "Invalid reply: 'id' given twice (3 and 3.0)",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"jsonrpc":"1.0"}',
            "Invalid reply: 'jsonrpc' must be exactly \"2.0\"",
        ),
    ],
)
def test_a_raw_reply_that_is_not_the_response_it_opens_as_is_refused(
    message: str, error: str
) -> None:
    with pytest.raises(InvalidRequest) as caught:
        parse_raw_reply(raw(message))
    assert caught.value.message == error


@pytest.mark.parametrize(
    ("message", "error"),
    [
        (
            '{"jsonrpc":"2.0","id":3,"result":{]}',
            "Parse error: key must be a string at line 1 column 35",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":1,x}',
            "Parse error: key must be a string at line 1 column 36",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":"\\ud800"}',
            "Parse error: unexpected end of hex escape at line 1 column 41",
        ),
    ],
)
def test_a_raw_reply_that_is_not_json_is_a_parse_error(message: str, error: str) -> None:
    with pytest.raises(ParseError) as caught:
        parse_raw_reply(raw(message))
    assert caught.value.message == error
