"""Camera frames over srvwire: pixels as bytes (base64 on the wire) and the size limits.

Run it with ``python examples/camera_frames.py``: it serves a camera on a free port, fetches a
640 x 480 RGB frame with the limits raised on both sides, then shows what the default limit
does with the same frame.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import srvwire
from srvwire.models import build_service
from srvwire.parser import parse_service

CAPTURE_SRV = """\
uint32 width
uint32 height
---
uint32 width
uint32 height
string encoding  # rgb8: three bytes per pixel
uint32 step      # bytes per row
uint8[] data     # step * height bytes
float32 exposure # inf while the camera still adjusts
"""

# Built at run time, so a type checker only knows it is a service class (see docs/types.md).
Capture: Any = build_service(parse_service(CAPTURE_SRV, "my_camera", "Capture"))

# --8<-- [start:limits]
FRAME_LIMIT = 4 * 2**20  # 4 MiB; a 640 x 480 RGB frame is 921 600 bytes, 1 228 800 in base64


def camera_server() -> srvwire.Server:
    server = srvwire.Server(max_message_size=FRAME_LIMIT)  # what the server accepts

    @server.service("/capture", Capture)
    async def capture(request: Any) -> Any:
        step = request.width * 3
        return Capture.Response(
            width=request.width,
            height=request.height,
            encoding="rgb8",
            step=step,
            data=bytes(step * request.height),  # bytes in Python, base64 text in JSON
            exposure=math.inf,
        )

    return server


async def main() -> None:
    async with srvwire.serve(camera_server(), "127.0.0.1", 0) as running:
        # What the client accepts, and the largest request it sends.
        async with srvwire.connect(running.url, max_message_size=FRAME_LIMIT) as client:
            vga = Capture.Request(width=640, height=480)
            frame = await client.call("/capture", vga, srv_type=Capture)
            print(f"{frame.encoding} {frame.width}x{frame.height}: {len(frame.data)} bytes")
            print(f"exposure: {frame.exposure}")
        async with srvwire.connect(running.url) as small:  # the default limit, 1 MiB
            try:
                await small.call("/capture", vga, srv_type=Capture)
            except srvwire.ConnectionLost as exc:
                print(f"default limit: closed with {exc.data['close_code']}, {exc.message}")


# --8<-- [end:limits]

if __name__ == "__main__":
    asyncio.run(main())
