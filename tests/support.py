"""Helpers shared by the tests: one timeout factor, and where the shared corpora live."""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import ModuleType
from typing import IO, Any

import pytest
import trustme

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"

# Every timeout in the tests is multiplied by this factor, so a slow machine can raise them all
# at once (SRVWIRE_TEST_TIMEOUT_FACTOR=3) instead of any single test growing its own margin.
TIMEOUT_FACTOR = float(os.environ.get("SRVWIRE_TEST_TIMEOUT_FACTOR", "1"))


def scaled(seconds: float) -> float:
    """Return ``seconds`` multiplied by the suite's timeout factor."""
    return seconds * TIMEOUT_FACTOR


def ros_test_interfaces() -> Path:
    """Return the folder of ROS 2's own test interfaces, or fail saying where it should be.

    The corpus is not part of this repository: it sits in ``shared/ros_test_interfaces`` beside
    the checkout (CI puts it there), or wherever ``SRVWIRE_ROS_TEST_INTERFACES`` points.
    """
    configured = os.environ.get("SRVWIRE_ROS_TEST_INTERFACES")
    folder = Path(configured) if configured else ROOT.parent / "shared" / "ros_test_interfaces"
    if not (folder / "msg").is_dir():
        pytest.fail(
            f"ROS 2's test interface corpus is not at {folder}: these conformance tests read it "
            "from shared/ros_test_interfaces beside the checkout, or from the folder named by "
            "SRVWIRE_ROS_TEST_INTERFACES",
            pytrace=False,
        )
    return folder


def record_calls(monkeypatch: pytest.MonkeyPatch, module: ModuleType, name: str) -> list[Any]:
    """Wrap ``module.name`` so that each call's arguments are recorded; return the record."""
    calls: list[Any] = []
    real = getattr(module, name)

    def recording(*args: Any) -> Any:
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(module, name, recording)
    return calls


def run_benchmark(script: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Run a benchmark script with ``args`` as a smoke test does (see :func:`run_python`)."""
    return run_python(str(script), *args)


def run_python(*args: str) -> subprocess.CompletedProcess[str]:
    """Run this Python with ``args`` in a process of its own: from the project's root, its
    output captured, within two (scaled) minutes; fail with that output unless it exits 0."""
    result = subprocess.run(
        [sys.executable, *args],
        capture_output=True,
        text=True,
        timeout=scaled(120),
        cwd=ROOT,
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result


def import_each_first(root: Path, package: str, modules: Iterable[str], use: str) -> None:
    """Import each of ``package``'s ``modules`` first, in a fresh interpreter each (working in
    ``root``), then run ``use``: every order in which a program may import generated modules."""
    for first in modules:
        ran = subprocess.run(
            [sys.executable, "-c", f"import {package}.{first}\n{use}"],
            cwd=root,
            capture_output=True,
            text=True,
            check=False,
        )
        assert (ran.returncode, ran.stderr) == (0, ""), first


def write_package(root: Path, package: str, sources: dict[str, str]) -> Path:
    """Write generated ``sources`` (module name -> text) as the package ``package`` in ``root``."""
    folder = root / package
    folder.mkdir()
    (folder / "__init__.py").write_text("", encoding="utf-8")
    for module, source in sources.items():
        (folder / f"{module}.py").write_text(source, encoding="utf-8")
    return folder


def tls_on_localhost(tls: bool) -> tuple[ssl.SSLContext | None, ssl.SSLContext | None]:
    """The server's and the client's TLS contexts for 127.0.0.1, from a new certificate
    authority (trustme); with ``tls`` False, neither."""
    if not tls:
        return None, None
    ca = trustme.CA()
    server_ssl = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("127.0.0.1").configure_cert(server_ssl)
    client_ssl = ssl.create_default_context()
    ca.configure_trust(client_ssl)
    return server_ssl, client_ssl


def interruptible() -> None:
    """In a child before it runs: SIGINT to its default action, so that Ctrl-C reaches it as
    from a terminal. A shell starts a background job (the suite run with `&` from a script)
    with SIGINT ignored, and its children inherit that, so Python would not raise
    KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_interruptible(*args: str) -> subprocess.Popen[str]:
    """Start ``python *args`` with its output and errors piped as text, Ctrl-C reaching it as
    from a terminal (:func:`interruptible`)."""
    return subprocess.Popen(
        [sys.executable, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=interruptible,
    )


GOAL_SERVER = ROOT / "tests" / "servers" / "goal_server.py"


class Lines:
    """The lines a child process writes to one of its pipes, read by a thread as they come."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream
        self.queue: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.stream:
            self.queue.put(line)
        self.queue.put("")  # the end of the stream

    def expect(self, wanted: str) -> None:
        """Wait for a line that starts with ``wanted``; fail if the stream ends first (or,
        as a backstop on a hung child, after a minute)."""
        while True:
            line = self.queue.get(timeout=scaled(60))
            self.seen.append(line)
            if line == "":
                pytest.fail(f"the stream ended before {wanted!r}: {''.join(self.seen)}")
            if line.startswith(wanted):
                return

    def close(self) -> str:
        """Once the child ended: everything it wrote, and close the pipe."""
        self.reader.join(scaled(60))
        while not self.queue.empty():
            self.seen.append(self.queue.get())
        self.stream.close()
        return "".join(self.seen)


@contextlib.contextmanager
def serve_goal_server() -> Iterator[tuple[str, Lines]]:
    """``srvwire serve tests/servers/goal_server.py`` in a process: its URL and its output."""
    process = subprocess.Popen(
        [sys.executable, "-m", "srvwire", "serve", str(GOAL_SERVER), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert process.stdout is not None
    lines = Lines(process.stdout)
    try:
        first = lines.queue.get(timeout=scaled(60))
        match = re.fullmatch(r"serving 0 services and 1 action on (ws://[^ ,]+).*\n", first)
        assert match, first
        yield match.group(1), lines
    finally:
        process.kill()
        process.wait()
        lines.close()
