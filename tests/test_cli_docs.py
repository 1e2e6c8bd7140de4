"""Every ``srvwire ...`` sample in docs/ runs, and prints what the page shows.

Most are in docs/cli.md; every page of docs/ is read, so that a sample on a new page runs too.
The samples are the lines of a page's ``console`` blocks that start with ``$ srvwire `` (the
lines after one, up to the next ``$ ``, are its output; a following ``$ echo $?`` gives its exit
code) and the lines of its ``sh`` blocks that start with ``srvwire ``. Each runs through
``main(argv)`` in a folder holding the files the page assumes. Samples that talk to a server
get ``$SRVWIRE_URL``: the robot example's ``build_server()`` for the robot's services and for
``srvwire service`` and ``srvwire topic``, and a small server of the page's other services
(``/add_two_ints``, ``/trigger``, ...) for the rest. What cannot run here is listed in
``NOT_RUN``, with the reason.
"""

from __future__ import annotations

import asyncio
import importlib.util
import io
import re
import shlex
import socket
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from srvwire.cli import main
from srvwire.loader import load_service
from srvwire.server import Server
from support import ROOT
from test_cli import start_in_thread, write

PAGES = sorted((ROOT / "docs").glob("*.md"))
ROBOT_SERVICES = ("/get_robot_state", "/execute_robot_command")

NOT_RUN = {
    "srvwire serve my_app.services:server --port 9000": (
        "serves until Ctrl-C; test_cli.py's test_serve_a_file_until_ctrl_c runs serve in a "
        "child process and checks these lines"
    ),
    "srvwire serve examples/robot_state_server.py:build_server --factory": (
        "serves until Ctrl-C; test_cli.py's serve tests cover --factory"
    ),
    "srvwire topic hz /joint_states": (
        "prints the rate until Ctrl-C; test_cli_topics.py's test_hz_measures_the_rate runs it "
        "with --count"
    ),
    "srvwire serve app.py --host 0.0.0.0 --certfile cert.pem --keyfile key.pem "
    "--client-ca clients.pem": (
        "serves until Ctrl-C, with certificates of its own; test_cli_security.py's "
        "test_serve_with_client_certificates_may_listen_publicly serves the same way"
    ),
    "srvwire serve app.py --certfile cert.pem --keyfile ca.pem": (
        "needs the TLS files; test_cli_security.py's "
        "test_serve_names_a_tls_file_it_cannot_use_and_what_is_wrong checks this line"
    ),
    'srvwire call /status --url wss://robot.example.com:8765 --cacert ca.pem --token "$TOKEN"': (
        "needs a TLS server with its certificates; test_cli_security.py's "
        "test_serve_tls_and_call_it_with_the_ca calls one with --cacert"
    ),
    "srvwire serve app.py --port 8765 --origin https://robot.example.com": (
        "serves until Ctrl-C; test_cli_security.py's test_serve_refuses_a_bad_origin and "
        "test_nginx.py serve with --origin"
    ),
}
"""Samples that are not run, each with the reason."""

OUTPUT_NOT_COMPARED = {
    "srvwire call /get_robot_state \"{query_type: position}\" --json | jq '.values[0]'": (
        "the output is jq's; the srvwire part runs and must succeed"
    ),
    "srvwire call /slow_service --timeout 0.5": (
        "the client's deadline and the server's (sent with the call) race, and the server's "
        "words differ; the exit code, 4, is checked"
    ),
}
"""Samples that run, but whose output is not compared, each with the reason."""


@dataclass(frozen=True)
class Sample:
    page: str  # its file name in docs/
    line: int
    command: str  # without the leading "$ "
    output: str | None  # None: the page shows none to compare (a sh block)
    exit_code: int | None  # from a following "$ echo $?"; None: 0, or not 0 after an error line


def samples() -> list[Sample]:
    return [sample for page in PAGES for sample in page_samples(page)]


def page_samples(page: Path) -> list[Sample]:
    found: list[Sample] = []
    lines = page.read_text(encoding="utf-8").splitlines()
    language = None
    for number, line in enumerate(lines):
        fence = re.match(r"^```(\S*)", line)  # ```sh, or ```{.python title="..."}
        if fence:
            language = None if language is not None else fence.group(1) or "text"
            continue
        if language == "sh" and line.startswith("srvwire "):
            found.append(Sample(page.name, number + 1, line, None, None))
        elif language == "console" and line.startswith("$ srvwire "):
            output: list[str] = []
            end = number + 1
            while not lines[end].startswith(("$ ", "```")):
                output.append(lines[end])
                end += 1
            code = None
            if lines[end] == "$ echo $?":
                code = int(lines[end + 1])
            shown = "".join(f"{o}\n" for o in output)
            found.append(Sample(page.name, number + 1, line[2:], shown, code))
    return found


def test_the_page_has_samples() -> None:
    commands = {sample.command for sample in samples()}
    assert len(commands) > 30
    assert set(NOT_RUN) | set(OUTPUT_NOT_COMPARED) <= commands  # no stale exceptions


def load_example(name: str) -> Any:
    path = ROOT / "examples" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"cli_docs_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@dataclass(frozen=True)
class Servers:
    robot: str
    other: str


@pytest.fixture(scope="module")
def servers() -> Iterator[Servers]:
    robot: Server = load_example("robot_state_server").build_server()
    add_two_ints: Any = load_service("example_interfaces/srv/AddTwoInts")
    trigger: Any = load_service("std_srvs/srv/Trigger")

    def add(request: Any) -> Any:
        return add_two_ints.Response(sum=request.a + request.b)

    def done(request: Any) -> Any:
        return trigger.Response(success=True, message="done")

    async def hang(request: Any) -> Any:
        await asyncio.Event().wait()  # never set: only the deadline ends this call

    other = Server(grace_period=0)
    other.add_service("/add_two_ints", add_two_ints, add)
    other.add_service("/trigger", trigger, done)
    other.add_service("/calibrate", trigger, done)
    other.add_service("/slow_service", trigger, hang)
    robot_url, stop_robot = start_in_thread(robot)
    other_url, stop_other = start_in_thread(other)
    yield Servers(robot_url, other_url)
    stop_other()
    stop_robot()


@pytest.fixture
def workspace(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The current folder the samples assume: the files they name, and nothing else."""
    write(tmp_path, "request.yaml", "{a: 1, b: 2}\n")
    write(tmp_path, "my_robot/msg/Counter.msg", "int32 count 1.5\n")
    write(tmp_path, "my_robot/srv/Rename.srv", "string name\n---\nbool ok\n")
    write(tmp_path, "base_robot/msg/Point.msg", "float64 x\nfloat64 y\n")
    write(tmp_path, "base_robot/msg/Lost.msg", "# Where it was lost.\nPointt p\n")
    for relative, text in (
        ("msg/Pose.msg", "float64 x\nfloat64 y\n"),
        ("msg/Status.msg", "string word\n"),
        ("srv/Move.srv", "Pose target\n---\nbool ok\n"),
        ("srv/Rename.srv", "string name\n---\nbool ok\n"),
        ("action/Go.action", "Pose target\n---\nbool reached\n---\nfloat64 left\n"),
    ):
        write(tmp_path, f"interfaces/my_robot/{relative}", text)
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("SRVWIRE_INTERFACE_PATH", raising=False)
    return tmp_path


def closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port


def run(capsys: pytest.CaptureFixture[str], command: str) -> tuple[int, str, str]:
    """Run one shell line through main(): ``$(srvwire ...)`` and ``< FILE`` as a shell would."""

    def substitute(match: re.Match[str]) -> str:
        code, out, err = run(capsys, match.group(1))
        assert (code, err) == (0, ""), (match.group(1), err)
        return shlex.quote(out.rstrip("\n"))

    command = re.sub(r'"\$\((srvwire [^)]*)\)"', substitute, command)
    argv = shlex.split(command, comments=True)  # a "# ..." after a sample explains it
    assert argv[0] == "srvwire"
    argv = argv[1:]
    stdin = sys.stdin
    if "<" in argv:
        at = argv.index("<")
        stdin = io.StringIO(Path(argv[at + 1]).read_text(encoding="utf-8"))
        del argv[at : at + 2]
    if "|" in argv:
        argv = argv[: argv.index("|")]
    capsys.readouterr()
    original, sys.stdin = sys.stdin, stdin
    try:
        code = main(argv)
    finally:
        sys.stdin = original
    out, err = capsys.readouterr()
    return code, out, err


def expected_pattern(output: str) -> re.Pattern[str]:
    """The page's output as a pattern: a line ``...`` stands for any lines."""
    parts = [
        r"(?:.*\n)*?" if line.strip() == "..." else re.escape(line) + r"\n"
        for line in output.splitlines()
    ]
    return re.compile("".join(parts))


@pytest.mark.parametrize(
    "sample",
    [s for s in samples() if s.command not in NOT_RUN],
    ids=lambda s: f"{s.page}:{s.line}",
)
def test_sample(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    workspace: Path,
    servers: Servers,
    sample: Sample,
) -> None:
    words = sample.command.split()
    robot = words[1] in ("service", "topic", "action") or (
        words[1] == "call" and words[2] in ROBOT_SERVICES
    )
    monkeypatch.setenv("SRVWIRE_URL", servers.robot if robot else servers.other)
    command, output = sample.command, sample.output
    if "ws://localhost:9999" in command:  # a server that is not there: a port nobody uses
        port = closed_port()
        command = command.replace("ws://localhost:9999", f"ws://127.0.0.1:{port}")
        assert output is not None
        output = output.replace("localhost:9999", f"127.0.0.1:{port}")
        output = output.replace("9999)", f"{port})")
    code, out, err = run(capsys, command)
    if sample.exit_code is not None:
        assert code == sample.exit_code, out + err
    elif output is not None and "srvwire: error:" in output:
        assert code != 0, out + err
    else:
        assert code == 0, out + err
    if output is None or sample.command in OUTPUT_NOT_COMPARED:
        return
    assert expected_pattern(output).fullmatch(out + err), out + err


def test_call_help_examples_work_against_the_robot(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, servers: Servers
) -> None:
    main(["call", "--help"])
    examples = [
        line.strip()
        for line in capsys.readouterr().out.splitlines()
        if line.startswith("  srvwire call /get_robot_state")
    ]
    assert examples
    monkeypatch.setenv("SRVWIRE_URL", servers.robot)
    for example in examples:
        argv = [*shlex.split(example)[1:], "-n", "1", "--json"]
        assert main(argv) == 0
        assert '"success": true' in capsys.readouterr().out, example
