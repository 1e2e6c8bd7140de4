"""The documentation's code is example files, and every example file runs.

The rules these tests keep true:

* a page in ``docs/`` shows Python only by including a file from ``examples/`` (a snippet), never
  as a block typed into the page, so what a reader copies is what a test ran;
* every file in ``examples/`` is run by a test: the scripts here, as a reader would run them;
  the tutorial's server and client in ``tests/test_examples.py``;
* a transcript ``$ python examples/NAME.py`` on a page shows what that script really prints;
* every page is in the site's navigation, and every navigation entry is a page.
"""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from support import ROOT, scaled

DOCS = ROOT / "docs"
EXAMPLES = ROOT / "examples"
PAGES = sorted(DOCS.rglob("*.md"))

# Examples that a test elsewhere runs, and why they are not simply run as scripts here.
RUN_ELSEWHERE = {
    "robot_state_server.py": "a server that runs until stopped: tests/test_examples.py",
    "robot_command_client.py": "needs the robot server: tests/test_examples.py",
    "joint_state_publisher.py": "needs the robot server: tests/test_examples.py",
    "demo.py": "make demo; starts the robot server itself: tests/test_examples.py",
    "testing_services.py": "a pytest file: test_the_testing_page_passes_under_pytest",
    "testing_with_the_plugin.py": "a pytest file: test_the_testing_page_passes_under_pytest",
    "conftest.py": "the srvwire_server of testing_with_the_plugin.py, run with it",
    "sync_client.py": "needs the robot server: tests/test_examples.py",
    "sync_topics.py": "needs the robot server: tests/test_examples.py",
    "notebook.py": "a notebook's cells (top-level await): tests/test_notebook.py runs them",
}

# The scripts run here, with what each must print: its whole standard output, with the port of
# any URL written as PORT, since each run listens on a port of its own.
SCRIPTS = {
    "quickstart.py": "2 + 3 = 5\n",
    "native_transport.py": "2 + 3 = 5 over picows\n",
    "logging_setup.py": (
        "2 + 3 = 5\nnot found: no service named /add_to_ints; did you mean /add_two_ints?\n"
    ),
    "blocking_handlers.py": (
        "calibrate: the deadline passed\nthe handler stopped early, at step 0\n2 + 3 = 5\n"
    ),
    "field_names.py": '{"from":3,"to":0}\n',
    "one_class_per_type.py": (
        "GetStatus_Response: ok=True frame=base\n"
        "built from three sources: map\n"
        "same Header class: True\n"
    ),
    "camera_frames.py": (
        "rgb8 640x480: 921600 bytes\n"
        "exposure: inf\n"
        "default limit: closed with 1009, the connection closed with code 1009 (over the "
        "client's max_message_size (frame with 1228922 bytes exceeds limit of 1048576 bytes))\n"
    ),
    "handling_errors.py": (
        "sum: 3\n"
        "invalid request: b: Input should be a valid integer\n"
        "no such service; did you mean ['/add_two_ints']\n"
        "too slow; the call was cancelled on the server\n"
        "battery at 0.07\n"
        "server unavailable: not connected to ws://127.0.0.1:PORT\n"
        "sum after reconnecting: 42\n"
    ),
    "secure_server.py": (
        "['/status']\n"
        "hello viewer\n"
        "permission denied: /motors needs the scope robot:write, which this connection's "
        "identity does not hold\n"
        "on\n"
        "the server refused the connection: HTTP 401: the token is not valid\n"
        "off\n"
    ),
}

PORT = re.compile(r"(ws://[\w.]+):\d+")
FENCE = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}|~{3,})(?P<info>.*)$")
PYTHON_LANGUAGES = {"python", "py", "python3", "pycon", "ipython", "pyi"}


def run_script(path: Path, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(path), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=scaled(30),
        check=False,
    )


def without_ports(text: str) -> str:
    return PORT.sub(r"\1:PORT", text)


# --- every example runs -----------------------------------------------------------------------


def test_every_example_is_run_by_a_test() -> None:
    examples = {path.name for path in EXAMPLES.glob("*.py")}
    known = set(SCRIPTS) | set(RUN_ELSEWHERE)
    assert examples - known == set(), "add the new example to SCRIPTS or RUN_ELSEWHERE"
    assert known - examples == set(), "these examples are listed but do not exist"


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_example_script(name: str) -> None:
    result = run_script(EXAMPLES / name)
    assert result.returncode == 0, result.stdout + result.stderr
    assert without_ports(result.stdout) == SCRIPTS[name]


def test_quickstart_logs_nothing() -> None:
    result = run_script(EXAMPLES / "quickstart.py")
    assert result.stderr == ""


def test_handling_errors_logs_the_lost_connection() -> None:
    # The server shuts down under the connected client: the client says so once, as a warning.
    result = run_script(EXAMPLES / "handling_errors.py")
    assert without_ports(result.stderr).splitlines() == [
        "WARNING srvwire.client: connection to ws://127.0.0.1:PORT lost: the connection closed "
        "with code 1001 (server shutting down); failing 0 pending calls"
    ]


@pytest.mark.parametrize(
    ("example", "tests"), [("testing_services.py", 7), ("testing_with_the_plugin.py", 10)]
)
def test_the_testing_page_passes_under_pytest(example: str, tests: int) -> None:
    # An examples/ file is not collected by the suite (testpaths is tests/): run it on its own.
    # The plugin's example also takes examples/conftest.py, as pytest finds it beside it.
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            f"examples/{example}",
            "-q",
            "-p",
            "no:cacheprovider",
            f"--timeout={scaled(30):g}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=scaled(60),
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    summary = result.stdout.strip().splitlines()[-1]
    assert re.fullmatch(rf"{tests} passed in [\d.]+s", summary), result.stdout


def test_the_generated_module_of_the_cli_page(tmp_path: Path) -> None:
    # docs/cli.md: `srvwire gen ... -o my_app/interfaces.py`, then import it in a new process.
    gen = subprocess.run(
        [
            sys.executable,
            "-m",
            "srvwire",
            "gen",
            "std_srvs",
            "example_interfaces/srv/AddTwoInts",
            "-o",
            "my_app/interfaces.py",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=scaled(30),
        check=False,
    )
    assert gen.returncode == 0, gen.stderr
    assert gen.stdout == "wrote my_app/interfaces.py (4 interfaces)\n"
    code = "from my_app.interfaces import AddTwoInts; print(repr(AddTwoInts.Request(a=1, b=2)))"
    assert f"$ python -c '{code}'\nAddTwoInts_Request(a=1, b=2)\n" in read(DOCS / "cli.md")
    result = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=scaled(30),
        check=False,
    )
    assert (result.returncode, result.stdout, result.stderr) == (
        0,
        "AddTwoInts_Request(a=1, b=2)\n",
        "",
    )


# --- what the pages show ----------------------------------------------------------------------


def read(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def code_blocks(text: str) -> Iterator[tuple[int, str, list[str]]]:
    """Yield each fenced block of a Markdown page: its line number, info string and lines."""
    lines = text.splitlines()
    index = 0
    while index < len(lines):
        opening = FENCE.match(lines[index])
        if opening is None:
            index += 1
            continue
        fence = opening["fence"]
        body: list[str] = []
        end = index + 1
        while end < len(lines) and not lines[end].strip().startswith(fence):
            body.append(lines[end])
            end += 1
        yield index + 1, opening["info"].strip(), body
        index = end + 1


def language(info: str) -> str:
    """The language of a fence's info string: ``python``, ``{.python title="x"}``, ``py title``."""
    info = info.strip()
    if info.startswith("{"):
        match = re.search(r"\.([\w-]+)", info)
        return match.group(1).lower() if match else ""
    return info.split(maxsplit=1)[0].lower() if info else ""


def test_code_blocks_are_found() -> None:
    # The scanner itself: one typed-in block, one snippet include, one block of another language.
    page = (
        "text\n```python\nx = 1\n```\n\n"
        '```{.python title="a"}\n--8<-- "examples/quickstart.py"\n```\n'
        "  ```json\n  {}\n  ```\n"
    )
    blocks = [(line, language(info), body) for line, info, body in code_blocks(page)]
    assert blocks == [
        (2, "python", ["x = 1"]),
        (6, "python", ['--8<-- "examples/quickstart.py"']),
        (9, "json", ["  {}"]),
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda path: path.name)
def test_python_on_a_page_is_included_from_an_example(page: Path) -> None:
    typed_in = [
        f"{page.relative_to(ROOT)}:{line}: a ```{info} block typed into the page"
        for line, info, body in code_blocks(read(page))
        if language(info) in PYTHON_LANGUAGES
        and not (body and all(text.strip().startswith("--8<--") for text in body if text.strip()))
    ]
    assert typed_in == [], (
        "put the code in a file under examples/ that a test runs, and include it with "
        '--8<-- "examples/NAME.py" (a section: "examples/NAME.py:section")'
    )


@pytest.mark.parametrize("page", PAGES, ids=lambda path: path.name)
def test_snippets_come_from_files_that_exist(page: Path) -> None:
    for line, _, body in code_blocks(read(page)):
        for text in body:
            if match := re.match(r'\s*--8<-- "([^":]+)(?::[\w-]+)?"', text):
                assert (ROOT / match.group(1)).is_file(), f"{page.name}:{line}: {text}"


def transcripts() -> Iterator[Any]:
    """Every ``$ python examples/NAME.py`` console block on a page, with what it shows."""
    for page in PAGES:
        for line, info, body in code_blocks(read(page)):
            if language(info) == "console" and body:
                if match := re.fullmatch(r"\$ python (examples/\w+\.py)", body[0]):
                    output = "".join(f"{text}\n" for text in body[1:])
                    yield pytest.param(match.group(1), output, id=f"{page.name}:{line}")


TRANSCRIPTS = list(transcripts())


def test_pages_show_transcripts() -> None:
    assert len(TRANSCRIPTS) >= 2  # docs/index.md and docs/errors.md


@pytest.mark.parametrize(("script", "shown"), TRANSCRIPTS)
def test_a_transcript_shows_what_the_script_prints(script: str, shown: str) -> None:
    result = run_script(ROOT / script)
    assert result.returncode == 0, result.stderr
    assert without_ports(result.stdout) == without_ports(shown)


# --- the site's navigation --------------------------------------------------------------------


def nav_pages(entries: Any) -> Iterator[str]:
    """Every page named in mkdocs.yml's ``nav``, in order (sections are followed)."""
    for entry in entries:
        if isinstance(entry, str):
            yield entry
        elif isinstance(entry, dict):
            for value in entry.values():
                if isinstance(value, str):
                    if not value.startswith(("http://", "https://")):
                        yield value
                else:
                    yield from nav_pages(value)


def test_every_page_is_in_the_navigation_and_every_entry_exists() -> None:
    config = yaml.safe_load(read(ROOT / "mkdocs.yml"))
    listed = list(nav_pages(config["nav"]))
    assert len(listed) == len(set(listed)), "a page is listed twice"
    pages = {path.relative_to(DOCS).as_posix() for path in PAGES}
    assert set(listed) - pages == set(), "nav entries without a page"
    assert pages - set(listed) == set(), "pages missing from nav"
    assert listed[0] == "index.md"


def test_the_readme_quotes_the_quickstart() -> None:
    # The README cannot include files, so it quotes examples/quickstart.py: every line it shows
    # must be a line of that file.
    blocks = [body for _, info, body in code_blocks(read(ROOT / "README.md")) if info == "python"]
    assert len(blocks) == 1
    quickstart = read(EXAMPLES / "quickstart.py").splitlines()
    assert [line for line in blocks[0] if line not in quickstart] == []
