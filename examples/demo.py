"""Run the robot-state tutorial end to end: what ``make demo`` does.

It starts ``robot_state_server.py`` on a free port in a child process, reads the port from the
line the server logs once it listens, runs ``robot_command_client.py``'s sequence against it in
this process (the services, then the ``/calibrate`` action with its progress; the calibration
asks for 1 s, or ``$DEMO_CALIBRATION_TIME``), then publishes a few joint states with
``joint_state_publisher.py`` (a topic the server subscribes to), and stops the server whatever
happened. The server's own log is shown only when something went wrong.
"""

from __future__ import annotations

import logging
import os
import queue
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO

import joint_state_publisher
import robot_command_client

HERE = Path(__file__).resolve().parent
SERVER = HERE / "robot_state_server.py"
URL_LINE = re.compile(r"serving \d+ services?(?: and \d+ actions?)? on (ws://\S+)")
STARTUP_TIMEOUT = 20.0  # seconds for the server to import srvwire and start listening
SHUTDOWN_TIMEOUT = 5.0  # seconds for it to stop after SIGTERM before it is killed
CALIBRATION_TIME = os.environ.get("DEMO_CALIBRATION_TIME", "1")  # seconds: the action's goal


class ServerProcess:
    """``robot_state_server.py --port 0`` in a child process, its log collected as it comes."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, str(SERVER), "--port", "0"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.log: list[str] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        assert self.process.stderr is not None
        threading.Thread(target=self._collect, args=(self.process.stderr,), daemon=True).start()

    def _collect(self, stream: IO[str]) -> None:
        # Read the log for as long as the server runs, so that it never blocks on a full pipe.
        for line in stream:
            self.log.append(line)
            self._lines.put(line)
        self._lines.put(None)

    def wait_for_url(self, timeout: float) -> str:
        """Return the URL the server logs once it listens, or raise RuntimeError."""
        while True:
            try:
                line = self._lines.get(timeout=timeout)
            except queue.Empty:
                raise RuntimeError(f"the server did not listen within {timeout:g} s") from None
            if line is None:
                status = self.process.wait()
                raise RuntimeError(f"the server exited with status {status} before listening")
            if match := URL_LINE.search(line):
                return match.group(1)

    def stop(self) -> None:
        """Ask the server to stop (SIGTERM), as Ctrl-C would; kill it if it does not."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=SHUTDOWN_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def main() -> int:
    server = ServerProcess()
    status = 1
    try:
        url = server.wait_for_url(STARTUP_TIMEOUT)
        print(f"make demo: robot_state_server.py is serving on {url}", flush=True)
        print("make demo: robot_command_client.py runs the tutorial's sequence:", flush=True)
        # The client logs each answer; here, to stdout with the rest, so that it pipes as one.
        logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
        # A short calibration, so that the demo stays quick; the robot's own takes 5 s.
        status = robot_command_client.main(["--url", url, "--calibration-time", CALIBRATION_TIME])
        if status == 0:
            print(
                "make demo: joint_state_publisher.py publishes on /joint_states, "
                "which the server subscribes to:",
                flush=True,
            )
            status = joint_state_publisher.main(["--url", url, "--count", "3", "--rate", "100"])
    except RuntimeError as exc:
        print(f"make demo: {exc}", file=sys.stderr)
    finally:
        server.stop()
    if status == 0:
        print("make demo: the server has stopped; every call was answered.", flush=True)
    else:
        print("make demo: FAILED. The server's log:", *server.log, sep="\n", file=sys.stderr)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
