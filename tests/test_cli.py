"""The ``srvwire`` command line, driven through ``main([...])`` with exact output and exit codes."""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import importlib.util
import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from srvwire import cli, version
from srvwire.cli import ExitCode, common as cli_common, interface as cli_interface, main
from srvwire.cli.common import EXIT_CODES, EXIT_CODES_HELP, exit_code_for
from srvwire.client import Client
from srvwire.errors import (
    ConnectionLost,
    ErrorCode,
    ResourceExhausted,
    RPCError,
    ServiceError,
    ServiceNotFound,
    ServiceUnavailable,
    error_from_code,
)
from srvwire.loader import InterfaceLoader, default_search_path
from srvwire.server import Server, serve
from support import ROOT, import_each_first, scaled

# --- helpers ----------------------------------------------------------------------------------


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """Run the command line in-process; return its exit code, stdout and stderr."""
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    """Check that stderr is exactly one ``srvwire: error:`` line and return its message."""
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert err.startswith("srvwire: error: "), err
    assert "Traceback" not in err
    return err.removeprefix("srvwire: error: ").rstrip("\n")


def write(root: Path, relative: str, text: str) -> Path:
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


VEC = """\
# A 2-D vector.
float64 x  # Along x.
float64 y 1.5  # Along y.
"""

SEGMENT = """\
# A straight line between two points.

# Where it starts.
Vec start
demo/Vec[2] ends  # Both ends.
string label "a # b"  # A label; the quoted '#' is not a comment.
"""

MEASURE = """\
# Measure a segment.
Segment segment  # What to measure.
---
float64 length  # How long it is.
Vec direction
"""

GO = """\
# Drive to a target.
Vec target
---
bool reached
---
float64 remaining  # Distance left.
"""


@pytest.fixture
def packages(tmp_path: Path) -> Path:
    """A search-path folder holding the package ``demo``: messages, a service and an action."""
    root = tmp_path / "interfaces"
    write(root, "demo/msg/Vec.msg", VEC)
    write(root, "demo/msg/Segment.msg", SEGMENT)
    write(root, "demo/srv/Measure.srv", MEASURE)
    write(root, "demo/action/Go.action", GO)
    return root


# --- the command line itself ------------------------------------------------------------------


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "--version")
    version = importlib.metadata.version("srvwire")
    assert (code, out, err) == (ExitCode.OK, f"srvwire {version}\n", "")


def test_version_is_the_package_version(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(version, "__version__", "1.2.3+test")  # one source: srvwire.version
    assert run(capsys, "--version") == (ExitCode.OK, "srvwire 1.2.3+test\n", "")


def test_help_lists_every_command_and_the_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "--help")
    assert code == ExitCode.OK and err == ""
    for command in ("call", "service", "interface", "gen", "serve"):
        assert f"    {command} " in out
    assert "exit codes:" in out


@pytest.mark.parametrize(
    "argv",
    [
        ["call", "--help"],
        ["service", "list", "--help"],
        ["service", "type", "--help"],
        ["service", "find", "--help"],
        ["interface", "list", "--help"],
        ["interface", "packages", "--help"],
        ["interface", "package", "--help"],
        ["interface", "show", "--help"],
        ["interface", "proto", "--help"],
        ["interface", "check", "--help"],
        ["gen", "--help"],
        ["serve", "--help"],
    ],
)
def test_every_command_has_help_with_an_example(
    capsys: pytest.CaptureFixture[str], argv: list[str]
) -> None:
    code, out, err = run(capsys, *argv)
    assert code == ExitCode.OK and err == ""
    assert out.startswith(f"usage: srvwire {' '.join(argv[:-1])} ")
    assert "example" in out
    assert f"  srvwire {' '.join(argv[:-1])} " in out


def test_call_help_documents_the_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    _, out, _ = run(capsys, "call", "--help")
    assert "  4    deadline exceeded (DEADLINE_EXCEEDED)\n" in out
    assert "  5    no such service or topic (SERVICE_NOT_FOUND)\n" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "the following arguments are required: COMMAND (see 'srvwire --help')"),
        (["launch"], "argument COMMAND: invalid choice: 'launch' "),
        (
            ["interface"],
            "the following arguments are required: SUBCOMMAND (see 'srvwire interface --help')",
        ),
        (
            ["interface", "show"],
            "the following arguments are required: TYPE (see 'srvwire interface show --help')",
        ),
        (
            ["call", "/x", "--timeout", "-1"],
            "argument --timeout: must be a positive number, not -1 (see 'srvwire call --help')",
        ),
        (
            ["call", "/x", "--count", "0"],
            "argument -n/--count: must be at least 1, not 0 (see 'srvwire call --help')",
        ),
        (
            ["serve", "app.py", "--port", "70000"],
            "argument --port: must be between 0 and 65535, not 70000 (see 'srvwire serve --help')",
        ),
    ],
)
def test_usage_errors_are_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    code, out, err = run(capsys, *argv)
    assert code == ExitCode.USAGE and out == ""
    assert one_error_line(err).startswith(message)


def test_python_dash_m_runs_the_same_main() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "srvwire", "interface", "package", "std_srvs"],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert (done.returncode, done.stderr) == (0, "")
    assert done.stdout == "std_srvs/srv/Empty\nstd_srvs/srv/SetBool\nstd_srvs/srv/Trigger\n"


@pytest.mark.parametrize(
    "argv", [["interface", "list"], ["interface", "show", "geometry_msgs/msg/Pose"]]
)
def test_a_closed_stdout_ends_quietly(argv: list[str]) -> None:
    # As `srvwire interface list | head -1` once head has exited: the pipe's only reader is
    # closed before the process starts, so its first write of output is sure to fail.
    reader, writer = os.pipe()
    os.close(reader)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "srvwire", *argv],
            stdout=writer,
            stderr=subprocess.PIPE,
            text=True,
            check=False,
            timeout=60,
        )
    finally:
        os.close(writer)
    assert (done.returncode, done.stderr) == (ExitCode.FAILURE, "")


# --- exit codes -------------------------------------------------------------------------------


def test_every_error_code_has_an_exit_code() -> None:
    assert set(EXIT_CODES) == set(ErrorCode)


@pytest.mark.parametrize(
    ("error", "expected"),
    [
        (error_from_code(ErrorCode.PARSE_ERROR, "x"), ExitCode.OTHER_RPC_ERROR),
        (error_from_code(ErrorCode.INVALID_REQUEST, "x"), ExitCode.OTHER_RPC_ERROR),
        (error_from_code(ErrorCode.SERVICE_NOT_FOUND, "x"), ExitCode.SERVICE_NOT_FOUND),
        (error_from_code(ErrorCode.INVALID_PARAMS, "x"), ExitCode.INVALID_PARAMS),
        (error_from_code(ErrorCode.INTERNAL, "x"), ExitCode.SERVICE_FAILED),
        (error_from_code(ErrorCode.DEADLINE_EXCEEDED, "x"), ExitCode.DEADLINE_EXCEEDED),
        (error_from_code(ErrorCode.CANCELLED, "x"), ExitCode.OTHER_RPC_ERROR),
        (error_from_code(ErrorCode.UNAVAILABLE, "x"), ExitCode.UNAVAILABLE),
        (ConnectionLost("x"), ExitCode.UNAVAILABLE),
        (error_from_code(ErrorCode.RESOURCE_EXHAUSTED, "x"), ExitCode.OTHER_RPC_ERROR),
        (error_from_code(ErrorCode.UNAUTHENTICATED, "x"), ExitCode.OTHER_RPC_ERROR),
        (ServiceError(42, "x"), ExitCode.SERVICE_FAILED),
        (ServiceError(-1, "x"), ExitCode.SERVICE_FAILED),
        (error_from_code(-32050, "x"), ExitCode.OTHER_RPC_ERROR),  # reserved, but unnamed
    ],
    ids=repr,
)
def test_the_exit_code_of_each_error(error: RPCError, expected: ExitCode) -> None:
    assert exit_code_for(error) is expected


def exit_code_table(lines: list[str], row: str) -> dict[int, str]:
    """Read ``code: meaning`` from the lines that match ``row`` (a regex with two groups)."""
    matches = (re.fullmatch(row, line) for line in lines)
    return {int(match[1]): match[2] for match in matches if match}


def test_the_exit_codes_agree_with_the_docs_and_the_help() -> None:
    docs = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    section = docs.split("\n## Exit codes\n", 1)[1].split("\n## ", 1)[0]
    documented = exit_code_table(section.splitlines(), r"\| (\d+) \| (.+) \|")
    helped = exit_code_table(EXIT_CODES_HELP.splitlines(), r"  (\d+) +(.+)")
    assert list(documented) == list(helped) == [int(code) for code in ExitCode]
    for code in ErrorCode:
        # Where a status is named, it is named under its own exit code, and only there.
        for table, name in ((documented, f"`{code.name}`"), (helped, code.name)):
            rows = [exit_code for exit_code, meaning in table.items() if name in meaning]
            assert rows in ([], [EXIT_CODES[code]]), (code, rows)
        if EXIT_CODES[code] is not ExitCode.OTHER_RPC_ERROR:  # the others end in "..."
            assert f"`{code.name}`" in documented[EXIT_CODES[code]], code
            assert code.name in helped[EXIT_CODES[code]], code


# --- srvwire interface ------------------------------------------------------------------------


def sections(out: str) -> dict[str, list[str]]:
    """Split ``interface list`` output into its headings and their indented lines."""
    found: dict[str, list[str]] = {}
    current: list[str] = []
    for line in out.splitlines():
        if line.startswith("    "):
            current.append(line.removeprefix("    "))
        else:
            current = found.setdefault(line, [])
    return found


def test_interface_list_groups_types_by_kind(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    code, out, err = run(capsys, "interface", "list", "--path", str(packages))
    assert (code, err) == (ExitCode.OK, "")
    listed = sections(out)
    assert list(listed) == ["Messages:", "Services:", "Actions:"]
    assert {"demo/msg/Vec", "geometry_msgs/msg/Pose"} <= set(listed["Messages:"])
    assert {"demo/srv/Measure", "std_srvs/srv/Trigger"} <= set(listed["Services:"])
    assert "demo/action/Go" in listed["Actions:"]
    for heading, kind in (("Messages:", "msg"), ("Services:", "srv"), ("Actions:", "action")):
        assert listed[heading] == sorted(listed[heading])
        assert all(name.split("/")[1] == kind for name in listed[heading])


@pytest.mark.parametrize(
    ("flags", "headings"),
    [
        (["-m"], ["Messages:"]),
        (["-s"], ["Services:"]),
        (["-a"], ["Actions:"]),
        (["-m", "-a"], ["Messages:", "Actions:"]),
    ],
)
def test_interface_list_filters(
    capsys: pytest.CaptureFixture[str], packages: Path, flags: list[str], headings: list[str]
) -> None:
    code, out, _ = run(capsys, "interface", "list", "--path", str(packages), *flags)
    assert code == ExitCode.OK
    assert list(sections(out)) == headings


def test_interface_packages(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, err = run(capsys, "interface", "packages", "--path", str(packages))
    assert (code, err) == (ExitCode.OK, "")
    names = out.splitlines()
    assert names == sorted(names)
    assert {"demo", "std_srvs", "example_interfaces", "geometry_msgs"} <= set(names)


def test_interface_package(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, err = run(capsys, "interface", "package", "demo", "--path", str(packages))
    assert (code, err) == (ExitCode.OK, "")
    assert out == "demo/action/Go\ndemo/msg/Segment\ndemo/msg/Vec\ndemo/srv/Measure\n"


def test_interface_package_unknown(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, err = run(capsys, "interface", "package", "dmeo", "--path", str(packages))
    assert (code, out) == (ExitCode.FAILURE, "")
    message = one_error_line(err)
    assert message.startswith("no interface package 'dmeo' in ")
    assert message.endswith("(did you mean: demo?)")


def test_interface_path_from_the_environment(
    capsys: pytest.CaptureFixture[str], packages: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SRVWIRE_INTERFACE_PATH", str(packages))
    code, out, _ = run(capsys, "interface", "package", "demo")
    assert code == ExitCode.OK and "demo/msg/Vec\n" in out


def test_interface_show_bundled_pose(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "interface", "show", "geometry_msgs/msg/Pose")
    assert (code, err) == (ExitCode.OK, "")
    assert out == (
        "# Where something is and which way it faces.\n"
        "\n"
        "Point position  # The location.\n"
        "\tfloat64 x\n"
        "\tfloat64 y\n"
        "\tfloat64 z\n"
        "Quaternion orientation  # The heading, as a rotation from the frame's axes.\n"
        "\tfloat64 x 0.0\n"
        "\tfloat64 y 0.0\n"
        "\tfloat64 z 0.0\n"
        "\tfloat64 w 1.0\n"
    )


def test_interface_show_keeps_top_level_comments_only(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    code, out, err = run(capsys, "interface", "show", "demo/srv/Measure", "--path", str(packages))
    assert (code, err) == (ExitCode.OK, "")
    assert out == (
        "# Measure a segment.\n"
        "Segment segment  # What to measure.\n"
        "\tVec start\n"
        "\t\tfloat64 x\n"
        "\t\tfloat64 y 1.5\n"
        "\tdemo/Vec[2] ends\n"
        "\t\tfloat64 x\n"
        "\t\tfloat64 y 1.5\n"
        '\tstring label "a # b"\n'
        "---\n"
        "float64 length  # How long it is.\n"
        "Vec direction\n"
        "\tfloat64 x\n"
        "\tfloat64 y 1.5\n"
    )


def test_interface_show_all_comments(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, _ = run(
        capsys, "interface", "show", "demo/Segment", "--all-comments", "--path", str(packages)
    )
    assert code == ExitCode.OK
    assert out == (
        "# A straight line between two points.\n"
        "\n"
        "# Where it starts.\n"
        "Vec start\n"
        "\t# A 2-D vector.\n"
        "\tfloat64 x  # Along x.\n"
        "\tfloat64 y 1.5  # Along y.\n"
        "demo/Vec[2] ends  # Both ends.\n"
        "\t# A 2-D vector.\n"
        "\tfloat64 x  # Along x.\n"
        "\tfloat64 y 1.5  # Along y.\n"
        "string label \"a # b\"  # A label; the quoted '#' is not a comment.\n"
    )


def test_interface_show_no_comments(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, _ = run(
        capsys, "interface", "show", "demo/action/Go", "--no-comments", "--path", str(packages)
    )
    assert code == ExitCode.OK
    assert out == (
        "Vec target\n\tfloat64 x\n\tfloat64 y 1.5\n---\nbool reached\n---\nfloat64 remaining\n"
    )


def test_interface_show_comment_flags_exclude_each_other(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, _, err = run(
        capsys, "interface", "show", "std_srvs/Trigger", "--all-comments", "--no-comments"
    )
    assert code == ExitCode.USAGE
    assert one_error_line(err).startswith(
        "argument --no-comments: not allowed with argument --all-comments"
    )


def test_interface_show_unknown_type(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "interface", "show", "std_srvs/srv/Triger")
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == (
        "no service 'Triger' in package 'std_srvs' (did you mean: std_srvs/srv/Trigger?)"
    )


def test_interface_show_broken_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    bad = write(tmp_path, "broken/msg/Bad.msg", "int32 ok\nint32 2bad\n")
    code, out, err = run(capsys, "interface", "show", "broken/Bad", "--path", str(tmp_path))
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err).startswith(f"{bad}:2:7: ")


def test_interface_show_all_comments_of_nested_bundled_types(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, _ = run(capsys, "interface", "show", "geometry_msgs/Pose", "--all-comments")
    assert code == ExitCode.OK
    assert out.startswith(
        "# Where something is and which way it faces.\n"
        "\n"
        "Point position  # The location.\n"
        "\t# A location in 3-D space.\n"
        "\n"  # a blank line stays blank: no tab
        "\tfloat64 x  # Coordinate along the x axis.\n"
    )


def test_interface_proto_of_a_service(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "interface", "proto", "example_interfaces/srv/AddTwoInts")
    assert (code, out, err) == (ExitCode.OK, '"a: 0\nb: 0\n"\n', "")


def test_interface_proto_flow_without_quotes(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(
        capsys, "interface", "proto", "example_interfaces/AddTwoInts", "--flow", "--no-quotes"
    )
    assert (code, out) == (ExitCode.OK, "{a: 0, b: 0}\n")


def test_interface_proto_of_nested_messages(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    code, out, _ = run(capsys, "interface", "proto", "demo/Segment", "--path", str(packages))
    assert code == ExitCode.OK
    assert out == (
        '"start:\n'
        "  x: 0.0\n"
        "  y: 1.5\n"
        "ends:\n"
        "- x: 0.0\n"
        "  y: 1.5\n"
        "- x: 0.0\n"
        "  y: 1.5\n"
        "label: 'a # b'\n"
        '"\n'
    )


def test_interface_proto_of_an_action_is_its_goal(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    code, out, _ = run(
        capsys, "interface", "proto", "demo/Go", "--flow", "--no-quotes", "--path", str(packages)
    )
    assert (code, out) == (ExitCode.OK, "{target: {x: 0.0, y: 1.5}}\n")


def test_interface_proto_of_a_name_without_package_suggests_full_names(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, err = run(capsys, "interface", "proto", "AddTwoInts")
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == (
        "'AddTwoInts' has no package: write pkg/kind/Name or pkg/Name, as ros2 interface does; "
        "did you mean example_interfaces/srv/AddTwoInts?"
    )


def test_interface_proto_refuses_a_template_too_large_to_send(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # 1024 rows of 1024 values and one more is one more than a 1 MiB message could carry.
    write(tmp_path, "big/msg/Row.msg", "float64[1024] cells\n")
    write(tmp_path, "big/srv/Rows.srv", "Row[1024] rows\nint8 pad\n---\n")
    write(tmp_path, "big/srv/Huge.srv", "int32 a\nint32[4294967295] values\n---\n")
    write(tmp_path, "big/msg/Few.msg", "Row[2] rows\n")
    code, out, err = run(capsys, "interface", "proto", "big/srv/Huge", "--path", str(tmp_path))
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == (
        "the template of big/Huge_Request would hold 4294967296 values, 4294967295 of them in "
        "the field 'values' (int32[4294967295]), more than the 1048576 bytes of a message "
        "srvwire call sends by default (srvwire call --max-message-size raises its limit): "
        "write the values of such a type yourself"
    )
    code, out, err = run(capsys, "interface", "proto", "big/srv/Rows", "--path", str(tmp_path))
    assert (code, out) == (ExitCode.FAILURE, "")
    assert "would hold 1048577 values, 1048576 of them in the field 'rows' (big/Row[1024])" in (
        one_error_line(err)
    )
    code, out, err = run(capsys, "interface", "proto", "big/Few", "--path", str(tmp_path))
    assert (code, err) == (ExitCode.OK, "")
    assert out.count("- 0.0\n") == 2 * 1024


def test_interface_proto_of_an_empty_request(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "interface", "proto", "std_srvs/srv/Trigger")
    assert (code, out) == (ExitCode.OK, '"{}\n"\n')


def test_interface_check_good_files(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, err = run(capsys, "interface", "check", str(packages))
    assert (code, out, err) == (ExitCode.OK, "checked 4 files, 0 errors\n", "")


def test_interface_check_reports_each_broken_file(
    capsys: pytest.CaptureFixture[str], packages: Path, tmp_path: Path
) -> None:
    first = write(packages, "demo/msg/Bad.msg", "int32 ok\nint32 2bad\n")
    second = write(tmp_path, "other/srv/Half.srv", "int32 a\n")
    write(packages, "demo/msg/README.md", "not an interface file")
    code, out, err = run(capsys, "interface", "check", str(packages), str(second))
    assert (code, err) == (ExitCode.FAILURE, "")
    lines = out.splitlines()
    assert len(lines) == 3
    assert lines[0].startswith(f"{first}:2:7: ")
    assert lines[1] == (
        f"{second}:2:1: a service needs a '---' line between the request and the response; "
        "found none"
    )
    assert lines[2] == "checked 6 files, 2 errors"


def test_interface_check_one_file(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    code, out, _ = run(capsys, "interface", "check", str(packages / "demo/msg/Vec.msg"))
    assert (code, out) == (ExitCode.OK, "checked 1 file, 0 errors\n")


def test_interface_check_resolves_nested_types(
    capsys: pytest.CaptureFixture[str], packages: Path, tmp_path: Path
) -> None:
    lost = write(packages, "demo/msg/Lost.msg", "# Nested types.\nVec here\n  Missing gone\n")
    uses = write(tmp_path, "app/srv/Use.srv", "demo/Segment s\n---\ngeometry_msgs/Nope n\n")
    code, out, err = run(
        capsys, "interface", "check", str(packages), str(uses), "--path", str(packages)
    )
    assert (code, err) == (ExitCode.FAILURE, "")
    assert out.splitlines() == [
        f"{lost}:3:3: unknown type 'demo/Missing' of field 'gone': "
        "no message 'Missing' in package 'demo'",
        f"{uses}:3:1: unknown type 'geometry_msgs/Nope' of field 'n': "
        "no message 'Nope' in package 'geometry_msgs'",
        "checked 6 files, 2 errors",
    ]


def test_interface_check_counts_a_broken_nested_file_once(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    write(packages, "demo/msg/Outer.msg", "Vec v\n")
    broken = write(packages, "demo/msg/Vec.msg", "float64 x\nWhere w\n")
    code, out, _ = run(capsys, "interface", "check", str(packages))
    assert code == ExitCode.FAILURE
    assert out.splitlines() == [
        f"{broken}:2:1: unknown type 'demo/Where' of field 'w': "
        "no message 'Where' in package 'demo'",
        "checked 5 files, 1 error",
    ]


def test_interface_check_reports_a_cycle_that_spans_two_files(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # Each file's load stops in the other: the cycle is reported at both fields, once each,
    # and Q3, which only nests the cycle, adds no error of its own.
    first = write(tmp_path, "cyc_pkg/msg/Q1.msg", "cyc_pkg/Q2 x\n")
    second = write(tmp_path, "cyc_pkg/msg/Q2.msg", "cyc_pkg/Q1 x\n")
    write(tmp_path, "cyc_pkg/msg/Q3.msg", "Q2[] x\n")
    code, out, err = run(capsys, "interface", "check", str(tmp_path / "cyc_pkg"))
    assert (code, err) == (ExitCode.FAILURE, "")
    assert out.splitlines() == [
        f"{second}:1:1: field 'x' makes a message contain itself "
        "(cyc_pkg/msg/Q1 -> cyc_pkg/msg/Q2 -> cyc_pkg/msg/Q1); "
        "a message cannot nest itself, directly or through other messages",
        f"{first}:1:1: field 'x' makes a message contain itself "
        "(cyc_pkg/msg/Q2 -> cyc_pkg/msg/Q1 -> cyc_pkg/msg/Q2); "
        "a message cannot nest itself, directly or through other messages",
        "checked 3 files, 2 errors",
    ]


def test_interface_check_nested_type_outside_the_checked_files(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    broken = write(packages, "demo/msg/Vec.msg", "float64 x\nWhere w\n")
    outer = write(packages, "demo/msg/Outer.msg", "Vec v\n")
    code, out, _ = run(capsys, "interface", "check", str(outer))
    assert code == ExitCode.FAILURE
    assert out.splitlines() == [
        f"{broken}:2:1: unknown type 'demo/Where' of field 'w': "
        "no message 'Where' in package 'demo'",
        "checked 1 file, 1 error",
    ]


def test_interface_check_missing_path(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    missing = tmp_path / "nowhere"
    code, out, err = run(capsys, "interface", "check", str(missing))
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == f"no such file or folder: {missing}"


# --- a live server for call and service -------------------------------------------------------


@dataclass
class Remote:
    """A server running in a thread of its own, and where its extra interfaces live."""

    url: str
    interfaces: Path


def start_in_thread(server: Server) -> tuple[str, Callable[[], None]]:
    """Serve ``server`` on a free port from a thread with its own loop; return url and stop."""
    ready = threading.Event()
    state: dict[str, Any] = {}

    async def serve_until_stopped() -> None:
        state["loop"] = asyncio.get_running_loop()
        state["stop"] = stop = asyncio.Event()
        async with serve(server, "127.0.0.1", 0) as running:
            state["url"] = running.url
            ready.set()
            await stop.wait()

    thread = threading.Thread(target=asyncio.run, args=(serve_until_stopped(),), daemon=True)
    thread.start()
    assert ready.wait(scaled(10)), "the test server did not start"

    def stop() -> None:
        state["loop"].call_soon_threadsafe(state["stop"].set)
        thread.join(scaled(10))
        assert not thread.is_alive(), "the test server did not stop"

    return state["url"], stop


@pytest.fixture(scope="module")
def remote(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Remote]:
    """A server offering the services every call and service test uses."""
    interfaces = tmp_path_factory.mktemp("remote") / "interfaces"
    for relative, text in (
        ("demo/msg/Vec.msg", VEC),
        ("demo/msg/Segment.msg", SEGMENT),
        ("demo/srv/Measure.srv", MEASURE),
    ):
        write(interfaces, relative, text)
    loader = InterfaceLoader([interfaces, *default_search_path()])
    add_two_ints: Any = loader.load_service("example_interfaces/srv/AddTwoInts")
    trigger: Any = loader.load_service("std_srvs/srv/Trigger")
    measure = loader.load_service("demo/srv/Measure")

    def add(request: Any) -> Any:
        return add_two_ints.Response(sum=request.a + request.b)

    def triggered(request: Any) -> Any:
        return trigger.Response(success=True, message="done")

    async def hang(request: Any) -> Any:
        await asyncio.Event().wait()  # never set: only the deadline ends this call

    def fail(request: Any) -> Any:
        raise RuntimeError("the handler broke")

    def refuse(request: Any) -> Any:
        raise ServiceError(42, "not now", {"retry_after": 5})

    def unavailable(request: Any) -> Any:
        raise ServiceUnavailable("going down")

    def exhausted(request: Any) -> Any:
        raise ResourceExhausted("too busy")

    def measured(request: Any) -> Any:
        start = request.segment.start
        return {"length": abs(start.x) + abs(start.y), "direction": {"x": 1.0, "y": 0.0}}

    server = Server(grace_period=0)
    server.add_service("/add_two_ints", add_two_ints, add)
    server.add_service("/trigger", trigger, triggered)
    server.add_service("/robot1/trigger", trigger, triggered)
    server.add_service("/hang", trigger, hang)
    server.add_service("/fail", trigger, fail)
    server.add_service("/refuse", trigger, refuse)
    server.add_service("/unavailable", trigger, unavailable)
    server.add_service("/exhausted", trigger, exhausted)
    server.add_service("/measure", measure, measured)
    url, stop = start_in_thread(server)
    yield Remote(url, interfaces)
    stop()


@pytest.fixture
def closed_url() -> str:
    """A URL nobody listens on: a port that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    return f"ws://127.0.0.1:{port}"


def call(capsys: pytest.CaptureFixture[str], remote: Remote, *argv: str) -> tuple[int, str, str]:
    return run(capsys, "call", "--url", remote.url, "--timeout", str(scaled(5)), *argv)


# --- srvwire call -----------------------------------------------------------------------------


def test_call_prints_request_and_response_like_ros(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/add_two_ints", "{a: 1, b: 2}")
    assert (code, err) == (ExitCode.OK, "")
    assert out == (
        "requester: making request: example_interfaces.srv.AddTwoInts_Request(a=1, b=2)\n"
        "\n"
        "response:\n"
        "example_interfaces.srv.AddTwoInts_Response(sum=3)\n"
    )


@pytest.mark.parametrize(
    "srv_type", ["example_interfaces/srv/AddTwoInts", "example_interfaces/AddTwoInts"]
)
def test_call_with_an_explicit_type(
    capsys: pytest.CaptureFixture[str], remote: Remote, srv_type: str
) -> None:
    code, out, _ = call(capsys, remote, "add_two_ints", srv_type, "{a: 40, b: 2}")
    assert code == ExitCode.OK
    assert out.endswith("\nresponse:\nexample_interfaces.srv.AddTwoInts_Response(sum=42)\n")


def test_call_json_prints_only_the_response(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/add_two_ints", "{a: 1, b: 2}", "--json")
    assert (code, out, err) == (ExitCode.OK, '{"sum": 3}\n', "")


def strict_json(line: str) -> Any:
    """``line`` read as standard JSON: the bare tokens NaN and Infinity are refused."""

    def refuse(token: str) -> Any:
        raise ValueError(f"{token} is not JSON")

    return json.loads(line, parse_constant=refuse)


def test_call_json_writes_a_float_that_is_not_finite_as_a_string(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    # Standard JSON has no NaN or Infinity: --json writes them as the strings a server writes
    # by default, which a client reads back as the same floats.
    path = ("--path", str(remote.interfaces))
    for x, expected in ((".inf", "Infinity"), ("-.inf", "Infinity"), (".nan", "NaN")):
        request = f"{{segment: {{start: {{x: {x}, y: 0}}}}}}"
        code, out, err = call(capsys, remote, "/measure", request, "--json", *path)
        assert (code, err) == (ExitCode.OK, "")
        assert strict_json(out)["length"] == expected  # abs() of both infinities is +inf
    code, out, _ = call(
        capsys, remote, "/measure", "{segment: {start: {x: 2, y: 0}}}", "--json", *path
    )
    assert code == ExitCode.OK and strict_json(out)["length"] == 2.0


def test_call_reads_numbers_with_an_exponent_as_json_spells_them(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    # YAML 1.1 reads 1e3 as a string; VALUES reads it as JSON does, so pasted JSON and --json's
    # own output (which writes 1e+16 and 1e-07) read back.
    path = ("--path", str(remote.interfaces))
    for x, y, length in (
        ("1e3", "2E-1", 1000.2),
        ("1e+16", "0", 1e16),
        ("-1.5e1", "1e-07", 15.0000001),
    ):
        request = f'{{"segment": {{"start": {{"x": {x}, "y": {y}}}}}}}'
        code, out, err = call(capsys, remote, "/measure", request, "--json", *path)
        assert (code, err) == (ExitCode.OK, "")
        assert strict_json(out)["length"] == pytest.approx(length)
    # An integer stays an integer, and a string stays a string.
    code, out, err = call(capsys, remote, "/add_two_ints", "{a: 10, b: 2}", "--json")
    assert (code, out) == (ExitCode.OK, '{"sum": 12}\n')
    code, out, err = call(capsys, remote, "/add_two_ints", "{a: '1e3', b: 2}", "--json")
    assert code == ExitCode.INVALID_PARAMS, (out, err)


def test_call_type_alone_and_defaults(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, _ = call(capsys, remote, "/trigger", "std_srvs/srv/Trigger")
    assert code == ExitCode.OK
    assert out == (
        "requester: making request: std_srvs.srv.Trigger_Request()\n"
        "\n"
        "response:\n"
        "std_srvs.srv.Trigger_Response(success=True, message='done')\n"
    )


def test_call_nested_types(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, _ = call(
        capsys,
        remote,
        "/measure",
        "{segment: {start: {x: -3}}}",
        "--path",
        str(remote.interfaces),
    )
    assert code == ExitCode.OK
    assert out == (
        "requester: making request: demo.srv.Measure_Request(segment=demo.msg.Segment("
        "start=demo.msg.Vec(x=-3.0, y=1.5), "
        "ends=[demo.msg.Vec(x=0.0, y=1.5), demo.msg.Vec(x=0.0, y=1.5)], label='a # b'))\n"
        "\n"
        "response:\n"
        "demo.srv.Measure_Response(length=4.5, direction=demo.msg.Vec(x=1.0, y=0.0))\n"
    )


def test_call_a_type_not_on_the_local_path_is_typed_from_the_server(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/measure", "{segment: {start: {x: -3}}}")
    assert (code, err) == (ExitCode.OK, "")
    assert out == (
        "requester: making request: demo.srv.Measure_Request(segment=demo.msg.Segment("
        "start=demo.msg.Vec(x=-3.0, y=1.5), ends=[demo.msg.Vec(x=0.0, y=1.5), "
        "demo.msg.Vec(x=0.0, y=1.5)], label='a # b'))\n"
        "\n"
        "response:\n"
        "demo.srv.Measure_Response(length=4.5, direction=demo.msg.Vec(x=1.0, y=0.0))\n"
    )


def test_call_repeats_at_a_rate(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, _ = call(capsys, remote, "/add_two_ints", "{a: 2, b: 2}", "-r", "100", "-n", "3")
    assert code == ExitCode.OK
    block = (
        "requester: making request: example_interfaces.srv.AddTwoInts_Request(a=2, b=2)\n"
        "\n"
        "response:\n"
        "example_interfaces.srv.AddTwoInts_Response(sum=4)\n"
    )
    assert out == "\n".join([block] * 3)


def test_call_count_with_json(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, _ = call(capsys, remote, "/trigger", "--json", "--count", "2")
    assert (code, out) == (ExitCode.OK, '{"success": true, "message": "done"}\n' * 2)


def test_call_url_from_the_environment(
    capsys: pytest.CaptureFixture[str], remote: Remote, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SRVWIRE_URL", remote.url)
    code, out, _ = run(capsys, "call", "/add_two_ints", "{a: 1, b: 1}", "--json")
    assert (code, out) == (ExitCode.OK, '{"sum": 2}\n')


@pytest.mark.parametrize(
    ("values", "message"),
    [
        (
            "{a: 1",
            "invalid VALUES at line 1, column 6: expected ',' or '}', but got '<stream end>'",
        ),
        (
            "{a: 1}\n b: 2",
            "invalid VALUES at line 2, column 2: "
            "expected '<document start>', but found '<block mapping start>'",
        ),
        (
            "[1, 2]",
            "invalid VALUES: expected a YAML mapping such as '{a: 1, b: 2}', got list [1, 2]",
        ),
        ("7", "invalid VALUES: expected a YAML mapping such as '{a: 1, b: 2}', got int 7"),
    ],
)
def test_call_bad_values_exit_2_before_connecting(
    capsys: pytest.CaptureFixture[str], closed_url: str, values: str, message: str
) -> None:
    code, out, err = run(capsys, "call", "/add_two_ints", values, "--url", closed_url)
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == message


def test_call_unknown_type_exits_1(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, err = call(capsys, remote, "/add_two_ints", "example_interfaces/srv/AddThreeInts")
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == (
        "no service 'AddThreeInts' in package 'example_interfaces' "
        "(did you mean: example_interfaces/srv/AddTwoInts?)"
    )


def test_call_server_down_exits_3(capsys: pytest.CaptureFixture[str], closed_url: str) -> None:
    code, out, err = run(capsys, "call", "/add_two_ints", "{a: 1}", "--url", closed_url)
    assert (code, out) == (ExitCode.UNAVAILABLE, "")
    assert one_error_line(err).startswith(
        f"ServiceUnavailable: UNAVAILABLE (-32003): cannot connect to {closed_url}: "
    )


def test_call_server_unavailable_exits_3(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, _, err = call(capsys, remote, "/unavailable")
    assert code == ExitCode.UNAVAILABLE
    assert one_error_line(err) == (
        "ServiceUnavailable: UNAVAILABLE (-32003) [/unavailable]: going down"
    )


def test_call_deadline_exits_4(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    timeout = f"{scaled(0.2):g}"
    code, out, err = run(capsys, "call", "/hang", "--url", remote.url, "--timeout", timeout)
    assert code == ExitCode.DEADLINE_EXCEEDED
    assert out == ("requester: making request: std_srvs.srv.Trigger_Request()\n")
    assert one_error_line(err).startswith("DeadlineExceeded: DEADLINE_EXCEEDED (-32001) [/hang]: ")


def test_call_unknown_service_exits_5_with_candidates(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/add_two_intz", "{a: 1, b: 2}")
    assert code == ExitCode.SERVICE_NOT_FOUND
    assert out == "requester: making request: {'a': 1, 'b': 2}\n"
    assert one_error_line(err) == (
        "ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/add_two_intz]: no service named "
        "/add_two_intz; did you mean /add_two_ints?"
    )


def test_call_invalid_values_checked_locally_exit_6(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/add_two_ints", "{a: one, c: 2}")
    assert (code, out) == (ExitCode.INVALID_PARAMS, "")
    assert one_error_line(err) == (
        "InvalidParams: INVALID_PARAMS (-32602) [/add_two_ints]: VALUES do not fit "
        "example_interfaces/srv/AddTwoInts (checked locally, not sent): "
        "a: Input should be a valid integer (and 1 more) "
        '(data: {"errors": [{"path": "a", "message": "Input should be a valid integer", '
        '"type": "int_type"}, {"path": "c", "message": "Extra inputs are not permitted", '
        '"type": "extra_forbidden"}]})'
    )


def test_call_invalid_params_of_a_type_the_server_described_exit_6(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    # demo/srv/Measure is not on the local path: the server's description types it here.
    code, _, err = call(capsys, remote, "/measure", "{segment: {start: {x: far}}}")
    assert code == ExitCode.INVALID_PARAMS
    assert one_error_line(err).startswith(
        "InvalidParams: INVALID_PARAMS (-32602) [/measure]: VALUES do not fit demo/srv/Measure "
        "(checked locally, not sent): segment.start.x: "
    )


@pytest.mark.parametrize(
    ("service", "message"),
    [
        ("/fail", "InternalError: INTERNAL (-32603) [/fail]: "),
        (
            "/refuse",
            'ServiceError: application error (42) [/refuse]: not now (data: {"retry_after": 5})',
        ),
    ],
)
def test_call_handler_failures_exit_7(
    capsys: pytest.CaptureFixture[str], remote: Remote, service: str, message: str
) -> None:
    code, _, err = call(capsys, remote, service)
    assert code == ExitCode.SERVICE_FAILED
    assert one_error_line(err).startswith(message)


@pytest.mark.parametrize(
    ("error", "line"),
    [
        # The message offers the candidates: the data does not repeat them.
        (
            ServiceNotFound("no service named /ad; did you mean /add?", {"candidates": ["/add"]}),
            "ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/ad]: no service named /ad; "
            "did you mean /add?",
        ),
        # A peer whose message does not offer them: the data still does, with the rest.
        (
            ServiceNotFound("unknown method", {"candidates": ["/add"], "hint": "x"}),
            "ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/ad]: unknown method "
            '(data: {"candidates": ["/add"], "hint": "x"})',
        ),
        # Mentioning /add_two_ints is not offering /add_two.
        (
            ServiceNotFound("did you mean /add_two_ints?", {"candidates": ["/add_two"]}),
            "ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/ad]: did you mean /add_two_ints? "
            '(data: {"candidates": ["/add_two"]})',
        ),
        # Other errors keep all their data.
        (
            ServiceError(42, "not now, /add", {"candidates": ["/add"]}),
            "ServiceError: application error (42) [/ad]: not now, /add "
            '(data: {"candidates": ["/add"]})',
        ),
    ],
)
def test_an_error_line_says_each_fact_once(error: RPCError, line: str) -> None:
    error.service = "/ad"
    assert cli._describe_rpc_error(error) == line


def test_call_other_errors_exit_8(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, _, err = call(capsys, remote, "/exhausted")
    assert code == ExitCode.OTHER_RPC_ERROR
    assert one_error_line(err) == (
        "ResourceExhausted: RESOURCE_EXHAUSTED (-32004) [/exhausted]: too busy"
    )


def test_call_bad_url_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(capsys, "call", "/trigger", "--url", "http://localhost:1")
    assert code == ExitCode.USAGE
    assert one_error_line(err).startswith("bad --url: not a WebSocket URL: 'http://localhost:1'")


def test_call_values_from_stdin(
    capsys: pytest.CaptureFixture[str], remote: Remote, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO("a: 1\nb: 2\n"))
    code, out, err = call(capsys, remote, "/add_two_ints", "--json", "-")
    assert (code, out, err) == (ExitCode.OK, '{"sum": 3}\n', "")


def test_call_values_from_a_file(
    capsys: pytest.CaptureFixture[str], remote: Remote, tmp_path: Path
) -> None:
    request = write(tmp_path, "request.yaml", "a: 40\nb: 2\n")
    code, out, err = call(capsys, remote, "/add_two_ints", f"@{request}", "--json")
    assert (code, out, err) == (ExitCode.OK, '{"sum": 42}\n', "")


def test_call_values_from_a_missing_file_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    missing = tmp_path / "nowhere.yaml"
    code, out, err = run(capsys, "call", "/add_two_ints", f"@{missing}")
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == (f"cannot read VALUES from {missing}: No such file or directory")


def test_call_values_from_a_folder_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    code, _, err = run(capsys, "call", "/add_two_ints", f"@{tmp_path}")
    assert code == ExitCode.USAGE
    assert one_error_line(err).startswith(f"cannot read VALUES from {tmp_path}: ")


@pytest.mark.parametrize(
    ("source", "text", "message"),
    [
        (
            "-",
            "a: [1\n",
            "invalid VALUES from standard input at line 2, column 1: "
            "expected ',' or ']', but got '<stream end>'",
        ),
        (
            "-",
            "[1, 2]\n",
            "invalid VALUES from standard input: expected a YAML mapping such as "
            "'{a: 1, b: 2}', got list [1, 2]",
        ),
        (
            "@{file}",
            "a: 1\n b: 2\n",
            "invalid VALUES in {file} at line 2, column 3: mapping values are not allowed here",
        ),
    ],
)
def test_call_bad_values_from_stdin_or_a_file_exit_2(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    source: str,
    text: str,
    message: str,
) -> None:
    file = write(tmp_path, "request.yaml", text)
    monkeypatch.setattr("sys.stdin", io.StringIO(text))
    code, out, err = run(capsys, "call", "/add_two_ints", source.replace("{file}", str(file)))
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == message.replace("{file}", str(file))


def test_call_url_without_a_scheme_means_ws(
    capsys: pytest.CaptureFixture[str], remote: Remote, monkeypatch: pytest.MonkeyPatch
) -> None:
    host_port = remote.url.removeprefix("ws://")
    code, out, _ = run(
        capsys, "call", "/add_two_ints", "{a: 1, b: 2}", "--json", "--url", host_port
    )
    assert (code, out) == (ExitCode.OK, '{"sum": 3}\n')
    monkeypatch.setenv("SRVWIRE_URL", host_port)
    code, out, _ = run(capsys, "service", "type", "/trigger")
    assert (code, out) == (ExitCode.OK, "std_srvs/srv/Trigger\n")


def test_call_url_without_a_port_exits_2(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    code, _, err = run(capsys, "call", "/trigger", "--url", "robot")
    assert code == ExitCode.USAGE
    assert one_error_line(err) == (
        "bad --url: 'robot' is not a server address; "
        "expected ws://HOST:PORT, wss://HOST:PORT or HOST:PORT"
    )
    monkeypatch.setenv("SRVWIRE_URL", "robot")
    code, _, err = run(capsys, "service", "list")
    assert code == ExitCode.USAGE
    assert one_error_line(err) == (
        "bad $SRVWIRE_URL: 'robot' is not a server address; "
        "expected ws://HOST:PORT, wss://HOST:PORT or HOST:PORT"
    )


def test_call_url_ipv6_host_and_port(capsys: pytest.CaptureFixture[str], closed_url: str) -> None:
    port = closed_url.rsplit(":", 1)[1]
    code, _, err = run(capsys, "call", "/trigger", "--url", f"[::1]:{port}")
    assert code in (ExitCode.UNAVAILABLE,)
    assert f"cannot connect to ws://[::1]:{port}" in one_error_line(err)


@pytest.mark.parametrize(("argv", "expected"), [([], ExitCode.INTERRUPTED), (["-r", "1"], 0)])
def test_call_interrupted(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    argv: list[str],
    expected: int,
) -> None:
    def interrupt(*args: Any, **kwargs: Any) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_common, "connect", interrupt)
    code, out, err = run(capsys, "call", "/trigger", *argv)
    assert (code, out) == (expected, "")
    if expected:
        assert one_error_line(err) == "interrupted"
    else:
        assert err == ""


@pytest.mark.parametrize(
    "argv",
    [
        ["/add_two_ints", "--json", "{a: 1, b: 2}"],
        ["/add_two_ints", "--json", "example_interfaces/AddTwoInts", "{a: 1, b: 2}"],
        ["/add_two_ints", "example_interfaces/AddTwoInts", "--json", "{a: 1, b: 2}"],
        ["--json", "/add_two_ints", "{a: 1, b: 2}"],
    ],
)
def test_call_positionals_around_options(
    capsys: pytest.CaptureFixture[str], remote: Remote, argv: list[str]
) -> None:
    code, out, _ = call(capsys, remote, *argv)
    assert (code, out) == (ExitCode.OK, '{"sum": 3}\n')


@pytest.mark.parametrize(
    "argv",
    [
        ["/add_two_ints", "--json", "example_interfaces/AddTwoInts", "{a: 1}", "{b: 2}"],
        ["/add_two_ints", "--json", "{a: 1}", "-x"],
    ],
)
def test_call_too_many_arguments(capsys: pytest.CaptureFixture[str], argv: list[str]) -> None:
    code, out, err = run(capsys, "call", *argv)
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err).startswith("unrecognized arguments: ")


def test_unrecognized_arguments_elsewhere(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(capsys, "interface", "packages", "extra")
    assert code == ExitCode.USAGE
    assert one_error_line(err) == "unrecognized arguments: extra (see 'srvwire --help')"


@pytest.fixture
def no_discover(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``rpc.discover`` fail, to prove ``call`` reads the advertised types instead."""

    async def refuse(self: Client, **kwargs: Any) -> Any:
        raise AssertionError("call asked the server for rpc.discover")

    monkeypatch.setattr(Client, "list_services", refuse)


@pytest.mark.usefixtures("no_discover")
def test_call_takes_the_type_from_the_advertisement_without_a_round_trip(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/add_two_ints", "{a: 1, b: 2}", "--json")
    assert (code, out, err) == (ExitCode.OK, '{"sum": 3}\n', "")


@pytest.mark.usefixtures("no_discover")
def test_call_with_the_wrong_type_exits_2(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = call(capsys, remote, "/trigger", "std_srvs/srv/Empty")
    assert (code, out) == (ExitCode.USAGE, "")
    assert (
        one_error_line(err)
        == "/trigger is a service of type std_srvs/srv/Trigger, not std_srvs/srv/Empty"
    )


# --- srvwire service --------------------------------------------------------------------------


def service(capsys: pytest.CaptureFixture[str], remote: Remote, *argv: str) -> tuple[int, str, str]:
    return run(capsys, "service", *argv, "--url", remote.url, "--timeout", str(scaled(5)))


SERVICES = [
    ("/add_two_ints", "example_interfaces/srv/AddTwoInts"),
    ("/exhausted", "std_srvs/srv/Trigger"),
    ("/fail", "std_srvs/srv/Trigger"),
    ("/hang", "std_srvs/srv/Trigger"),
    ("/measure", "demo/srv/Measure"),
    ("/refuse", "std_srvs/srv/Trigger"),
    ("/robot1/trigger", "std_srvs/srv/Trigger"),
    ("/trigger", "std_srvs/srv/Trigger"),
    ("/unavailable", "std_srvs/srv/Trigger"),
]


def test_service_list(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, err = service(capsys, remote, "list")
    assert (code, err) == (ExitCode.OK, "")
    assert out == "".join(f"{name}\n" for name, _ in SERVICES)


def test_service_list_with_types(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, _ = service(capsys, remote, "list", "-t")
    assert code == ExitCode.OK
    assert out == "".join(f"{name} [{type_name}]\n" for name, type_name in SERVICES)


def test_service_list_count(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, _ = service(capsys, remote, "list", "--count-services")
    assert (code, out) == (ExitCode.OK, f"{len(SERVICES)}\n")


def test_service_list_server_down_exits_3(
    capsys: pytest.CaptureFixture[str], closed_url: str
) -> None:
    code, out, err = run(capsys, "service", "list", "--url", closed_url)
    assert (code, out) == (ExitCode.UNAVAILABLE, "")
    assert one_error_line(err).startswith("ServiceUnavailable: UNAVAILABLE (-32003): ")


@pytest.mark.parametrize("name", ["/add_two_ints", "add_two_ints"])
def test_service_type(capsys: pytest.CaptureFixture[str], remote: Remote, name: str) -> None:
    code, out, _ = service(capsys, remote, "type", name)
    assert (code, out) == (ExitCode.OK, "example_interfaces/srv/AddTwoInts\n")


def test_service_type_unknown_exits_5(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, err = service(capsys, remote, "type", "/trigerr")
    assert (code, out) == (ExitCode.SERVICE_NOT_FOUND, "")
    assert one_error_line(err) == (
        "ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/trigerr]: no service named /trigerr; "
        "did you mean /trigger, /robot1/trigger?"
    )


def test_service_describe_prints_the_servers_definition(
    capsys: pytest.CaptureFixture[str], remote: Remote, packages: Path
) -> None:
    # demo/srv/Measure is not on the local path: what is printed is the server's.
    _, local, _ = run(capsys, "interface", "show", "demo/srv/Measure", "--path", str(packages))
    code, out, err = service(capsys, remote, "describe", "measure")
    assert (code, err) == (ExitCode.OK, "")
    assert out == "/measure [demo/srv/Measure]\n" + local
    assert "\tdemo/Vec[2] ends\n\t\tfloat64 x\n" in out


def test_service_describe_unknown_exits_5(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = service(capsys, remote, "describe", "/measur")
    assert (code, out) == (ExitCode.SERVICE_NOT_FOUND, "")
    assert one_error_line(err) == (
        "ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/measur]: no service named /measur; "
        "did you mean /measure?"
    )


@pytest.mark.parametrize("wanted", ["demo/msg/Segment", "demo/Segment"])
def test_interface_show_url_prints_the_servers_definition(
    capsys: pytest.CaptureFixture[str], remote: Remote, packages: Path, wanted: str
) -> None:
    _, local, _ = run(capsys, "interface", "show", "demo/Segment", "--path", str(packages))
    code, out, err = run(capsys, "interface", "show", wanted, "--url", remote.url, "--all-comments")
    _, local_all, _ = run(
        capsys, "interface", "show", "demo/Segment", "--path", str(packages), "--all-comments"
    )
    assert (code, err) == (ExitCode.OK, "")
    assert out == local_all
    code, out, _ = run(capsys, "interface", "show", wanted, "--url", remote.url)
    assert (code, out) == (ExitCode.OK, local)


def test_interface_show_url_of_a_type_the_server_does_not_serve(
    capsys: pytest.CaptureFixture[str], remote: Remote
) -> None:
    code, out, err = run(capsys, "interface", "show", "demo/Segmnt", "--url", remote.url)
    assert (code, out) == (ExitCode.FAILURE, "")
    assert err.startswith(
        f"srvwire: error: the server {remote.url} describes no type 'demo/Segmnt' (of "
    )
    assert err.endswith(" types); did you mean demo/msg/Segment, demo/msg/Vec?\n")


def test_interface_show_prints_nothing_of_a_type_it_cannot_build(
    capsys: pytest.CaptureFixture[str], packages: Path
) -> None:
    path = write(packages, "demo/msg/Broken.msg", "# Fine so far.\nint32 a\ndemo/Missing m\n")
    code, out, err = run(capsys, "interface", "show", "demo/Broken", "--path", str(packages))
    assert (code, out) == (ExitCode.FAILURE, "")
    assert err == (
        f"srvwire: error: {path}:3:1: unknown type 'demo/Missing' of field 'm': no message "
        "'Missing' in package 'demo'\n"
    )


@pytest.mark.parametrize("srv_type", ["std_srvs/srv/Trigger", "std_srvs/Trigger"])
def test_service_find(capsys: pytest.CaptureFixture[str], remote: Remote, srv_type: str) -> None:
    code, out, _ = service(capsys, remote, "find", srv_type)
    assert code == ExitCode.OK
    assert out == "".join(f"{name}\n" for name, t in SERVICES if t == "std_srvs/srv/Trigger")


def test_service_find_nothing(capsys: pytest.CaptureFixture[str], remote: Remote) -> None:
    code, out, err = service(capsys, remote, "find", "std_srvs/srv/SetBool")
    assert (code, out, err) == (ExitCode.OK, "", "")


# --- srvwire gen ------------------------------------------------------------------------------


def import_file(path: Path) -> Any:
    spec = importlib.util.spec_from_file_location(f"generated_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_gen_one_module(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    target = tmp_path / "app" / "interfaces.py"
    code, out, err = run(
        capsys, "gen", "std_srvs", "example_interfaces/srv/AddTwoInts", "-o", str(target)
    )
    assert (code, out, err) == (ExitCode.OK, f"wrote {target} (4 interfaces)\n", "")
    module = import_file(target)
    assert module.AddTwoInts.type_name == "example_interfaces/srv/AddTwoInts"
    assert module.Trigger.Response().model_dump() == {"success": False, "message": ""}
    assert module.SetBool.Request(data=True).data is True


def test_gen_one_module_per_package(capsys: pytest.CaptureFixture[str], packages: Path) -> None:
    folder = packages.parent / "generated"
    code, out, _ = run(
        capsys, "gen", "demo", "std_srvs", "-o", str(folder), "--path", str(packages)
    )
    assert code == ExitCode.OK
    assert out == (
        f"wrote {folder / 'demo.py'} (4 interfaces)\n"
        f"wrote {folder / 'std_srvs.py'} (3 interfaces)\n"
    )
    demo = import_file(folder / "demo.py")
    assert demo.Measure.Request().segment.start.y == 1.5
    assert import_file(folder / "std_srvs.py").Empty.type_name == "std_srvs/srv/Empty"


def test_gen_into_a_folder_imports_nested_types_from_sibling_modules(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    interfaces = tmp_path / "interfaces"
    write(interfaces, "my_robot/msg/Battery.msg", "float32 voltage\n")
    status = "std_msgs/Header header\ngeometry_msgs/Pose pose\nBattery battery\n"
    write(interfaces, "my_robot/msg/RobotStatus.msg", status)
    write(interfaces, "my_robot/srv/GetStatus.srv", "---\nRobotStatus status\n")
    folder = tmp_path / "robot_types"
    code, out, err = run(capsys, "gen", "my_robot", "-o", str(folder), "--path", str(interfaces))
    assert (code, err) == (ExitCode.OK, "")
    # The nested packages are written too, with the messages needed.
    assert out == (
        f"wrote {folder / 'my_robot.py'} (3 interfaces)\n"
        f"wrote {folder / 'builtin_interfaces.py'} (1 interface)\n"
        f"wrote {folder / 'geometry_msgs.py'} (3 interfaces)\n"
        f"wrote {folder / 'std_msgs.py'} (1 interface)\n"
    )
    source = (folder / "my_robot.py").read_text(encoding="utf-8")
    assert "from . import geometry_msgs, std_msgs\n" in source
    assert "class Header" not in source and "    header: std_msgs.Header = " in source
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        my_robot = importlib.import_module("robot_types.my_robot")
        std_msgs = importlib.import_module("robot_types.std_msgs")
        geometry_msgs = importlib.import_module("robot_types.geometry_msgs")
        built = my_robot.RobotStatus(
            header=std_msgs.Header(frame_id="base"), pose=geometry_msgs.Pose()
        )
        assert built.header.frame_id == "base"
        assert my_robot.RobotStatus.model_fields["header"].annotation is std_msgs.Header
        assert my_robot.GetStatus.Response().status.battery.voltage == 0.0
    finally:
        for name in [name for name in sys.modules if name.startswith("robot_types")]:
            del sys.modules[name]
    assert_lint_clean(folder)


def assert_lint_clean(folder: Path) -> None:
    """Generated modules are lint-clean as written, and ruff format leaves them as they are;
    ruff runs inside ``folder``, isolated, so srvwire is a third-party package there, as in a
    user's project."""
    for arguments in (["check", "--select", "E,F,W,I,B,UP,RUF"], ["format", "--check"]):
        linted = subprocess.run(
            [sys.executable, "-m", "ruff", *arguments, "--isolated", "--line-length", "100", "."],
            cwd=folder,
            capture_output=True,
            text=True,
            check=False,
        )
        assert linted.returncode == 0, linted.stdout


IMPORT_ORDERS = {
    "my_robot first": "import robot_types.my_robot, robot_types.my_nav",
    "my_nav first": "import robot_types.my_nav, robot_types.my_robot",
    "my_robot only": "import robot_types.my_robot",
    "my_nav only": "import robot_types.my_nav",
}
USE_BOTH = """
import sys

from robot_types import my_nav, my_robot

plan = my_robot.Plan.Request.model_validate({"waypoints": [{"robot": {"name": "r2"}}]})
robot: my_robot.Status = plan.waypoints[0].robot
assert robot.name == "r2" and my_nav.Waypoint().robot.name == "r2d2"
assert my_nav.Waypoint.model_fields["robot"].annotation is my_robot.Status
assert my_robot.Plan.Request.model_fields["waypoints"].annotation.__args__[0] is my_nav.Waypoint
assert my_robot.Plan.Response().statuses == []
complete = [cls.__pydantic_complete__ for cls in (my_nav.Waypoint, my_robot.Plan.Request)]
assert complete == [True, True], complete
"""


def test_gen_into_a_folder_packages_that_nest_each_other_import_in_any_order(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # my_robot's Plan nests my_nav's Waypoint, which nests my_robot's Status: no message
    # contains itself, but each package's module needs a class of the other's.
    interfaces = tmp_path / "interfaces"
    write(interfaces, "my_robot/msg/Status.msg", 'string<=16 name "r2d2"\n')
    write(
        interfaces,
        "my_robot/srv/Plan.srv",
        "my_nav/Waypoint[<=10] waypoints\n---\nStatus[] statuses\n",
    )
    write(interfaces, "my_nav/msg/Waypoint.msg", "my_robot/Status robot\nfloat32 speed 1.5\n")
    folder = tmp_path / "robot_types"
    code, out, err = run(capsys, "gen", "my_robot", "-o", str(folder), "--path", str(interfaces))
    assert (code, err) == (ExitCode.OK, "")
    assert out == (
        f"wrote {folder / 'my_robot.py'} (2 interfaces)\n"
        f"wrote {folder / 'my_nav.py'} (1 interface)\n"
        f"wrote {folder / '_my_nav__my_robot.py'} (3 interfaces)\n"
    )
    for order, imports in IMPORT_ORDERS.items():
        ran = subprocess.run(
            [sys.executable, "-c", f"{imports}\n{USE_BOTH}"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            check=False,
        )
        assert (ran.returncode, ran.stderr) == (0, ""), order
    # Lint-clean as written, and mypy --strict sees each package's classes with their fields.
    assert_lint_clean(folder)
    (tmp_path / "use.py").write_text(
        "from robot_types import my_nav, my_robot\n\n"
        "status: my_robot.Status = my_robot.Status(name='x')\n"
        "request = my_robot.Plan.Request(waypoints=[my_nav.Waypoint(robot=status)])\n"
        "name: str = request.waypoints[0].robot.name\n"
        "wrong: int = my_nav.Waypoint().speed\n",
        encoding="utf-8",
    )
    checked = subprocess.run(
        [
            *(sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml")),
            *("--strict", "--cache-dir", str(tmp_path / ".mypy_cache"), "--no-error-summary"),
            *("--hide-error-context", "use.py"),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert (checked.stdout, checked.stderr) == (
        'use.py:6: error: Incompatible types in assignment (expression has type "float", '
        'variable has type "int")  [assignment]\n',
        "",
    )


USE_PREFIXED = """
from shapes import p, q

assert q.Uses.model_fields["arrays"].annotation is p.p_msg_Arrays
assert q.Uses.model_validate({"arrays": {"values": [1, 2]}}).arrays.values == [1, 2]
assert p.p_srv_Arrays.Request().arrays.values == []
"""


def test_gen_into_a_folder_refers_to_a_prefixed_class_by_its_name_in_its_module(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # p has a message and a service both named Arrays, so its module prefixes both classes;
    # q's module must name the message as p's module does.
    interfaces = tmp_path / "interfaces"
    write(interfaces, "p/msg/Arrays.msg", "int32[] values\n")
    write(interfaces, "p/srv/Arrays.srv", "Arrays arrays\n---\n")
    write(interfaces, "q/msg/Uses.msg", "p/Arrays arrays\n")
    folder = tmp_path / "shapes"
    code, out, err = run(capsys, "gen", "q", "p", "-o", str(folder), "--path", str(interfaces))
    assert (code, err) == (ExitCode.OK, "")
    assert out == (
        f"wrote {folder / 'q.py'} (1 interface)\nwrote {folder / 'p.py'} (2 interfaces)\n"
    )
    assert "    arrays: p.p_msg_Arrays = " in (folder / "q.py").read_text(encoding="utf-8")
    import_each_first(tmp_path, "shapes", ("q", "p"), USE_PREFIXED)


def test_gen_reports_a_cycle_across_files_at_its_field(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    interfaces = tmp_path / "interfaces"
    write(interfaces, "cyc_pkg/msg/Q1.msg", "cyc_pkg/Q2 x\n")
    closing = write(interfaces, "cyc_pkg/msg/Q2.msg", "# back\n  cyc_pkg/Q1 x\n")
    target = tmp_path / "out.py"
    code, out, err = run(capsys, "gen", "cyc_pkg", "-o", str(target), "--path", str(interfaces))
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == (
        f"{closing}:2:3: field 'x' makes a message contain itself "
        "(cyc_pkg/msg/Q1 -> cyc_pkg/msg/Q2 -> cyc_pkg/msg/Q1); "
        "a message cannot nest itself, directly or through other messages"
    )
    assert not target.exists()


def test_gen_unknown_package_exits_1(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    target = tmp_path / "out.py"
    code, out, err = run(capsys, "gen", "std_srv", "-o", str(target))
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err).startswith("no interface package 'std_srv' in ")
    assert not target.exists()


def test_gen_cannot_write_exits_1(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    code, _, err = run(capsys, "gen", "std_srvs", "-o", str(blocker / "out.py"))
    assert code == ExitCode.FAILURE
    assert one_error_line(err).startswith(f"cannot write {blocker / 'out.py'}: ")


# --- srvwire serve ----------------------------------------------------------------------------

APP = """\
from srvwire.loader import load_service
from srvwire.server import Server

AddTwoInts = load_service("example_interfaces/srv/AddTwoInts")
server = Server(grace_period=0)


@server.service("/add_two_ints", AddTwoInts)
def add(request):
    return AddTwoInts.Response(sum=request.a + request.b)
"""


@pytest.mark.parametrize("transport", [[], ["--transport", "picows"]], ids=["default", "picows"])
def test_serve_a_file_until_ctrl_c(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, transport: list[str]
) -> None:
    app = tmp_path / "cli_app.py"
    app.write_text(APP, encoding="utf-8")
    process = subprocess.Popen(
        [
            *(sys.executable, "-m", "srvwire", "serve", str(app)),
            *("--port", "0", "--log-level", "debug", *transport),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        first = process.stdout.readline()
        match = re.fullmatch(r"serving 1 service on (ws://127\.0\.0\.1:\d+)\n", first)
        assert match, first
        assert process.stdout.readline() == "  /add_two_ints [example_interfaces/srv/AddTwoInts]\n"
        assert process.stdout.readline() == (
            "only programs on this machine can connect (loopback); no authentication; unencrypted\n"
        )
        url = match.group(1)
        code, out, _ = run(capsys, "call", "/add_two_ints", "{a: 2, b: 3}", "--json", "--url", url)
        assert (code, out) == (ExitCode.OK, '{"sum": 5}\n')
        process.send_signal(signal.SIGINT)
        rest, err = process.communicate(timeout=scaled(10))
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 0, err
    assert rest == "shutting down\nstopped\n"
    assert "Traceback" not in err
    assert "DEBUG srvwire.server: connection from" in err
    assert "serving" not in err and "shutting down" not in err  # said once, on stdout


def test_serve_on_picows_without_it_names_the_extra(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    app = tmp_path / "cli_app_no_picows.py"
    app.write_text(APP, encoding="utf-8")
    monkeypatch.setitem(sys.modules, "picows", None)  # what importing it does when it is absent
    monkeypatch.delitem(sys.modules, "srvwire.transports.picows", raising=False)
    code, out, err = run(capsys, "serve", str(app), "--port", "0", "--transport", "picows")
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == (
        "the picows transport needs the picows package: pip install 'srvwire[fast]'"
    )


def test_serve_on_two_hosts_with_an_access_log(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    app = tmp_path / "cli_app.py"
    app.write_text(APP, encoding="utf-8")
    hosts = ["--host", "127.0.0.1", "--host", "localhost"]
    process = subprocess.Popen(
        [sys.executable, "-m", "srvwire", "serve", str(app), "--port", "0", *hosts, "--access-log"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None and process.stderr is not None
        first = process.stdout.readline()
        match = re.fullmatch(r"serving 1 service on (ws://127\.0\.0\.1:\d+)(, .+)?\n", first)
        assert match, first
        url = match.group(1)
        code, out, _ = run(capsys, "call", "/add_two_ints", "{a: 2, b: 3}", "--json", "--url", url)
        assert (code, out) == (ExitCode.OK, '{"sum": 5}\n')
        code, _, _ = run(capsys, "call", "/add_two", "{a: 2, b: 3}", "--url", url)
        assert code == ExitCode.SERVICE_NOT_FOUND
        lines = [process.stderr.readline() for _ in range(2)]
        process.send_signal(signal.SIGINT)
        process.communicate(timeout=scaled(10))
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 0
    assert re.fullmatch(
        r"\S+ \S+ INFO srvwire.access: 127\.0\.0\.1:\d+ /add_two_ints OK \d+\.\d\d ms\n",
        lines[0],
    ), lines
    assert re.fullmatch(
        r"\S+ \S+ INFO srvwire.access: 127\.0\.0\.1:\d+ /add_two SERVICE_NOT_FOUND -\n", lines[1]
    ), lines


@pytest.mark.parametrize(
    ("source", "target", "message"),
    [
        (None, "{tmp}/missing.py", "no such file: {tmp}/missing.py"),
        (
            "x = 1\n",
            "{tmp}/no_server.py",
            "{tmp}/no_server.py has no attribute 'server' or 'app'; "
            "name the Server object as {tmp}/no_server.py:NAME",
        ),
        (
            "handler = print\n",
            "{tmp}/not_server.py:handler",
            "{tmp}/not_server.py:handler is 'builtin_function_or_method', not a srvwire Server",
        ),
        (
            "def make():\n    return None\n",
            "{tmp}/a_factory.py:make",
            "{tmp}/a_factory.py:make is 'function', not a srvwire Server; if it returns the "
            "Server, add --factory",
        ),
        (
            "raise ValueError('boom')\n",
            "{tmp}/broken_app.py:server",
            "importing {tmp}/broken_app.py failed: ValueError: boom",
        ),
        (None, "srvwire_no_such_module:server", "no module named 'srvwire_no_such_module'"),
        (
            None,
            "srvwire.errors:ErrorCode",
            "srvwire.errors:ErrorCode is 'EnumType', not a srvwire Server",
        ),
    ],
)
def test_serve_bad_targets_exit_1(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    source: str | None,
    target: str,
    message: str,
) -> None:
    target = target.format(tmp=tmp_path)
    if source is not None:
        Path(target.partition(":")[0]).write_text(source, encoding="utf-8")
    code, out, err = run(capsys, "serve", target, "--port", "0")
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == message.format(tmp=tmp_path)


@pytest.mark.parametrize(
    ("source", "target", "flags"),
    [
        ("app = Server()\n", "busy_app.py", []),
        ("def make():\n    return Server()\n", "busy_factory.py:make", ["--factory"]),
    ],
)
def test_serve_port_in_use_exits_1(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    source: str,
    target: str,
    flags: list[str],
) -> None:
    app = tmp_path / target.partition(":")[0]
    app.write_text(f"from srvwire.server import Server\n{source}", encoding="utf-8")
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        code, out, err = run(capsys, "serve", str(tmp_path / target), "--port", str(port), *flags)
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err).startswith(f"cannot listen on 127.0.0.1:{port}: ")


@pytest.mark.parametrize(
    ("source", "target", "message"),
    [
        (
            "server = 5\n",
            "{tmp}/not_callable.py:server",
            "{tmp}/not_callable.py:server is not callable, so it is not a factory",
        ),
        (
            "def make():\n    return 5\n",
            "{tmp}/factory_int.py:make",
            "{tmp}/factory_int.py:make() returned 'int', not a srvwire Server",
        ),
        (
            "def make():\n    raise OSError('no config')\n",
            "{tmp}/factory_fails.py:make",
            "{tmp}/factory_fails.py:make() failed: OSError: no config",
        ),
    ],
)
def test_serve_bad_factories_exit_1(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, source: str, target: str, message: str
) -> None:
    target = target.format(tmp=tmp_path)
    Path(target.partition(":")[0]).write_text(source, encoding="utf-8")
    code, out, err = run(capsys, "serve", target, "--factory", "--port", "0")
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == message.format(tmp=tmp_path)


# --- failures no command expects --------------------------------------------------------------


@pytest.mark.parametrize(
    ("error", "message"),
    [
        (PermissionError(13, "Permission denied", "/x"), "[Errno 13] Permission denied: '/x'"),
        (RuntimeError("boom"), "unexpected RuntimeError: boom"),
    ],
)
def test_unexpected_errors_are_one_line(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    error: Exception,
    message: str,
) -> None:
    def fail(args: Any) -> int:
        raise error

    monkeypatch.setattr(cli_interface, "_cmd_interface_packages", fail)
    code, out, err = run(capsys, "interface", "packages")
    assert (code, out) == (ExitCode.FAILURE, "")
    assert one_error_line(err) == message


def test_interface_check_finds_the_package_however_the_path_is_written(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # From inside the kind folder, or through '..': the package is where the file really is.
    broken = write(tmp_path, "pkg/msg/N.msg", "Missing2 m\n")
    expected = "unknown type 'pkg/Missing2' of field 'm': no message 'Missing2' in package 'pkg'"
    monkeypatch.chdir(broken.parent)
    for written in ("N.msg", "../msg/N.msg"):
        code, out, _ = run(capsys, "interface", "check", written)
        assert code == ExitCode.FAILURE, written
        assert out.splitlines() == [f"{written}:1:1: {expected}", "checked 1 file, 1 error"]


def test_call_values_from_a_closed_stdin_is_a_usage_error(
    capsys: pytest.CaptureFixture[str], remote: Remote, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("sys.stdin", None)
    code, out, err = call(capsys, remote, "/add_two_ints", "-")
    assert (code, out) == (ExitCode.USAGE, "")
    assert (
        err == "srvwire: error: cannot read VALUES from standard input: standard input is closed\n"
    )


def test_a_lost_connection_is_one_error_line() -> None:
    """The client logs the lost connection; the command says it once, in its own line."""
    server = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "servers" / "hanging_server.py")],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert server.stdout is not None
    try:
        url = f"ws://127.0.0.1:{server.stdout.readline().strip()}"
        command = subprocess.Popen(
            [sys.executable, "-m", "srvwire", "call", "/hang", "--url", url, "--timeout", "60"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert server.stdout.readline() == "started 1\n"
            server.kill()
            _, err = command.communicate(timeout=scaled(60))
        finally:
            command.kill()
            command.communicate()
    finally:
        server.kill()
        server.communicate()
    assert command.returncode == ExitCode.UNAVAILABLE
    assert one_error_line(err).startswith(
        "ConnectionLost: UNAVAILABLE (-32003) [/hang]: the connection dropped (no close frame)"
    )


SIZES_APP = """\
from srvwire.models import build_service
from srvwire.parser import parse_service
from srvwire.server import Server

SIZED = "string data\\n---\\nint64 size\\nstring data\\n"
Sized = build_service(parse_service(SIZED, "sizes", "Sized"))
server = Server(grace_period=0)


@server.service("/measure", Sized)
def measure(request):
    return {"size": len(request.data)}


@server.service("/big", Sized)
def big(request):
    return {"size": 2_000_000, "data": "x" * 2_000_000}
"""


@contextlib.contextmanager
def serving(app: Path, *argv: str) -> Iterator[str]:
    """``srvwire serve app`` in a process of its own, with ``argv``; its URL."""
    process = subprocess.Popen(
        [sys.executable, "-m", "srvwire", "serve", str(app), "--port", "0", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        first = process.stdout.readline()
        match = re.fullmatch(r"serving \d+ services? on (ws://127\.0\.0\.1:\d+)\n", first)
        assert match, first
        yield match.group(1)
    finally:
        process.kill()
        process.communicate()


def test_max_message_size_lets_a_command_take_a_larger_reply(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    app = tmp_path / "sizes_app.py"
    app.write_text(SIZES_APP, encoding="utf-8")
    with serving(app) as url:
        code, out, err = run(capsys, "call", "/big", "--json", "--url", url)
        assert (code, out) == (ExitCode.UNAVAILABLE, "")
        assert "over the client's max_message_size" in err
        assert one_error_line(err).endswith(
            "; raise this command's limit with --max-message-size BYTES"
        )
        limit = ["--max-message-size", "4000000"]
        code, out, err = run(capsys, "call", "/big", "--json", "--url", url, *limit)
        assert (code, err) == (ExitCode.OK, "")
        assert json.loads(out)["size"] == 2_000_000


def test_max_message_size_on_both_sides_lets_a_larger_request_through(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    app = tmp_path / "sizes_app.py"
    app.write_text(SIZES_APP, encoding="utf-8")
    request = tmp_path / "request.yaml"
    request.write_text("{data: " + "x" * 2_000_000 + "}", encoding="utf-8")
    limit = ["--max-message-size", "4000000"]
    with serving(app) as url:
        # Over this command's limit: not sent.
        code, _, err = run(capsys, "call", "/measure", f"@{request}", "--url", url)
        assert code == ExitCode.OTHER_RPC_ERROR
        assert one_error_line(err).startswith("ResourceExhausted: ")
        assert one_error_line(err).endswith(
            "; raise this command's limit with --max-message-size BYTES (a request that size "
            "needs the server's limit raised too)"
        )
        # Sent, and over the server's.
        code, _, err = run(capsys, "call", "/measure", f"@{request}", "--url", url, *limit)
        assert code == ExitCode.UNAVAILABLE
        assert "over the server's max_message_size" in err
        assert one_error_line(err).endswith(
            "; the message was over the server's limit: raise it there (srvwire serve "
            "--max-message-size BYTES, or Server(max_message_size=...))"
        )
    with serving(app, *limit) as url:
        code, out, err = run(
            capsys, "call", "/measure", f"@{request}", "--json", "--url", url, *limit
        )
        assert (code, err) == (ExitCode.OK, "")
        assert json.loads(out) == {"size": 2_000_000, "data": ""}


@pytest.mark.parametrize(
    "command",
    [
        ["call", "/x"],
        ["service", "list"],
        ["service", "type", "/x"],
        ["service", "describe", "/x"],
        ["service", "find", "a/B"],
        ["topic", "list"],
        ["topic", "info", "/x"],
        ["topic", "echo", "/x"],
        ["topic", "pub", "/x"],
        ["topic", "hz", "/x"],
        ["action", "list"],
        ["action", "info", "/x"],
        ["action", "send_goal", "/x"],
        ["serve", "app.py"],
    ],
)
def test_every_command_that_connects_or_serves_takes_max_message_size(
    command: list[str],
) -> None:
    args = cli.build_parser().parse_args([*command, "--max-message-size", "3000000"])
    assert args.max_message_size == 3_000_000
