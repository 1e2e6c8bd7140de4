"""Calling the example server by hand with the real ``wscat``, as docs/wscat.md shows it.

wscat is a Node.js program; ``make test`` installs it from ``package.json`` into ``node_modules``
(``npm ci``). It prints what it receives the way a person sees it only when it runs in a
terminal, so these tests give it one: a pseudo-terminal they type into and read from, waiting
for each expected reply (never for a fixed time).

docs/wscat.md is a transcript: every line starting with ``> `` is typed, every line starting
with ``< `` is what must come back. The first test replays it, so the guide cannot drift from
what the server really says.
"""

from __future__ import annotations

import fcntl
import json
import os
import pty
import re
import selectors
import shutil
import signal
import struct
import subprocess
import termios
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from support import ROOT, scaled
from test_examples import start_server

WSCAT = ROOT / "node_modules" / ".bin" / "wscat"
GUIDE = ROOT / "docs" / "wscat.md"
README = ROOT / "README.md"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
TEXT_BLOCK = re.compile(r"^```text\n(.*?)^```", re.MULTILINE | re.DOTALL)
GOAL_ID = re.compile(r'"goal_id":"[0-9a-f-]{36}"')
EPOCH = re.compile(r'"epoch":"[0-9a-f]{16}"')


def same_goal_ids(line: str) -> str:
    """A received line with its goal id, a new UUID each time, written as one fixed id (and
    a topic's epoch, random too, as one fixed epoch)."""
    return EPOCH.sub('"epoch":"(random)"', GOAL_ID.sub('"goal_id":"(a uuid)"', line))


def wscat_command() -> list[str]:
    """Return the command that runs the project's wscat, or fail saying how to install it."""
    if shutil.which("node") is None:
        pytest.fail(
            "Node.js is not installed: tests/test_wscat.py drives the real wscat, a Node.js "
            "program. Install node and npm, then run `make test` (it runs `npm ci`).",
            pytrace=False,
        )
    if not WSCAT.exists():
        pytest.fail(
            f"wscat is not installed at {WSCAT.relative_to(ROOT)}: `make test` installs it "
            "from package.json with `npm ci`; run that (or `npm ci` by hand) first.",
            pytrace=False,
        )
    return [str(WSCAT), "--no-color"]


def transcript(markdown: str) -> list[str]:
    """The ``> `` and ``< `` lines of every ``text`` code block, in order."""
    return [
        line
        for block in TEXT_BLOCK.findall(markdown)
        for line in block.splitlines()
        if line.startswith(("> ", "< "))
    ]


class Terminal:
    """A program running in a pseudo-terminal, typed into and read from like a person would."""

    def __init__(self, argv: list[str]) -> None:
        self.master, follower = pty.openpty()
        # A wide window, so that readline never wraps the long JSON lines it echoes.
        fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 1000, 0, 0))
        try:
            self.process = subprocess.Popen(
                argv,
                stdin=follower,
                stdout=follower,
                stderr=follower,
                start_new_session=True,  # its own process group, killed whole in close()
                env={**os.environ, "NO_COLOR": "1"},
            )
        finally:
            os.close(follower)
        self.selector = selectors.DefaultSelector()
        self.selector.register(self.master, selectors.EVENT_READ)
        self.output = ""  # everything it printed so far, without escape sequences
        self.seen = 0  # how many received lines expect_reply has handed out
        self.closed = False  # whether the program has let go of the terminal

    def type_line(self, text: str) -> None:
        os.write(self.master, text.encode() + b"\r")

    def press_ctrl_c(self) -> None:
        os.write(self.master, b"\x03")

    def screen(self) -> list[str]:
        """The lines as the terminal shows them: a carriage return starts its line over."""
        lines = self.output.replace("\r\n", "\n").split("\n")
        return [line.rsplit("\r", 1)[-1] for line in lines]

    def received(self) -> list[str]:
        """What wscat printed as received: the lines that start with ``< ``."""
        return [line[2:] for line in self.screen() if line.startswith("< ")]

    def read_until(self, done: Callable[[], bool], timeout: float, what: str) -> None:
        """Read until ``done()`` is true; fail naming ``what`` if ``timeout`` passes first."""
        deadline = time.monotonic() + timeout
        while not done():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.fail(f"wscat did not show {what} within {timeout:g} s")
            if not self.selector.select(remaining):
                continue
            try:
                chunk = os.read(self.master, 65536)
            except OSError:  # EIO: every process holding the terminal is gone
                chunk = b""
            if not chunk:
                self.closed = True
                if not done():
                    self.fail(f"wscat exited before showing {what}")
                return
            self.output += ANSI.sub("", chunk.decode(errors="replace"))

    def expect_reply(self, timeout: float) -> dict[str, Any]:
        """Wait for the next line wscat shows as received and decode its JSON."""
        self.read_until(lambda: len(self.received()) > self.seen, timeout, "a reply")
        line = self.received()[self.seen]
        self.seen += 1
        decoded: dict[str, Any] = json.loads(line)
        return decoded

    def wait_for_exit(self, timeout: float) -> int:
        """Wait until the program closes the terminal and exits; return its exit status."""
        self.read_until(lambda: self.closed, timeout, "its exit")
        return self.process.wait(timeout)

    def fail(self, why: str) -> None:
        pytest.fail(f"{why}; the terminal shows:\n" + "\n".join(self.screen()), pytrace=False)

    def close(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self.selector.close()
        os.close(self.master)


@pytest.fixture
def wscat() -> Iterator[Terminal]:
    """wscat in a terminal, connected to the example server; both are killed afterwards."""
    command = wscat_command()
    with start_server() as server:
        terminal = Terminal([*command, "-c", server.url])
        try:
            terminal.read_until(
                lambda: "Connected (press CTRL+C to quit)" in terminal.output,
                scaled(10),
                "'Connected'",
            )
            yield terminal
        finally:
            terminal.close()


def test_the_guide_is_what_wscat_shows(wscat: Terminal) -> None:
    lines = transcript(GUIDE.read_text(encoding="utf-8"))
    assert len(lines) > 30, "docs/wscat.md should hold the whole session"
    for line in lines:
        if line.startswith("> "):
            wscat.type_line(line[2:])
        else:
            # A typed line followed by no "<" line (a notification) gets no reply: the next
            # reply must then be the one the guide shows for the line after it. An action's
            # goal id is new each time: any UUID stands for the one the guide shows (and
            # any epoch for a topic's).
            reply = wscat.expect_reply(scaled(5))
            assert json.loads(same_goal_ids(json.dumps(reply, separators=(",", ":")))) == (
                json.loads(same_goal_ids(line[2:]))
            )


def test_a_half_typed_line_gets_a_parse_error(wscat: Terminal) -> None:
    wscat.expect_reply(scaled(5))  # $/services
    wscat.expect_reply(scaled(5))  # $/topics
    wscat.type_line('{"jsonrpc": "2.0", "id": 1, "method": "/get_robot_state", "par')
    reply = wscat.expect_reply(scaled(5))
    assert reply["id"] is None
    assert reply["error"]["code"] == -32700
    assert reply["error"]["data"] == {"status": "PARSE_ERROR"}
    # The connection is still there.
    wscat.type_line('{"jsonrpc": "2.0", "id": 2, "method": "get_robot_state"}')
    reply = wscat.expect_reply(scaled(5))
    assert reply["id"] == 2
    assert reply["result"]["message"] == "Unknown query type: "


def test_ctrl_c_leaves_wscat(wscat: Terminal) -> None:
    wscat.expect_reply(scaled(5))
    wscat.press_ctrl_c()
    assert wscat.wait_for_exit(scaled(5)) == 0


def test_the_readme_quotes_the_guide() -> None:
    readme = README.read_text(encoding="utf-8")
    section = readme.split("## Calling by hand with wscat", 1)[1].split("\n## ", 1)[0]
    quoted = transcript(section)
    assert quoted, "the README's wscat section should show a short session"
    guide = transcript(GUIDE.read_text(encoding="utf-8"))
    assert [line for line in quoted if line not in guide] == []
    assert "npx wscat -c ws://localhost:8765" in section
