"""What a type checker sees of a call: mypy, run on a small user file, reveals the types.

The user file, for the async client and the blocking one, imports classes written by
``srvwire gen`` (the typed path) and one loaded with
``load_service`` (known to mypy only as ``type[Service]``), as a user's project would.

At run time, over a real connection, a call with a generated ``Request`` returns that
module's ``Response``, as ``srv_type=`` its service would, for the async and the blocking
client; a ``Request`` of another type is refused naming both, and one that differs from the
server's definition is a conflict.
"""

from __future__ import annotations

import asyncio
import importlib.util
import sys
from pathlib import Path
from typing import Any

import mypy.api
import pytest

import srvwire
import srvwire.sync
from srvwire.cli import main
from srvwire.errors import InterfaceConflictError
from srvwire.loader import InterfaceLoader, bundled_interfaces, load_service
from srvwire.models import build_service
from srvwire.parser import parse_service
from srvwire.server import Server, serve
from support import DATA, ROOT, scaled

USER_CODE = """\
import srvwire
import srvwire.sync
from wire_types import Capture, Scan


async def use(client: srvwire.Client) -> None:
    reveal_type(await client.call("/scan", Scan.Request(fill=1.0)))
    reveal_type(await client.call("/scan", {"fill": 1.0}, srv_type=Scan))
    reveal_type(await client.call("/scan", Scan.Request(), timeout=2.0, wait_for_ready=True))
    reveal_type(client.proxy("/capture", Capture))
    reveal_type(await client.proxy("/capture", Capture, timeout=5.0)(width=2, height=1))
    reveal_type(await client.call("/scan", {"fill": 1.0}))
    reveal_type(await client.proxy("/scan")())
    loaded = srvwire.load_service("wire_msgs/srv/Scan")
    reveal_type(await client.call("/scan", loaded.Request(), srv_type=loaded))
    mean: str = (await client.call("/scan", Scan.Request())).mean
    frame: bytes = (await client.proxy("/capture", Capture)()).frame.data


def use_blocking(client: srvwire.sync.Client) -> None:
    reveal_type(client.call("/scan", Scan.Request(fill=1.0)))
    reveal_type(client.call("/scan", {"fill": 1.0}, srv_type=Scan))
    reveal_type(client.proxy("/capture", Capture))
    reveal_type(client.proxy("/capture", Capture, timeout=5.0)(width=2, height=1))
    reveal_type(client.call("/scan", {"fill": 1.0}))
    reveal_type(client.proxy("/scan")())
    mean: str = client.call("/scan", Scan.Request()).mean
"""


def test_mypy_sees_the_response_type_of_typed_calls(tmp_path: Path) -> None:
    generated = tmp_path / "wire_types.py"
    assert main(["gen", "wire_msgs", "--path", str(DATA / "wire_pkgs"), "-o", str(generated)]) == 0
    (tmp_path / "user.py").write_text(USER_CODE, encoding="utf-8")
    stdout, stderr, status = mypy.api.run(
        [
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--strict",
            "--python-executable",
            sys.executable,
            "--cache-dir",
            str(tmp_path / ".mypy_cache"),
            "--no-error-summary",
            "--hide-error-context",
            str(tmp_path / "wire_types.py"),
            str(tmp_path / "user.py"),
        ]
    )
    assert stderr == ""
    assert [line.split("user.py:", 1)[1] for line in stdout.splitlines()] == [
        '7: note: Revealed type is "wire_types.Scan_Response"',
        '8: note: Revealed type is "wire_types.Scan_Response"',
        '9: note: Revealed type is "wire_types.Scan_Response"',
        '10: note: Revealed type is "srvwire.client.ServiceProxy[wire_types.Capture_Response]"',
        '11: note: Revealed type is "wire_types.Capture_Response"',
        '12: note: Revealed type is "Any"',
        '13: note: Revealed type is "Any"',
        '15: note: Revealed type is "Any"',
        '16: error: Incompatible types in assignment (expression has type "float", variable has '
        'type "str")  [assignment]',
        '21: note: Revealed type is "wire_types.Scan_Response"',
        '22: note: Revealed type is "wire_types.Scan_Response"',
        '23: note: Revealed type is "srvwire.sync.ServiceProxy[wire_types.Capture_Response]"',
        '24: note: Revealed type is "wire_types.Capture_Response"',
        '25: note: Revealed type is "Any"',
        '26: note: Revealed type is "Any"',
        '27: error: Incompatible types in assignment (expression has type "float", variable has '
        'type "str")  [assignment]',
    ]
    assert status == 1


# --- what a call with a generated Request does at run time ------------------------------------

ADD_TWO_INTS = "example_interfaces/srv/AddTwoInts"
AddTwoInts = load_service(ADD_TWO_INTS)
Scan = InterfaceLoader([DATA / "wire_pkgs", bundled_interfaces()]).load_service(
    "wire_msgs/srv/Scan"
)


def generated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, *argv: str) -> Any:
    """Write the module ``name`` with ``srvwire gen *argv`` and import it, as a user would."""
    path = tmp_path / f"{name}.py"
    assert main(["gen", *argv, "-o", str(path)]) == 0
    module_spec = importlib.util.spec_from_file_location(name, path)
    assert module_spec is not None and module_spec.loader is not None
    module = importlib.util.module_from_spec(module_spec)
    monkeypatch.setitem(sys.modules, name, module)
    module_spec.loader.exec_module(module)
    return module


def add_server() -> Server:
    """``/add`` (the bundled AddTwoInts) and ``/scan`` (``wire_msgs/srv/Scan``, a user's own)."""
    server = Server()
    server.add_service("/add", AddTwoInts, lambda request: {"sum": request.a + request.b})
    server.add_service("/scan", Scan, lambda request: {"mean": request.fill})
    return server


@pytest.fixture
def gen_add(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Any:
    return generated(tmp_path, monkeypatch, "gen_add", ADD_TWO_INTS)


@pytest.fixture
def wire_types(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Any:
    return generated(
        tmp_path, monkeypatch, "wire_types", "wire_msgs", "--path", str(DATA / "wire_pkgs")
    )


async def test_a_generated_request_types_the_call_as_its_service_would(
    gen_add: Any, wire_types: Any
) -> None:
    async with (
        serve(add_server(), "127.0.0.1", 0) as running,
        srvwire.connect(running.url, timeout=scaled(5)) as client,
    ):
        for _ in range(2):  # the first call finds the type, the second one has it at hand
            added = await client.call("/add", gen_add.AddTwoInts.Request(a=1, b=2))
            assert type(added) is gen_add.AddTwoInts.Response and added.sum == 3
            scanned = await client.call("/scan", wire_types.Scan.Request(fill=0.5))
            assert type(scanned) is wire_types.Scan.Response and scanned.mean == 0.5
        # The process's own class (the loader's) and a mapping: its Response, as before.
        added = await client.call("/add", AddTwoInts.Request(a=2, b=2))
        assert type(added) is AddTwoInts.Response and added.sum == 4
        added = await client.call("/add", {"a": 3, "b": 2})
        assert type(added) is AddTwoInts.Response and added.sum == 5
        assert {key for key in client._link.ready if isinstance(key, tuple)} == {  # type: ignore[union-attr]
            ("/add", gen_add.AddTwoInts),
            ("/scan", wire_types.Scan),
        }


async def test_a_blocking_call_with_a_generated_request_is_typed_too(gen_add: Any) -> None:
    def blocking(url: str) -> Any:
        with srvwire.sync.connect(url, timeout=scaled(5)) as client:
            return client.call("/add", gen_add.AddTwoInts.Request(a=4, b=5))

    async with serve(add_server(), "127.0.0.1", 0) as running:
        added = await asyncio.to_thread(blocking, running.url)
    assert type(added) is gen_add.AddTwoInts.Response and added.sum == 9


async def test_a_request_of_another_class_of_the_same_type_types_the_call() -> None:
    # A class built apart from the process's (build_service is not interned), as a test might.
    Copy = build_service(parse_service(AddTwoInts.text, "example_interfaces", "AddTwoInts"))
    assert Copy is not AddTwoInts
    async with (
        serve(add_server(), "127.0.0.1", 0) as running,
        srvwire.connect(running.url, timeout=scaled(5)) as client,
    ):
        added = await client.call("/add", Copy.Request(a=1, b=1))
    assert type(added) is Copy.Response and added.sum == 2


async def test_a_request_of_another_service_type_is_refused_naming_both(
    gen_add: Any, wire_types: Any
) -> None:
    async with (
        serve(add_server(), "127.0.0.1", 0) as running,
        srvwire.connect(running.url, timeout=scaled(5)) as client,
    ):
        with pytest.raises(TypeError) as generated_scan:
            await client.call("/add", wire_types.Scan.Request(fill=1.0))
        with pytest.raises(TypeError) as loaded_add:
            await client.call("/scan", AddTwoInts.Request())
        with pytest.raises(TypeError) as a_response:
            await client.call("/add", gen_add.AddTwoInts.Response(sum=1))
        assert (await client.call("/add", {"a": 1, "b": 1})).sum == 2  # nothing else changed
    assert str(generated_scan.value) == (
        "/add takes example_interfaces/srv/AddTwoInts requests, "
        "not wire_msgs/srv/Scan requests (wire_types.Scan_Request)"
    )
    assert str(loaded_add.value) == (
        "/scan takes wire_msgs/srv/Scan requests, "
        "not example_interfaces/srv/AddTwoInts requests (example_interfaces.srv.AddTwoInts_Request)"
    )
    assert str(a_response.value) == (
        "/add takes example_interfaces/srv/AddTwoInts requests, "
        "not example_interfaces/srv/AddTwoInts_Response (gen_add.AddTwoInts_Response)"
    )


async def test_a_generated_request_that_differs_from_the_servers_type_is_a_conflict(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The client's copy of example_interfaces/srv/AddTwoInts has one more field.
    # (Generated classes carry no file name: the error says "the local class", never the
    # process's own AddTwoInts file, which is the server's.)
    srv = tmp_path / "copy" / "example_interfaces" / "srv" / "AddTwoInts.srv"
    srv.parent.mkdir(parents=True)
    srv.write_text("int64 a\nint64 b\nint64 c\n---\nint64 sum\n", encoding="utf-8")
    other = generated(
        tmp_path, monkeypatch, "other_add", ADD_TWO_INTS, "--path", str(tmp_path / "copy")
    )
    async with (
        serve(add_server(), "127.0.0.1", 0) as running,
        srvwire.connect(running.url, timeout=scaled(5)) as client,
    ):
        assert (await client.call("/add", {"a": 1, "b": 1})).sum == 2  # compared: the same
        for _ in range(2):  # compared on its own, and never cached as if it were the same
            with pytest.raises(InterfaceConflictError) as caught:
                await client.call("/add", other.AddTwoInts.Request(a=1, b=1, c=1))
            assert str(caught.value) == (
                f"two different definitions of {ADD_TWO_INTS}: the local class and server "
                f"{running.url} (declaration 3: 'int64 c' against '---'); a type name has one "
                "definition per process"
            )
        with pytest.raises(InterfaceConflictError):  # as srv_type= does
            await client.call("/add", {"a": 1}, srv_type=other.AddTwoInts)
