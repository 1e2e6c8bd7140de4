"""A package of your own, a server that has its files, and a client that has none.

The server finds ``my_robot`` through ``search_path=``, which adds to the bundled packages, so
the ``std_msgs`` and ``geometry_msgs`` it nests are found too. The client is given no search
path: it builds ``my_robot``'s types from the server's description, and the classes it gets
are the process's, whichever way they were loaded.

Run it: ``python examples/one_class_per_type.py``.
"""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from typing import Any

import srvwire

FILES = {
    "my_robot/msg/RobotStatus.msg": (
        "# What the robot says about itself.\n"
        "std_msgs/Header header\n"
        "geometry_msgs/Pose pose\n"
        "string[] faults\n"
    ),
    "my_robot/srv/GetStatus.srv": "string robot\n---\nRobotStatus status\nbool ok\n",
}


def write_package(folder: Path) -> None:
    for relative, text in FILES.items():
        path = folder / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


# --8<-- [start:server]
def build_server(interfaces: Path) -> srvwire.Server:
    # search_path adds to the default path: std_msgs and geometry_msgs stay visible.
    GetStatus: Any = srvwire.load_service("my_robot/srv/GetStatus", search_path=[interfaces])
    server = srvwire.Server()

    @server.service("/get_status", GetStatus)
    async def get_status(request: Any) -> Any:
        response = GetStatus.Response(ok=True)
        response.status.header.frame_id = request.robot
        return response

    return server


# --8<-- [end:server]


async def main() -> None:
    with tempfile.TemporaryDirectory() as folder:
        write_package(Path(folder))
        server = build_server(Path(folder))
        async with srvwire.serve(server, "127.0.0.1", 0) as running:
            # --8<-- [start:client]
            async with srvwire.connect(running.url) as client:  # no search path at all
                reply = await client.call("/get_status", {"robot": "base"})
                print(f"{type(reply).__name__}: ok={reply.ok} frame={reply.status.header.frame_id}")

                # One class per type: the default path, another search path, the server.
                Header: Any = srvwire.load_message("std_msgs/Header")
                Pose = srvwire.InterfaceLoader([folder]).load_message("geometry_msgs/Pose")
                GetStatus: Any = await client.service_type("/get_status")
                RobotStatus = type(GetStatus.Response().status)
                status = RobotStatus(header=Header(frame_id="map"), pose=Pose())
                print(f"built from three sources: {status.header.frame_id}")
                print(f"same Header class: {type(reply.status.header) is Header}")
            # --8<-- [end:client]


if __name__ == "__main__":
    asyncio.run(main())
