"""The srvwire side's client: ``srvwire.client.connect`` and ``client.call``, as a user writes them.

Each call passes a typed ``RobotStateQuery.Request`` (built once) and gets the typed
``Response`` back, with the call's deadline enforced by the client: the client's default,
given once to ``connect``. The only option changed from the defaults is
``max_message_size``, so W4's 1.7 MB replies are accepted.
``--transport picows`` connects on the native transport instead of ``websockets``;
``--keep-heap`` calls ``srvwire.keep_freed_heap()`` first.
"""

from __future__ import annotations

import argparse
import functools
from contextlib import AsyncExitStack

from srvwire.client import connect

from common import CALL_TIMEOUT, MAX_MESSAGE, SERVICE
from typed import make_request, values_of
from workloads import Adapter, Call, main


async def open_connection(url: str, stack: AsyncExitStack, transport: str) -> Call:
    client = await stack.enter_async_context(
        connect(url, timeout=CALL_TIMEOUT, max_message_size=MAX_MESSAGE, transport=transport)
    )
    return functools.partial(client.call, SERVICE)  # the deadline: the client's, set above


if __name__ == "__main__":
    # workloads.main reads every option; the transport is needed before, to open connections.
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--transport", default="websockets")
    pre.add_argument("--keep-heap", action="store_true")
    known = pre.parse_known_args()[0]
    transport = known.transport
    if known.keep_heap:  # imported only then: the harness also runs older srvwire with this script
        from srvwire.heap import keep_freed_heap

        keep_freed_heap()
    opener = functools.partial(open_connection, transport=transport)
    main(Adapter(opener, make_request, values_of), __doc__ or "")
