"""Every code block in docs/ and the README is run, parsed or checked by a test.

Each fenced block of ``docs/*.md`` (every page, so a new page is covered as it lands) and of
``README.md`` falls in one of these kinds, each with its check:

* **included**: the block only includes files (``--8<-- "examples/NAME.py"``): every example
  runs under tests/test_docs_examples.py, and the included files exist;
* **python**: Python typed into a page, which tests/test_docs_examples.py refuses (the README's
  quote of examples/quickstart.py, which it checks line by line, is the only one);
* **commands** (``sh``, ``console``, ``shell``, ``bash``): every command in it is one that a
  test runs: ``srvwire ...`` by tests/test_cli_docs.py, ``python examples/NAME.py`` transcripts
  by tests/test_docs_examples.py, and the others as ``COMMANDS`` says, each with its test or the
  reason it cannot run here;
* **json** and **toml**: the block parses; **javascript** (``js``): ``node --check`` accepts it;
* **interface**: a block with no language on docs/interfaces.md is an interface file's text,
  and srvwire's parser reads it;
* **wire**: a ``text`` block of ``> `` and ``< `` lines is a wscat session: each line parses as
  JSON, docs/wscat.md is replayed against the real server by tests/test_wscat.py, and a session
  quoted anywhere else holds only lines of that guide;
* **explained**: any other block is listed in ``EXPLAINED`` by its page and first line, with
  the test that checks it or the reason it is not code (a diagram, a folder tree).

A block that fits none of these fails ``test_every_block_is_checked``, saying how to classify it.
"""

from __future__ import annotations

import json
import re
import subprocess
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

import srvwire
from srvwire.parser import parse_action, parse_message, parse_service
from support import ROOT
from test_cli_docs import NOT_RUN, samples
from test_docs_examples import PYTHON_LANGUAGES, TRANSCRIPTS, code_blocks, language
from test_wscat import transcript

DOCS = ROOT / "docs"
PAGES = [*sorted(DOCS.glob("*.md")), ROOT / "README.md"]
SHELLS = {"sh", "shell", "bash", "console"}

COMMANDS: dict[str, str] = {
    r"echo \$\?": "the exit code of the srvwire sample before it: tests/test_cli_docs.py checks it",
    r"case \$\? in|\S+\) echo .* ;;|esac": (
        "a script branching on the exit code of the srvwire sample in it: bash -n checks it "
        "(test_a_shell_block_is_valid_bash), tests/test_cli.py the exit codes"
    ),
    r"make demo": "tests/test_examples.py runs examples/demo.py, which is what make demo runs",
    r"make test": "the whole suite: what CI runs (.ci/run)",
    r"make (test|pytest) PYTEST_WORKERS=\d+": (
        "the whole suite, or its tests alone, on as many pytest workers: what CI runs"
    ),
    r"\.venv/bin/pytest tests/test_\w+\.py -q": "one file of the suite: make test runs every file",
    r"make bench": "minutes long; tests/test_benchmarks.py runs the harness's --quick mode",
    r"\.venv/bin/python benchmarks/run\.py .*": (
        "the benchmark harness: minutes long; tests/test_benchmarks.py runs it in --quick mode"
    ),
    r"\.venv/bin/python benchmarks/server_path\.py( .*)?": (
        "the server's path in one process: a minute long; tests/test_benchmarks.py runs it small"
    ),
    r"valgrind --tool=callgrind .* benchmarks/server_path\.py .*": (
        "benchmarks/server_path.py counted under callgrind: minutes long, and valgrind is no "
        "dependency; tests/test_benchmarks.py runs the script itself"
    ),
    r"valgrind --tool=callgrind .* benchmarks/picows_path\.py .*": (
        "benchmarks/picows_path.py counted under callgrind: minutes long, and valgrind is no "
        "dependency; tests/test_push.py runs the script itself"
    ),
    r"PYTHONHASHSEED=\d+ valgrind --tool=callgrind .* benchmarks/(server|picows)_path\.py .*": (
        "the same counts with the hash seed fixed: tests/test_benchmarks.py and "
        "tests/test_push.py run the scripts themselves"
    ),
    r"\.venv/bin/python benchmarks/picows_path\.py( .*)?": (
        "both ends on picows in one process: a minute long; tests/test_push.py runs it small, "
        "--steps too"
    ),
    r"\.venv/bin/py-spy record .* benchmarks/\w+\.py .*": (
        "a sampling profile of a benchmark script: py-spy comes with the bench extra (make "
        "bench), not with the tests' environment; tests/test_push.py runs the script itself"
    ),
    r"\.venv/bin/python benchmarks/(floor_)?picows_server\.py( --cork)?": (
        "the typed floor's or raw picows' server, serving until its stdin closes: "
        "tests/test_benchmarks.py runs it through the harness, and in-process"
    ),
    r"echo go \| PYTHONHASHSEED=\d+ valgrind --tool=(callgrind|cachegrind) .* "
    r"benchmarks/\w+_client\.py .*": (
        "a benchmark client counted under callgrind or cachegrind against a server started by "
        "hand: minutes long, and valgrind is no dependency; tests/test_benchmarks.py runs the "
        "clients"
    ),
    r"\.venv/bin/python benchmarks/topics\.py( .*)?": (
        "the topic benchmark: minutes long; tests/test_benchmarks.py runs its --quick mode"
    ),
    r"\.venv/bin/python benchmarks/client_path\.py( .*)?": (
        "the client's in-process benchmark: a minute long, valgrind's counts longer; "
        "tests/test_benchmarks.py runs it small"
    ),
    r"\.venv/bin/python benchmarks/srvwire_server\.py": (
        "the harness's srvwire server, serving until its input ends: tests/test_benchmarks.py "
        "runs it under client_path.py --server"
    ),
    r"PYTHONPATH=src:benchmarks strace -f -c \.venv/bin/python benchmarks/client_path\.py .*": (
        "the client benchmark's child counted by strace: strace is no dependency; "
        "tests/test_benchmarks.py runs the script itself"
    ),
    r"strace -f -c \.venv/bin/python benchmarks/run\.py .*": (
        "the harness's system calls counted by strace: strace is no dependency; "
        "tests/test_benchmarks.py runs the harness itself"
    ),
    r"\.venv/bin/python benchmarks/large_path\.py( .*)?": (
        "W4's two steps in one process, both ways: tests/test_benchmarks.py runs it small"
    ),
    r"echo go \| (perf stat|strace|valgrind) .* benchmarks/srvwire_client\.py .*": (
        "the harness's srvwire client alone, against a server started by hand, under perf, "
        "strace or valgrind (none a dependency): tests/test_benchmarks.py runs the client"
    ),
    r"\.venv/bin/python benchmarks/picows_large_send\.py( .*)?": (
        "a picows server's large messages in one process: tests/test_picows_large.py runs it"
    ),
    r"\.venv/bin/pytest tests/test_picows_large\.py": "the tests of the page: make test runs them",
    r"\.venv/bin/python benchmarks/defaults\.py( .*)?": (
        "loading and validating in several source trees, counted by valgrind: minutes long; "
        "tests/test_benchmarks.py runs it on CPU time"
    ),
    r"\.venv/bin/python benchmarks/deadline_cost\.py( .*)?": (
        "what each way of awaiting a reply costs asyncio, counted by valgrind: a minute long; "
        "tests/test_benchmarks.py runs it small"
    ),
    r"MALLOC_TOP_PAD_=\d+ \.venv/bin/python benchmarks/run\.py .*": (
        "the benchmark harness with the heap kept: minutes long; tests/test_benchmarks.py runs it"
    ),
    r"python benchmarks/slow_reader\.py .*": (
        "a benchmark of a client that never reads, tens of seconds long: tests/test_limits.py "
        "checks the same bound and the write timeout"
    ),
    r"python benchmarks/picows_memory\.py .*": (
        "the resident memory of idle connections after a large message, seconds long: "
        "tests/test_picows_memory.py runs it"
    ),
    r"python benchmarks/bare_requests\.py .*": (
        "a measurement of RSS with requests held, which needs a quiet machine: "
        "tests/test_benchmarks.py runs it small"
    ),
    r"python benchmarks/worst_message\.py .*": (
        "a benchmark of the worst 1 MiB messages, a minute long: tests/test_server.py checks "
        "that their replies stay small"
    ),
    r"(\.venv/bin/)?python examples/robot_state_server\.py( &)?": (
        "serves until stopped: tests/test_examples.py runs it in a child process"
    ),
    r"python examples/sync_client\.py": (
        "needs the robot server: tests/test_examples.py's test_the_blocking_client_script runs "
        "it against one and compares its output with the page"
    ),
    r"\.venv/bin/python examples/robot_command_client\.py": (
        "needs the robot server: tests/test_examples.py runs it against one"
    ),
    r"npx wscat -c ws://localhost:8765": "tests/test_wscat.py runs the installed wscat",
    r"wscat -c ws://127\.0\.0\.1:8765": "tests/test_wscat.py runs wscat; the session's lines parse",
    r"pip install \.": "tests/test_install.py installs the wheel that this builds",
    r"pip install -e '\.\[dev\]'": "what the Makefile runs for make test and make demo",
    r"pip wheel --no-deps \. -w dist": "tests/test_install.py builds the wheel this way",
    r"pip download dist/srvwire-[\w.-]+\.whl -d dist": (
        "fetches from the package index; tests/test_install.py needs no network"
    ),
    r"pip install --no-index --find-links dist srvwire": (
        "tests/test_install.py installs the wheel with --no-index (its dependencies from this venv)"
    ),
    r"scp dist/srvwire-[\w.-]+\.whl robot:": "copies a file to another machine",
    r"python3 -m venv ~/srvwire-env": "tests/test_install.py installs into a new venv",
    r"~/srvwire-env/bin/pip install \./srvwire-[\w.-]+\.whl": (
        "tests/test_install.py installs the wheel into a new venv"
    ),
    r"python -c 'from my_app\.interfaces import .*": (
        "tests/test_docs_examples.py's test_the_generated_module_of_the_cli_page runs it"
    ),
    r"python -m pytest examples/(testing_with_the_plugin|testing_services)\.py": (
        "tests/test_docs_examples.py's test_the_testing_page_passes_under_pytest runs it"
    ),
    r"python -m pytest tests/ --srvwire-url ws://robot\.local:8765": (
        "needs a robot; tests/test_plugin.py runs a project's tests with --srvwire-url"
    ),
}
"""The commands of the pages that are not ``srvwire`` samples or ``python examples/`` transcripts,
as patterns of the whole command, each with the test that runs it or why none can."""

EXPLAINED: dict[tuple[str, str], str] = {
    ("cli.md", "srvwire call NAME [TYPE] [VALUES] [--url URL] [--timeout SECONDS] [--path DIR]"): (
        "the synopsis of srvwire call, not a command; tests/test_cli_docs.py runs its samples"
    ),
    ("design.md", "server side                                   client side"): (
        "a diagram of the layers; tests/test_layers.py checks the table that follows it"
    ),
    ("errors.md", "SrvwireError"): "the exception tree: test_the_exception_tree_is_the_classes",
    ("interfaces.md", "my_robot/"): "a folder tree, not a file",
    (
        "interfaces.md",
        "no message 'Pose' in package 'geometry_msgs' (/home/me/ws/geometry_msgs hides the "
        "bundled package 'geometry_msgs' in .../srvwire/interfaces, which has it: a package is "
        "taken whole from the first folder that holds it)",
    ): "the overlay error: tests/test_loader.py asserts its text",
    (
        "interfaces.md",
        "two different definitions of std_msgs/msg/Header: .../srvwire/interfaces/std_msgs/msg/"
        "Header.msg and server ws://robot:8765 (declaration 1: 'builtin_interfaces/Time stamp' "
        "against 'uint32 seq'); a type name has one definition per process",
    ): "the conflict error: tests/test_typeregistry.py and tests/test_reflection.py assert it",
    (
        "interfaces.md",
        "two different definitions of my_robot/msg/Limits: .../client_interfaces/my_robot/msg/"
        "Limits.msg and server ws://robot:8765 (declaration 1: 'float64 max_speed' against "
        "'float32 max_speed'); a type name has one definition per process",
    ): "a local type that differs from the server's: tests/test_reflection.py asserts its text",
    (
        "security.md",
        "cannot connect to ws://127.0.0.1:8765: the server refused the connection: HTTP 401: "
        "the token is not valid",
    ): "a refused handshake: tests/test_docs_examples.py runs examples/secure_server.py for it",
    (
        "security.md",
        "srvwire: error: refusing to listen on 0.0.0.0 without authentication: any host that can "
        "reach it could call every service. Give the Server an authenticator "
        "(Server(auth=srvwire.TokenAuth(...))), require client certificates (--client-ca), or "
        "pass --allow-unauthenticated on a network you trust",
    ): (
        "serve's refusal: test_cli_security.py's "
        "test_serve_refuses_a_public_address_without_authentication asserts it"
    ),
    (
        "interfaces.md",
        "srv/RobotCommand.srv:3:7: 'Command_type' is an invalid field name: it must start with a "
        "lowercase letter and contain only lowercase letters, digits and underscores, with no "
        "double or trailing underscore",
    ): "the parser's errors: test_the_parser_errors_on_the_interfaces_page gives each of them",
    ("sync.md", "Current joint positions: [0.0, 0.0, 0.0, 0.0, 0.0]"): (
        "what examples/sync_client.py prints: tests/test_examples.py's "
        "test_the_blocking_client_script compares it"
    ),
    (
        "types.md",
        'reveal_type(await client.call("/scan", Scan.Request(fill=1.0)))      '
        "# wire_types.Scan_Response",
    ): "what mypy reveals: tests/test_typed_calls.py runs mypy on these calls and checks it",
    (
        "blocking.md",
        "WARNING srvwire.server: a call to /calibrate waited 1.02 s for a thread to run its "
        "blocking",
    ): ("the queueing warning: tests/test_blocking.py awaits it and checks its words"),
    (
        "logging.md",
        "INFO srvwire.server: serving 2 services on ws://127.0.0.1:8765, ws://192.168.1.20:8765, "
        "ws://[::1]:8765",
    ): "the startup line: tests/test_logging.py checks it for one host, several, and every one",
    ("logging.md", "INFO srvwire.access: 127.0.0.1:35658 /add_two_ints OK 0.16 ms"): (
        "the access log: tests/test_logging.py checks its lines on both transports"
    ),
    (
        "logging.md",
        "INFO srvwire.access: 127.0.0.1:35658 $/subscribe /joint_states CANCELLED 12034.51 ms "
        "delivered 1203 dropped 0",
    ): (
        "a subscription's access-log lines: tests/test_logging.py checks one of each ending, "
        "and a refused one, on every transport"
    ),
    ("logging.md", "INFO srvwire.access: 127.0.0.1:35658 $/publish /cmd_vel OK 0.12 ms"): (
        "the publishes' access-log lines: tests/test_logging.py checks an acknowledged one and "
        "the summary of those without an answer, on every transport"
    ),
    ("limits.md", "M  ≤  C + B + (3 + W)·R + P + F·(c + q) + S·s + (Q + 2)·m"): (
        "the memory formula: tests/test_limits.py measures a server against it"
    ),
    ("tutorial.md", "make demo: robot_state_server.py is serving on ws://127.0.0.1:41111"): (
        "make demo's output: tests/test_examples.py's test_make_demo_runs_the_whole_tutorial"
    ),
    (
        "tutorial.md",
        "no srvwire server answered at ws://localhost:8765: is robot_state_server.py running?",
    ): "the client with no server: tests/test_examples.py checks these lines",
    (
        "tutorial.md",
        "connection to ws://localhost:8765 lost: the connection dropped (no close frame); "
        "failing 1 pending calls",
    ): "the client when the server is killed: tests/test_examples.py checks these lines",
    ("wscat.md", "Connected (press CTRL+C to quit)"): (
        "wscat's first lines: tests/test_wscat.py waits for this one and replays the rest"
    ),
}
"""Blocks that are neither code nor commands, by (page, first line), with what checks them."""


@dataclass(frozen=True)
class Block:
    page: Path
    line: int
    info: str
    body: list[str]

    @property
    def language(self) -> str:
        return language(self.info)

    @property
    def first(self) -> str:
        return next((text.strip() for text in self.body if text.strip()), "")

    @property
    def key(self) -> tuple[str, str]:
        return (self.page.name, self.first)

    def __str__(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks() -> list[Block]:
    return [
        Block(page, line, info, body)
        for page in PAGES
        for line, info, body in code_blocks(page.read_text(encoding="utf-8"))
    ]


BLOCKS = blocks()


def without_comment(line: str) -> str:
    """A command line without its trailing ``# ...`` (which the pages use to explain it)."""
    return re.sub(r"\s+#.*$", "", line).strip()


def commands(block: Block) -> list[str]:
    """The commands of a shell block: its ``$ `` lines in a console block with prompts (the
    other lines are output), else every line that is not a comment. A line ending in ``\\``
    goes on in the next one; a trailing ``# ...`` is dropped."""
    prompted = block.language == "console" and any(t.startswith("$ ") for t in block.body)
    found: list[str] = []
    pending: str | None = None  # a command whose line ended in a backslash
    for text in block.body:
        if pending is None:
            if prompted and not text.startswith("$ "):
                continue  # output
            text = text[2:] if prompted else text
            if text.lstrip().startswith("#") or not text.strip():
                continue
            pending = ""
        text = without_comment(text)
        if text.endswith("\\"):
            pending += text[:-1].strip() + " "
            continue
        found.append(pending + text)
        pending = None
    return found


def is_wire_session(block: Block) -> bool:
    lines = [text for text in block.body if text.strip()]
    return bool(lines) and all(text.startswith(("> ", "< ")) for text in lines)


def is_include(block: Block) -> bool:
    lines = [text for text in block.body if text.strip()]
    return bool(lines) and all(text.strip().startswith("--8<--") for text in lines)


def kind(block: Block) -> str | None:
    """The kind of a block (see the module's docstring), or None when it fits none."""
    if is_include(block):
        return "included"
    if block.language in PYTHON_LANGUAGES:
        return "python"
    if block.language in SHELLS:
        return "commands"
    if block.language in {"json", "toml"}:
        return block.language
    if block.language in {"js", "javascript"}:
        return "javascript"
    if block.language == "" and block.page.name == "interfaces.md" and block.key not in EXPLAINED:
        return "interface"
    if block.language == "text" and is_wire_session(block):
        return "wire"
    if block.key in EXPLAINED:
        return "explained"
    return None


def of_kind(name: str) -> list[Block]:
    return [block for block in BLOCKS if kind(block) == name]


def hint(block: Block) -> str:
    """How a block that fits no kind could get a check."""
    if re.match(r"\$ python examples/\w+\.py$", block.first):
        return "a transcript: mark it ```console, and tests/test_docs_examples.py runs it"
    if block.first.startswith("$ "):
        return "commands: mark it ```console (or ```sh without the prompts)"
    return "list it in EXPLAINED with the test that checks it, or why nothing can"


def test_every_block_is_checked() -> None:
    unchecked = [
        f"{block}: ```{block.info} {block.first!r}: {hint(block)}"
        for block in BLOCKS
        if not kind(block)
    ]
    assert unchecked == [], "blocks no test checks (the module's docstring lists the kinds)"


def test_the_pages_have_blocks_of_every_kind() -> None:
    kinds = {kind(block) for block in BLOCKS}
    expected = {"included", "python", "commands", "json", "toml", "interface", "wire", "explained"}
    assert expected <= kinds  # each kind's check has something to check


def test_every_explanation_and_command_pattern_is_used() -> None:
    keys = {block.key for block in BLOCKS}
    assert set(EXPLAINED) - keys == set(), "EXPLAINED lists blocks no page has"
    every = [command for block in of_kind("commands") for command in commands(block)]
    unused = [p for p in COMMANDS if not any(re.fullmatch(p, command) for command in every)]
    assert unused == [], "COMMANDS lists commands no page shows"


def test_the_command_reader() -> None:
    block = Block(
        ROOT / "x.md",
        1,
        "console",
        ["$ make demo   # runs it", "output", "$ a \\", "    b", "# comment"],
    )
    assert commands(block) == ["make demo", "a b"]
    block = Block(ROOT / "x.md", 1, "sh", ["# a comment", "make test  # all", "", "x \\", "  y"])
    assert commands(block) == ["make test", "x y"]


# --- the checks of each kind --------------------------------------------------------------------

CLI_SAMPLES = {(sample.page, without_comment(sample.command)) for sample in samples()}
EXAMPLE_TRANSCRIPTS = {param.id for param in TRANSCRIPTS}


@pytest.mark.parametrize("block", of_kind("commands"), ids=str)
def test_every_command_is_run_by_a_test(block: Block) -> None:
    found = commands(block)
    assert found, f"{block}: a shell block with no command"
    for command in found:
        if command.startswith("srvwire "):
            # tests/test_cli_docs.py runs it (or lists it in NOT_RUN, with the reason).
            not_run = {without_comment(sample) for sample in NOT_RUN}
            assert (block.page.name, command) in CLI_SAMPLES or command in not_run, (
                f"{block}: tests/test_cli_docs.py does not find {command!r}; it reads ```sh and "
                "```console blocks"
            )
        elif re.fullmatch(r"python examples/\w+\.py", command) and block.language == "console":
            assert f"{block.page.name}:{block.line}" in EXAMPLE_TRANSCRIPTS, str(block)
        else:
            assert any(re.fullmatch(pattern, command) for pattern in COMMANDS), (
                f"{block}: {command!r} is run by no test: add it to COMMANDS with the test that "
                "runs it (or why none can)"
            )


@pytest.mark.parametrize(
    "block", [block for block in of_kind("commands") if block.language != "console"], ids=str
)
def test_a_shell_block_is_valid_bash(block: Block) -> None:
    script = "\n".join(block.body) + "\n"
    result = subprocess.run(
        ["bash", "-n"], input=script, capture_output=True, text=True, timeout=30, check=False
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("block", of_kind("json"), ids=str)
def test_json_parses(block: Block) -> None:
    json.loads("\n".join(block.body))


def node_check(source: str, folder: Path) -> str:
    """What ``node --check`` says of a script: "" when it is valid JavaScript."""
    script = folder / "sample.js"
    script.write_text(source, encoding="utf-8")
    result = subprocess.run(
        ["node", "--check", str(script)], capture_output=True, text=True, timeout=30, check=False
    )
    return "" if result.returncode == 0 else result.stderr or f"exit {result.returncode}"


def test_javascript_is_valid(tmp_path: Path) -> None:
    # One test for every ```js block (there may be none), after one that must be refused.
    assert node_check("const a = ;\n", tmp_path) != ""
    invalid = {
        str(block): error
        for block in of_kind("javascript")
        if (error := node_check("\n".join(block.body) + "\n", tmp_path))
    }
    assert invalid == {}


@pytest.mark.parametrize("block", of_kind("toml"), ids=str)
def test_toml_parses(block: Block) -> None:
    assert tomllib.loads("\n".join(block.body))


@pytest.mark.parametrize("block", of_kind("interface"), ids=str)
def test_an_interface_fragment_parses(block: Block) -> None:
    text = "\n".join(block.body) + "\n"
    separators = sum(1 for line in block.body if line.strip().startswith("---"))
    parse = {0: parse_message, 1: parse_service, 2: parse_action}[separators]
    spec = parse(text, "my_robot", "Sample", path=str(block))
    assert spec is not None


GUIDE = transcript((DOCS / "wscat.md").read_text(encoding="utf-8"))


@pytest.mark.parametrize("block", of_kind("wire"), ids=str)
def test_a_wire_session_parses_and_quotes_the_guide(block: Block) -> None:
    lines = [text for text in block.body if text.strip()]
    for number, text in enumerate(lines):
        reply = lines[number + 1] if number + 1 < len(lines) else ""
        if text.startswith("> ") and '"code":-32700' in reply:
            continue  # a line sent half-typed, to show the parse error it gets
        json.loads(text[2:])
    if block.page.name != "wscat.md":  # the guide itself is replayed by tests/test_wscat.py
        assert [text for text in lines if text not in GUIDE] == [], (
            f"{block}: quote lines of docs/wscat.md, which tests/test_wscat.py replays"
        )


def test_the_exception_tree_is_the_classes() -> None:
    # docs/errors.md draws the exception classes as a tree, with the code of each RPCError.
    [tree] = [block for block in BLOCKS if block.key == ("errors.md", "SrvwireError")]
    parents: list[tuple[int, type]] = []
    seen = []
    for text in tree.body:
        match = re.match(r"^([\s│├└─]*)(\w+)(?:\s+(-?\d+))?", text)
        assert match is not None, text
        depth, name, code = len(match.group(1)), match.group(2), match.group(3)
        cls = getattr(srvwire, name)
        while parents and parents[-1][0] >= depth:
            parents.pop()
        if parents:
            assert issubclass(cls, parents[-1][1]), f"{name} is not a {parents[-1][1].__name__}"
        if code is not None:
            assert cls.code == int(code), name
        parents.append((depth, cls))
        seen.append(cls)
    assert len(seen) == len(set(seen)) > 10


# Files that give the errors docs/interfaces.md shows, one for each line of its "Errors" block.
BAD_FILES = {
    "srv/RobotCommand.srv": "string name\nfloat64[] parameters\nint32 Command_type\n---\nbool ok\n",
    "msg/Speed.msg": "# The speed limit.\nuint8 min\n\nuint8 limit 300\n",
    "msg/Pose.msg": "float x\nfloat64 y\n",
    "srv/Ping.srv": "int32 a\n---\nint32 b\n# more\n---\n",
}


def test_the_parser_errors_on_the_interfaces_page() -> None:
    key = next(key for key in EXPLAINED if key[1].startswith("srv/RobotCommand.srv:3:7:"))
    [shown] = [block for block in BLOCKS if block.key == key]
    messages = []
    for path, text in BAD_FILES.items():
        folder, file = path.split("/")
        name = file.split(".")[0]
        parse = parse_service if folder == "srv" else parse_message
        with pytest.raises(srvwire.InterfaceSyntaxError) as error:
            parse(text, "my_robot", name, path=path)
        messages.append(str(error.value))
    assert messages == [line for line in shown.body if line.strip()]
