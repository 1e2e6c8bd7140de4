"""The command line at the edge: serve's safe defaults and TLS; call's token, headers and CAs."""

from __future__ import annotations

import re
import signal
import ssl
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import trustme
from cryptography.hazmat.primitives import serialization

from conftest import Subtract, subtract
from srvwire import Identity, Server, TokenAuth, connect
from srvwire.cli import ExitCode
from support import scaled
from test_cli import one_error_line, run, start_in_thread

APP = """\
from srvwire.loader import load_service
from srvwire.server import Server

AddTwoInts = load_service("example_interfaces/srv/AddTwoInts")
server = Server(grace_period=0)


@server.service("/add_two_ints", AddTwoInts)
def add(request):
    return AddTwoInts.Response(sum=request.a + request.b)
"""


@pytest.fixture
def app(tmp_path: Path) -> Path:
    path = tmp_path / "edge_app.py"
    path.write_text(APP, encoding="utf-8")
    return path


def test_serve_refuses_a_public_address_without_authentication(
    capsys: pytest.CaptureFixture[str], app: Path
) -> None:
    code, out, err = run(capsys, "serve", str(app), "--host", "0.0.0.0", "--port", "0")
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == (
        "refusing to listen on 0.0.0.0 without authentication: any host that can reach it "
        "could call every service. Give the Server an authenticator "
        "(Server(auth=srvwire.TokenAuth(...))), require client certificates (--client-ca), "
        "or pass --allow-unauthenticated on a network you trust"
    )


def test_serve_refuses_a_bad_origin(capsys: pytest.CaptureFixture[str], app: Path) -> None:
    code, _, err = run(capsys, "serve", str(app), "--port", "0", "--origin", "app.example")
    assert code == ExitCode.USAGE
    assert one_error_line(err) == (
        "bad --origin: not an origin: 'app.example'; write scheme://host[:port], such as "
        "https://app.example.com, or 'null', or '*'"
    )


class Served:
    """``srvwire serve`` in a subprocess: its URL, and the lines it printed after it."""

    def __init__(self, *argv: str) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "srvwire", "serve", *argv, "--port", "0"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self.process.stdout is not None
        first = self.process.stdout.readline()
        match = re.fullmatch(r"serving 1 service on (wss?://[^ ,]+)(?:, wss?://[^ ,]+)*\n", first)
        assert match, first + self.process.stderr.read()  # type: ignore[union-attr]
        self.url = match.group(1)
        self.lines = [self.process.stdout.readline(), self.process.stdout.readline()]

    def stop(self) -> str:
        self.process.send_signal(signal.SIGINT)
        rest, err = self.process.communicate(timeout=scaled(10))
        assert self.process.returncode == 0, err
        return rest


@pytest.fixture
def tls_files(tmp_path: Path) -> Iterator[tuple[Path, Path, Path]]:
    ca = trustme.CA()
    cert = ca.issue_cert("localhost", "127.0.0.1")
    cafile, certfile, keyfile = tmp_path / "ca.pem", tmp_path / "cert.pem", tmp_path / "key.pem"
    ca.cert_pem.write_to_path(str(cafile))
    cert.private_key_pem.write_to_path(str(keyfile))
    for blob in cert.cert_chain_pems:
        blob.write_to_path(str(certfile), append=True)
    yield cafile, certfile, keyfile


def test_serve_on_every_address_when_allowed_says_who_can_reach_it(app: Path) -> None:
    served = Served(str(app), "--host", "0.0.0.0", "--allow-unauthenticated")
    try:
        assert served.lines == [
            "  /add_two_ints [example_interfaces/srv/AddTwoInts]\n",
            "any host that can route to 0.0.0.0 can connect; no authentication; unencrypted\n",
        ]
    finally:
        assert served.stop() == "shutting down\nstopped\n"


def test_serve_tls_and_call_it_with_the_ca(
    capsys: pytest.CaptureFixture[str], app: Path, tls_files: tuple[Path, Path, Path]
) -> None:
    cafile, certfile, keyfile = tls_files
    served = Served(
        str(app), "--host", "localhost", "--certfile", str(certfile), "--keyfile", str(keyfile)
    )
    try:
        assert served.url.startswith("wss://localhost:")
        assert served.lines[1] == (
            "only programs on this machine can connect (loopback); no authentication; over TLS\n"
        )
        request = ("call", "/add_two_ints", "{a: 2, b: 3}", "--json", "--url", served.url)
        code, out, _ = run(capsys, *request, "--cacert", str(cafile))
        assert (code, out) == (ExitCode.OK, '{"sum": 5}\n')
        code, out, _ = run(capsys, *request, "--insecure")
        assert (code, out) == (ExitCode.OK, '{"sum": 5}\n')
        code, _, err = run(capsys, *request)
        assert code == ExitCode.UNAVAILABLE
        assert one_error_line(err).startswith(
            f"ServiceUnavailable: UNAVAILABLE (-32003): cannot connect to {served.url}: "
            "the server's TLS certificate is not trusted: "
        )
    finally:
        served.stop()


def test_call_wss_against_a_plain_server_says_it_may_not_speak_tls(
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = Server()
    server.add_service("/subtract", Subtract, subtract)
    url, stop = start_in_thread(server)
    try:
        tls_url = url.replace("ws:", "wss:")
        code, _, err = run(capsys, "call", "/subtract", "--url", tls_url)
    finally:
        stop()
    assert code == ExitCode.UNAVAILABLE
    assert one_error_line(err).startswith(
        f"ServiceUnavailable: UNAVAILABLE (-32003): cannot connect to {tls_url}: the TLS "
        "handshake failed; the server may not speak TLS (try ws://): "
    )


def test_call_with_a_token_a_header_or_the_environment(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    server = Server(auth=TokenAuth({"tok": Identity("cli", {"math"})}))
    server.add_service("/subtract", Subtract, subtract, scopes={"math"})
    url, stop = start_in_thread(server)
    request = ("call", "/subtract", "{minuend: 3, subtrahend: 1}", "--json", "--url", url)
    try:
        code, out, _ = run(capsys, *request, "--token", "tok")
        assert (code, out) == (ExitCode.OK, '{"difference": 2}\n')
        code, out, _ = run(capsys, *request, "-H", "Authorization: Bearer tok")
        assert (code, out) == (ExitCode.OK, '{"difference": 2}\n')
        monkeypatch.setenv("SRVWIRE_TOKEN", "tok")
        code, out, _ = run(capsys, *request)
        assert (code, out) == (ExitCode.OK, '{"difference": 2}\n')
        monkeypatch.setenv("SRVWIRE_TOKEN", "wrong")
        code, _, err = run(capsys, *request)
        assert code == ExitCode.UNAVAILABLE
        assert one_error_line(err) == (
            f"ServiceUnavailable: UNAVAILABLE (-32003): cannot connect to {url}: the server "
            f"refused the connection: HTTP 401: the token is not valid (data: "
            f'{{"url": "{url}"}})'
        )
    finally:
        stop()


def test_call_keeps_a_token_off_plain_ws_to_another_host(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, _, err = run(capsys, "call", "/x", "--url", "ws://robot.example:8765", "--token", "tok")
    assert code == ExitCode.USAGE
    assert one_error_line(err) == (
        "refusing to send credentials over plain ws:// to robot.example, where anyone on the "
        "way can read them: use wss://"
    )
    code, _, err = run(capsys, "call", "/x", "-H", "no colon")
    assert code == ExitCode.USAGE
    assert "not a header: 'no colon'; write 'Name: value'" in one_error_line(err)


async def test_serve_with_client_certificates_may_listen_publicly(
    app: Path, tls_files: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    cafile, certfile, keyfile = tls_files
    clients = trustme.CA()
    client_ca = tmp_path / "clients.pem"
    clients.cert_pem.write_to_path(str(client_ca))
    served = Served(
        str(app),
        "--host",
        "0.0.0.0",
        "--certfile",
        str(certfile),
        "--keyfile",
        str(keyfile),
        "--client-ca",
        str(client_ca),
    )
    try:
        assert served.lines[1] == (
            "any host that can route to 0.0.0.0 can connect; callers must authenticate; over TLS\n"
        )
        port = served.url.rsplit(":", 1)[1]
        context = ssl.create_default_context(cafile=str(cafile))
        clients.issue_cert("bench", common_name="bench").configure_cert(context)
        async with connect(f"wss://localhost:{port}", ssl=context) as client:
            response = await client.call("/add_two_ints", {"a": 1, "b": 2})
            assert response.sum == 3
    finally:
        served.stop()


def test_serve_tls_options_that_do_not_fit(
    capsys: pytest.CaptureFixture[str], app: Path, tmp_path: Path
) -> None:
    code, _, err = run(capsys, "serve", str(app), "--port", "0", "--keyfile", "k.pem")
    assert code == ExitCode.USAGE
    assert one_error_line(err) == (
        "--keyfile and --client-ca need --certfile (the server's certificate)"
    )
    missing = tmp_path / "missing.pem"
    code, _, err = run(capsys, "call", "/x", "--url", "wss://localhost:1", "--cacert", str(missing))
    assert code == ExitCode.USAGE
    assert one_error_line(err) == (
        f"cannot use --cacert {missing}: [Errno 2] No such file or directory"
    )


@pytest.fixture
def bad_tls_files(tmp_path: Path, tls_files: tuple[Path, Path, Path]) -> Path:
    """Beside ``tls_files``: a key of another certificate, the certificate and its key in one
    file, a file that is not PEM, and the key encrypted."""
    ca = trustme.CA()
    ca.issue_cert("localhost").private_key_pem.write_to_path(str(tmp_path / "other_key.pem"))
    _, certfile, keyfile = tls_files
    (tmp_path / "both.pem").write_bytes(certfile.read_bytes() + keyfile.read_bytes())
    (tmp_path / "junk.pem").write_text("not a certificate\n", encoding="ascii")
    key = serialization.load_pem_private_key(keyfile.read_bytes(), None)
    encrypted = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.BestAvailableEncryption(b"secret"),
    )
    (tmp_path / "encrypted_key.pem").write_bytes(encrypted)
    return tmp_path


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (
            ["--certfile", "missing.pem"],
            "cannot read --certfile {d}/missing.pem: No such file or directory",
        ),
        (
            ["--certfile", "cert.pem", "--keyfile", "missing.pem"],
            "cannot read --keyfile {d}/missing.pem: No such file or directory",
        ),
        (
            ["--certfile", "cert.pem"],
            "--certfile {d}/cert.pem holds no private key: give the certificate's key with "
            "--keyfile FILE",
        ),
        (
            ["--certfile", "cert.pem", "--keyfile", "ca.pem"],
            "--keyfile {d}/ca.pem holds no PEM private key (it holds a certificate)",
        ),
        (
            ["--certfile", "cert.pem", "--keyfile", "other_key.pem"],
            "the private key in --keyfile {d}/other_key.pem is not the key of the certificate "
            "in --certfile {d}/cert.pem",
        ),
        (
            ["--certfile", "junk.pem", "--keyfile", "key.pem"],
            "--certfile {d}/junk.pem holds no PEM certificate",
        ),
        (
            ["--certfile", "key.pem"],
            "--certfile {d}/key.pem holds no PEM certificate (it holds a private key: give that "
            "as --keyfile)",
        ),
        (
            ["--certfile", "cert.pem", "--keyfile", "encrypted_key.pem"],
            "the private key in --keyfile {d}/encrypted_key.pem is encrypted; serve needs it "
            "unencrypted",
        ),
        (
            ["--certfile", "both.pem", "--client-ca", "key.pem"],
            "--client-ca {d}/key.pem holds no PEM certificate",
        ),
        (
            ["--certfile", "both.pem", "--client-ca", "missing.pem"],
            "cannot read --client-ca {d}/missing.pem: No such file or directory",
        ),
    ],
)
def test_serve_names_a_tls_file_it_cannot_use_and_what_is_wrong(
    capsys: pytest.CaptureFixture[str],
    app: Path,
    bad_tls_files: Path,
    argv: list[str],
    said: str,
) -> None:
    folder = bad_tls_files
    paths = [str(folder / arg) if arg.endswith(".pem") else arg for arg in argv]
    code, out, err = run(capsys, "serve", str(app), "--port", "0", *paths)
    assert (code, out) == (ExitCode.USAGE, "")
    assert one_error_line(err) == said.format(d=folder)


def test_serve_takes_the_certificate_and_its_key_from_one_file(
    app: Path, bad_tls_files: Path
) -> None:
    served = Served(str(app), "--certfile", str(bad_tls_files / "both.pem"))
    try:
        assert served.url.startswith("wss://")
    finally:
        served.stop()
