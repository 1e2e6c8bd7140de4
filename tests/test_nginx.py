"""srvwire behind nginx with TLS, end to end: the configuration docs/security.md shows
(examples/nginx/srvwire.conf), run by a real nginx in front of a real server.

nginx is a system package: ``.ci/run`` installs it when it is missing (as root, with apt-get).
Without it this test fails, saying how to install it.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import socket
import ssl
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import trustme
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import InvalidStatus

from srvwire import Identity, connect, serve
from srvwire.auth import bearer_subprotocol
from support import ROOT, scaled
from test_security import EVIL_ORIGIN, READER_TOKEN, TOKEN, TOKENS, Robot, http

CONFIG = ROOT / "examples" / "nginx" / "srvwire.conf"


def nginx_binary() -> str:
    found = shutil.which("nginx") or next(
        (path for path in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if os.access(path, os.X_OK)),
        None,
    )
    if found is None:
        pytest.fail(
            "nginx is not installed, and this test runs srvwire behind a real nginx: install "
            "it with 'apt-get update && apt-get install -y nginx' (.ci/run does this when it "
            "runs as root)",
            pytrace=False,
        )
    return found


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def replace_once(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"examples/nginx/srvwire.conf should hold {old!r} once"
    return text.replace(old, new)


@pytest.fixture
async def nginx_in_front(tmp_path: Path) -> AsyncIterator[dict[str, Any]]:
    """A srvwire server on loopback and nginx in front of it on a free port, over TLS."""
    binary = nginx_binary()
    ca = trustme.CA()
    cert = ca.issue_cert("robot.example.com", "localhost")
    certfile, keyfile = tmp_path / "fullchain.pem", tmp_path / "privkey.pem"
    cert.private_key_pem.write_to_path(str(keyfile))
    for blob in cert.cert_chain_pems:
        blob.write_to_path(str(certfile), append=True)
    cafile = tmp_path / "ca.pem"
    ca.cert_pem.write_to_path(str(cafile))

    robot = Robot(auth=TOKENS, origins=["https://robot.example.com"])
    async with serve(robot.server, "127.0.0.1", 0) as running:
        port = free_port()
        site = CONFIG.read_text(encoding="utf-8")
        site = replace_once(site, "listen 443 ssl;", f"listen 127.0.0.1:{port} ssl;")
        site = replace_once(site, "/etc/ssl/robot.example.com/fullchain.pem", str(certfile))
        site = replace_once(site, "/etc/ssl/robot.example.com/privkey.pem", str(keyfile))
        site = replace_once(site, "127.0.0.1:8765", f"127.0.0.1:{running.port}")
        (tmp_path / "srvwire.conf").write_text(site, encoding="utf-8")
        temp = {name: tmp_path / name for name in ("body", "proxy", "fastcgi", "uwsgi", "scgi")}
        for folder in temp.values():
            folder.mkdir()
        (tmp_path / "nginx.conf").write_text(
            "daemon off;\n"
            "worker_processes 1;\n"
            f"pid {tmp_path / 'nginx.pid'};\n"
            "error_log stderr notice;\n"
            "events { worker_connections 64; }\n"
            "http {\n"
            "    access_log off;\n"
            f"    client_body_temp_path {temp['body']};\n"
            f"    proxy_temp_path {temp['proxy']};\n"
            f"    fastcgi_temp_path {temp['fastcgi']};\n"
            f"    uwsgi_temp_path {temp['uwsgi']};\n"
            f"    scgi_temp_path {temp['scgi']};\n"
            f"    include {tmp_path / 'srvwire.conf'};\n"
            "}\n",
            encoding="utf-8",
        )
        process = await asyncio.create_subprocess_exec(
            binary,
            "-p",
            str(tmp_path),
            "-c",
            str(tmp_path / "nginx.conf"),
            "-e",
            "stderr",
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        assert process.stderr is not None
        said: list[str] = []
        try:
            # nginx opens its listening socket, then starts its worker and says so.
            async with asyncio.timeout(scaled(10)):
                while not any("start worker process" in line for line in said):
                    line = (await process.stderr.readline()).decode()
                    assert line, "nginx stopped: " + "".join(said)
                    said.append(line)
            yield {
                "robot": robot,
                "port": port,
                "cafile": cafile,
                "context": ssl.create_default_context(cafile=str(cafile)),
            }
        finally:
            process.send_signal(signal.SIGQUIT)  # graceful: finish the open connections
            try:
                async with asyncio.timeout(scaled(10)):
                    await process.communicate()
            except TimeoutError:
                process.kill()
                await process.wait()


async def test_a_client_calls_through_nginx_with_tls_and_a_token(
    nginx_in_front: dict[str, Any],
) -> None:
    port, robot = nginx_in_front["port"], nginx_in_front["robot"]
    url = f"wss://localhost:{port}"
    async with connect(url, ssl=nginx_in_front["cafile"], token=TOKEN, timeout=scaled(5)) as c:
        assert sorted(c.services) == ["/add", "/arm"]
        assert (await c.call("/arm", {"minuend": 7, "subtrahend": 2})).difference == 5
    async with connect(url, ssl=nginx_in_front["cafile"], token=READER_TOKEN) as c:
        assert list(c.services) == ["/add"]
    assert robot.calls == [("/arm", Identity("operator", {"robot:write"}))]


async def test_a_browser_page_of_the_proxied_name_is_served_and_others_refused(
    nginx_in_front: dict[str, Any],
) -> None:
    port, context = nginx_in_front["port"], nginx_in_front["context"]
    # As a browser at https://robot.example.com sends it; the name resolves to this machine.
    address: dict[str, Any] = {"host": "127.0.0.1", "port": port, "ssl": context}
    async with ws_connect(
        f"wss://robot.example.com:{port}",
        origin="https://robot.example.com",  # type: ignore[arg-type]
        subprotocols=["srvwire.v1", bearer_subprotocol(TOKEN)],  # type: ignore[list-item]
        **address,
    ) as ws:
        assert ws.subprotocol == "srvwire.v1"
        await ws.recv()
        await ws.send('{"jsonrpc":"2.0","id":1,"method":"/arm","params":[4,1]}')
        assert json.loads(await ws.recv())["result"] == {"difference": 3}
    with pytest.raises(InvalidStatus) as refused:
        async with ws_connect(
            f"wss://robot.example.com:{port}",
            origin="https://evil.example",  # type: ignore[arg-type]
            additional_headers={"Authorization": f"Bearer {TOKEN}"},
            **address,
        ):
            pass
    assert refused.value.response.status_code == 403
    assert refused.value.response.body.decode() == EVIL_ORIGIN
    assert nginx_in_front["robot"].calls == [("/arm", Identity("operator", {"robot:write"}))]


async def test_healthz_through_nginx(nginx_in_front: dict[str, Any]) -> None:
    status, _, body = await http(
        nginx_in_front["port"], "/healthz", upgrade=False, context=nginx_in_front["context"]
    )
    assert (status, body) == (200, "ok\n")


def test_without_nginx_the_test_fails_saying_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    with pytest.raises(pytest.fail.Exception) as failed:
        nginx_binary()
    assert str(failed.value) == (
        "nginx is not installed, and this test runs srvwire behind a real nginx: install "
        "it with 'apt-get update && apt-get install -y nginx' (.ci/run does this when it "
        "runs as root)"
    )
