"""The typed floor client on picows: the floor's typed JSON-RPC 2.0 caller on ``picows``' callbacks.

It is built like the raw picows client (``picows_client.py``: pending futures by integer id,
each resolved inside ``on_ws_frame`` as its reply arrives, picows' synchronous ``send`` per call,
no reader task) and does exactly the typed work of the floor's client on ``websockets``
(``floor_client.py``), with its serializer, validator and request prefix: each call takes a
generated ``RobotStateQuery.Request``, serializes it with pydantic with ``_meta.timeout``
spliced in, waits for the reply, and validates the reply's ``result`` into a typed
``Response``. Every reply is decoded with pydantic_core; one without a pending id (srvwire's
``$/services`` notification) is dropped; an error reply raises a plain ``RuntimeError``.

The wait is ``asyncio.wait_for(future, CALL_TIMEOUT)``, the deadline srvwire's design has its
client enforce, at its cheapest: on Python 3.11 the future is srvwire's ``Answer``, whose reply
releases ``wait_for``'s waiter at once, so the caller wakes at the next loop turn instead of
the one after (on 3.12+, where ``wait_for`` awaits the future itself, it is a plain future).
With ``--no-deadline`` (``floor-picows-bare`` in ``run.py``) a plain future is awaited bare,
so a run beside the default says what the deadline costs on this transport.

With ``--cork`` (``floor-picows-corked``) the calls made in one turn of the event loop are held
and written together at the turn's end (or once they pass ``CLIENT_WRITE_AT`` bytes), each
masked with a fresh key by websockets' C ``apply_mask``: one system call for them all, as
srvwire's client on picows writes the calls of a turn. As there, the first call after a read
that brought one reply is written at once (one call at a time, nothing would join it), and a
lone call goes through picows' ``send``, which frames and masks it in C.
"""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack
from typing import Any

from picows import ws_connect
from pydantic_core import from_json

from srvwire.link import Answer

from common import CALL_TIMEOUT, MAX_MESSAGE
from floor_client import PARAMS_PREFIX, serialize_request, validate_response
from picows_client import HoldingCaller, asked
from typed import make_request, values_of
from workloads import Adapter, Call, main


class TypedCaller(HoldingCaller):
    """Pending calls by id over one connection, resolved as their replies arrive: raw picows'
    caller (its connection, its close, its futures failed when the connection ends, its
    holding of a turn's calls), typed."""

    decode = staticmethod(from_json)

    async def call(self, request: Any) -> Any:  # type: ignore[override]
        fields = serialize_request(request, by_alias=True)  # b'{"query_type":...}'
        rest = fields[1:] if fields == b"{}" else b"," + fields[1:]
        request_id = next(self._ids)
        message = b'{"jsonrpc":"2.0","id":' + str(request_id).encode() + PARAMS_PREFIX + rest + b"}"
        future: asyncio.Future[Any] = (
            Answer(loop=self._loop) if self._deadline else self._loop.create_future()
        )
        self._pending[request_id] = future
        try:
            self.write(message)
            if self._deadline:
                reply = await asyncio.wait_for(future, CALL_TIMEOUT)
            else:
                reply = await future
        finally:
            self._pending.pop(request_id, None)
        if "error" in reply:
            raise RuntimeError(f"error reply: {reply['error']}")
        return validate_response(reply["result"])


def adapter(deadline: bool, cork: bool = False) -> Adapter:
    """How the workloads call through this client, with or without a deadline on each wait,
    each call written alone or the calls of a turn together."""

    async def open_connection(url: str, stack: AsyncExitStack) -> Call:
        _, caller = await ws_connect(
            lambda: TypedCaller(deadline, cork), url, max_frame_size=MAX_MESSAGE
        )
        stack.push_async_callback(caller.close)
        return caller.call

    return Adapter(open_connection, make_request, values_of)


def deadline_asked() -> bool:
    """Whether the command line leaves the deadline on (no ``--no-deadline``)."""
    return not asked().no_deadline


if __name__ == "__main__":
    main(adapter(deadline_asked(), asked().cork), __doc__ or "")
