"""What a type checker sees of a call: mypy, run on a small user file, reveals the types.

The user file, for the async client and the blocking one, imports classes written by
``srvwire gen`` (the typed path) and one loaded with
``load_service`` (known to mypy only as ``type[Service]``), as a user's project would.
"""

from __future__ import annotations

import sys
from pathlib import Path

import mypy.api

from srvwire.cli import main
from support import DATA, ROOT

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
