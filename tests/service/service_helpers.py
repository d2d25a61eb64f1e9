"""Helpers shared by the service tests (imported by module name)."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import ipaddress
import os
import shutil
import ssl
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiomqtt


from bms_estimator.mosquitto import Mosquitto as Broker  # noqa: E402,F401 - the project's one launcher
from bms_estimator.mosquitto import find_mosquitto, free_port  # noqa: E402,F401

MOSQUITTO = find_mosquitto() or os.environ.get("MOSQUITTO", "/usr/sbin/mosquitto")


def mosquitto_available() -> bool:
    return find_mosquitto() is not None


def run_async(coro: Any, timeout: float = 30.0) -> Any:
    """Run a coroutine in a fresh event loop with an overall timeout."""

    async def _guarded() -> Any:
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(_guarded())


async def wait_until(pred: Callable[[], bool], timeout: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout}s waiting for {what}")
        await asyncio.sleep(0.01)


class NotifySocket:
    """A systemd notify socket at ``path`` (``$NOTIFY_SOCKET`` set with ``monkeypatch``, no watchdog):
    :meth:`drain` returns every datagram received so far, in order."""

    def __init__(self, path: Path, monkeypatch: Any) -> None:
        import socket

        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        monkeypatch.delenv("WATCHDOG_USEC", raising=False)
        self.got: list[str] = []

    def drain(self) -> list[str]:
        while True:
            try:
                self.got.append(self.sock.recv(4096).decode())
            except BlockingIOError:
                return self.got

    def close(self) -> None:
        self.sock.close()


class Collector:
    """An aiomqtt subscriber recording every message it receives."""

    def __init__(self, port: int, topics: tuple[str, ...] = ("#",), qos: int = 2, **client_kw: Any) -> None:
        self.port = port
        self.topics = topics
        self.qos = qos
        self.client_kw = client_kw
        self.messages: list[aiomqtt.Message] = []
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> Collector:
        self.client = aiomqtt.Client("127.0.0.1", self.port, **self.client_kw)
        await self.client.__aenter__()
        for t in self.topics:
            await self.client.subscribe(t, qos=self.qos)
        self._task = asyncio.create_task(self._read())
        return self

    async def _read(self) -> None:
        with contextlib.suppress(aiomqtt.MqttError):
            async for m in self.client.messages:
                self.messages.append(m)

    async def __aexit__(self, *exc: object) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(BaseException):
                await self._task
        with contextlib.suppress(Exception):
            await self.client.__aexit__(None, None, None)

    def on(self, topic: str) -> list[aiomqtt.Message]:
        return [m for m in self.messages if m.topic.value == topic]

    def payloads(self, topic: str) -> list[str]:
        return [bytes(m.payload).decode() for m in self.on(topic)]

    async def wait(self, pred: Callable[[Collector], bool], timeout: float = 5.0, what: str = "messages") -> None:
        try:
            await wait_until(lambda: pred(self), timeout, what)
        except AssertionError as exc:
            topics = sorted({m.topic.value for m in self.messages})
            raise AssertionError(f"{exc}; got {len(self.messages)} messages on {topics[:20]}") from None


async def retained(port: int, topic: str, timeout: float = 3.0, **client_kw: Any) -> aiomqtt.Message | None:
    """The retained message a fresh subscriber gets for ``topic`` (None if none)."""
    async with Collector(port, (topic,), qos=2, **client_kw) as c:
        try:
            await c.wait(lambda c: any(m.retain for m in c.messages), timeout, f"retained {topic}")
        except AssertionError:
            return None
        return [m for m in c.messages if m.retain][-1]


# ------------------------------------------------------------------------ TLS
def make_tls_files(directory: Path) -> dict[str, Path] | None:
    """CA + server certificate for 127.0.0.1/localhost; None if no tool can make them."""
    directory.mkdir(parents=True, exist_ok=True)
    try:
        return _tls_with_cryptography(directory)
    except ImportError:
        pass
    if shutil.which("openssl"):
        return _tls_with_openssl(directory)
    return None


def _tls_with_cryptography(d: Path) -> dict[str, Path]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = dt.datetime.now(dt.timezone.utc)

    def pem_key(key: Any) -> bytes:
        return key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "bms-test-ca")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
                encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    srv_key = ec.generate_private_key(ec.SECP256R1())
    srv = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")]))
        .issuer_name(ca_name)
        .public_key(srv_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    files = {"ca": d / "ca.pem", "cert": d / "server.pem", "key": d / "server.key"}
    files["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    files["cert"].write_bytes(srv.public_bytes(serialization.Encoding.PEM))
    files["key"].write_bytes(pem_key(srv_key))
    return files


def _tls_with_openssl(d: Path) -> dict[str, Path]:
    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True, timeout=30)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    run("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "1", "-subj", "/CN=bms-test-ca")
    run("req", *ec, "-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=localhost")
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    run(
        "x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
        "-out", "server.pem", "-days", "1", "-extfile", "ext.cnf",
    )
    return {"ca": d / "ca.pem", "cert": d / "server.pem", "key": d / "server.key"}


def client_tls_context(ca: Path) -> ssl.SSLContext:
    return ssl.create_default_context(cafile=str(ca))
