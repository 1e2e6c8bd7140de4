"""A server that authenticates its callers and lets only some of them move the robot."""

import asyncio
import os
import time
from typing import Any

import srvwire

Trigger = srvwire.load_service("std_srvs/srv/Trigger")
SetBool = srvwire.load_service("std_srvs/srv/SetBool")

# --8<-- [start:server]
# Each token stands for an identity; the scopes say what it may call. In a real deployment
# the tokens come from a secret store or the environment, never from the source.
OPERATOR_TOKEN = os.environ.get("ROBOT_OPERATOR_TOKEN", "operator-secret")
VIEWER_TOKEN = os.environ.get("ROBOT_VIEWER_TOKEN", "viewer-secret")

auth = srvwire.TokenAuth(
    {
        OPERATOR_TOKEN: srvwire.Identity("operator", scopes={"robot:write"}),
        VIEWER_TOKEN: "viewer",  # a plain name: an identity with no scopes
    }
)
server = srvwire.Server(auth=auth, origins=["https://robot.example.com"])


@server.service("/status", Trigger)
async def status(request: Any, context: srvwire.Context) -> Any:
    return {"success": True, "message": f"hello {context.identity.name}"}


@server.service("/motors", SetBool, scopes={"robot:write"})
async def motors(request: Any) -> Any:
    return {"success": True, "message": "on" if request.data else "off"}


# --8<-- [end:server]


# --8<-- [start:authenticator]
async def badge_reader(handshake: srvwire.Handshake) -> srvwire.Identity:
    """An authenticator of your own: read what you need from the opening request."""
    badge = handshake.header("X-Badge")
    if badge != "42":
        raise srvwire.Unauthenticated("show badge 42")
    # expires: past it, the connection's calls are answered UNAUTHENTICATED.
    return srvwire.Identity("badge 42", scopes={"robot:write"}, expires=time.time() + 3600)


# --8<-- [end:authenticator]


async def main() -> None:
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        # --8<-- [start:client]
        async with srvwire.connect(running.url, token=VIEWER_TOKEN) as viewer:
            print(sorted(viewer.services))  # only what this identity may call
            print((await viewer.call("/status")).message)
            try:
                await viewer.call("/motors", {"data": True})
            except srvwire.PermissionDenied as exc:
                print(exc.message)
        async with srvwire.connect(running.url, token=OPERATOR_TOKEN) as operator:
            print((await operator.call("/motors", {"data": True})).message)
        # --8<-- [end:client]
        try:
            await srvwire.connect(running.url, token="a guess")
        except srvwire.ServiceUnavailable as exc:
            print(exc.message.split(": ", 1)[1])
    badged = srvwire.Server(auth=badge_reader)
    badged.add_service("/motors", SetBool, motors, scopes={"robot:write"})
    async with srvwire.serve(badged, "127.0.0.1", 0) as running:
        async with srvwire.connect(running.url, headers={"X-Badge": "42"}) as client:
            print((await client.call("/motors", {"data": False})).message)


asyncio.run(main())
