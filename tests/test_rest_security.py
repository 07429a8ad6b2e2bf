"""REST hardening against a real uvicorn server in its own process: tokens, failed-attempt limit, body limits, memory, caps, audit, TLS."""

import contextlib
import io
import json
import select
import socket
import stat
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import httpx
import psutil
import pytest

from drillnav.service.auth import FailureLimiter, resolve_token
from drillnav.service.settings import SettingsError, load_settings
from conftest import free_port
from tls_certs import make_test_pki

TOKEN = "rest-security-token-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SERVER = Path(__file__).with_name("rest_server.py")
MB = 1024 * 1024


@contextlib.contextmanager
def server(tmp_path, api=None, *, scheme="http", client_kwargs=None):
    port = free_port()
    work = tmp_path / f"srv-{port}"
    log_path = tmp_path / f"server-{port}.log"
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen([sys.executable, str(SERVER), "--port", str(port), "--work", str(work), "--token", TOKEN, "--api-json", json.dumps(api or {})],
                                stdout=log_file, stderr=subprocess.STDOUT)
        try:
            base = f"{scheme}://127.0.0.1:{port}"
            with httpx.Client(base_url=base, timeout=30, **(client_kwargs or {})) as client:
                deadline = time.monotonic() + 30
                while True:
                    try:
                        if client.get("/health").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass
                    assert proc.poll() is None, log_path.read_text()
                    assert time.monotonic() < deadline, "server did not come up: " + log_path.read_text()
                    time.sleep(0.1)
                yield client, proc, port, work, log_path
        finally:
            proc.kill()
            proc.wait(timeout=10)


def test_no_default_token_real_device_refuses_twin_generates():
    with pytest.raises(SettingsError, match=r"api\.token is not set"):
        resolve_token(load_settings())
    out = io.StringIO()
    token = resolve_token(load_settings(twin=True), out=out)
    assert len(token) >= 16 and out.getvalue().count(token) == 1
    assert resolve_token(load_settings(twin=True), out=io.StringIO()) != token  # random per run
    with pytest.raises(SettingsError, match=r"api\.token"):
        load_settings(api={"token": "fifteen-chars.."})
    assert resolve_token(load_settings(api={"token": "sixteen-chars..."})) == "sixteen-chars..."


def test_failure_limiter_window():
    lim = FailureLimiter(burst=3, window_s=10.0)
    for t in (0.0, 1.0, 2.0):
        assert lim.retry_after_s("a", now=t) == 0.0
        lim.fail("a", now=t)
    assert lim.retry_after_s("a", now=2.5) == pytest.approx(7.5)
    assert lim.retry_after_s("b", now=2.5) == 0.0  # per client
    assert lim.retry_after_s("a", now=10.0) == 0.0  # the first failure has left the window


def test_wrong_tokens_get_429_and_log_lines(tmp_path):
    with server(tmp_path) as (client, proc, port, work, log_path):
        codes = []
        t0 = time.monotonic()
        for i in range(1000):
            r = client.post("/registration/refresh", headers={"Authorization": f"Bearer wrong-{i}"})
            codes.append(r.status_code)
            if r.status_code == 429:
                assert int(r.headers["Retry-After"]) >= 1
        elapsed = time.monotonic() - t0
        assert elapsed < 10.0, "the burst window is 10 s: the counts below assume the run fits in it"
        assert codes[:10] == [403] * 10 and codes[10:] == [429] * 990
        # Blocked: even the right token waits; reading is never blocked.
        r = client.post("/registration/refresh", headers=AUTH)
        assert r.status_code == 429 and int(r.headers["Retry-After"]) <= 10
        assert client.get("/status").json()["refreshes"] == 0
        r = client.post("/registration/refresh")  # no token at all: from another client it would be 401
        assert r.status_code == 429
        log = log_path.read_text()
        fails = [line for line in log.splitlines() if "failed authentication (" in line]
        assert len(fails) == 10 and all("127.0.0.1" in line for line in fails)
        assert "client 127.0.0.1 blocked" in log
        audit = [json.loads(line) for line in (work / "audit" / "audit.jsonl").read_text().splitlines()]
        assert [e["action"] for e in audit].count("auth-failed") == 10
        assert any(e["action"] == "auth-rate-limited" for e in audit)
        print(f"\n1000 wrong tokens in {elapsed:.1f} s: {codes.count(403)} x 403, {codes.count(429)} x 429, {len(fails)} log lines")


def _body_chunks(total_bytes, chunk=256 * 1024):
    """The upload, made on demand: nothing is held beyond one chunk."""
    piece = b"\0" * chunk
    sent = 0
    while sent < total_bytes:
        yield piece
        sent += len(piece)


def _multipart_chunks(total_bytes):
    """A well-formed multipart upload of one huge file part (so only the size can stop it)."""
    yield b'--xyz\r\nContent-Disposition: form-data; name="kind"\r\n\r\ncamera\r\n'
    yield b'--xyz\r\nContent-Disposition: form-data; name="files"; filename="big.png"\r\nContent-Type: image/png\r\n\r\n'
    yield from _body_chunks(total_bytes)


def _stream_until_answer(port, head: bytes, chunks, *, chunked: bool, stop_after_bytes: int):
    """Send ``head`` then body chunks until the server answers; returns (status, body bytes sent, response text)."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(head)
    sock.setblocking(False)
    sent, response = 0, b""
    pending = b""
    try:
        for piece in chunks:
            pending = (f"{len(piece):x}\r\n".encode() + piece + b"\r\n") if chunked else piece
            while pending:
                readable, writable, _ = select.select([sock], [sock], [], 5.0)
                if readable:
                    break
                try:
                    n = sock.send(pending)
                except (BrokenPipeError, ConnectionResetError):
                    readable = [sock]
                    break
                pending = pending[n:]
                sent += n
            if readable or sent > stop_after_bytes:
                break  # the server answered: the generator is not asked for more
        sock.setblocking(True)
        sock.settimeout(10)
        with contextlib.suppress(ConnectionResetError):
            while b"\r\n\r\n" not in response:
                got = sock.recv(65536)
                if not got:
                    break
                response += got
    finally:
        sock.close()
    status = int(response.split(b" ", 2)[1]) if response.startswith(b"HTTP/") else None
    return status, sent, response.decode("latin-1")


def _upload_head(port, *, length: int | None, auth: bool, path="/calibration/jobs", ctype="multipart/form-data; boundary=xyz"):
    lines = [f"POST {path} HTTP/1.1", f"Host: 127.0.0.1:{port}", f"Content-Type: {ctype}"]
    lines.append(f"Content-Length: {length}" if length is not None else "Transfer-Encoding: chunked")
    if auth:
        lines.append(AUTH["Authorization"].join(["Authorization: ", ""]))
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


class _PeakRss:
    """Samples a process's resident memory every 5 ms while in the ``with``."""

    def __init__(self, pid):
        self.proc, self.peak, self._stop = psutil.Process(pid), 0, threading.Event()

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.proc.memory_info().rss)
            time.sleep(0.005)

    def __enter__(self):
        self.peak = self.proc.memory_info().rss
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)


def _png_bomb(side=30000, rows_per_block=1000):
    """A valid PNG of side x side grey pixels (all zero) in about 0.9 MB: repeated, fully flushed deflate blocks."""

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    block = bytes((side + 1) * rows_per_block)  # each row: filter byte + pixels
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    adler = 1
    for _ in range(side // rows_per_block):
        adler = zlib.adler32(block, adler)
    idat = b"\x78\xda" + piece * (side // rows_per_block) + zlib.compressobj(9, zlib.DEFLATED, -15).flush() + struct.pack(">I", adler)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_hostile_bodies_refused_early_and_memory_bounded(tmp_path):
    figures = {}
    with server(tmp_path) as (client, proc, port, work, log_path):
        for _ in range(3):  # warm up: first requests import and allocate what every later one shares
            client.get("/status")
            client.post("/registration/refresh", headers=AUTH)
        idle = psutil.Process(proc.pid).memory_info().rss
        with _PeakRss(proc.pid) as rss:
            # 1 GiB unauthenticated upload, declared, then chunked (no length to refuse on): 401 before the body is read.
            # What the server read: the bytes uvicorn's protocol took off its sockets (tests/rest_server.py counts them).
            for chunked in (False, True):
                read_before = client.get("/test/bytes-read").json()["bytes"]
                status, sent, _ = _stream_until_answer(port, _upload_head(port, length=None if chunked else 1 << 30, auth=False), _multipart_chunks(1 << 30),
                                                       chunked=chunked, stop_after_bytes=10 * MB)
                server_read = client.get("/test/bytes-read").json()["bytes"] - read_before
                assert status == 401 and sent < 10 * MB and server_read < 10 * MB, (status, sent, server_read)
                figures[f"1 GiB unauthenticated, {'chunked' if chunked else 'Content-Length'}: client sent"] = sent
                figures[f"1 GiB unauthenticated, {'chunked' if chunked else 'Content-Length'}: server read"] = server_read
            # Authenticated 1 GiB upload, declared: 413 on its Content-Length alone.
            status, sent, text = _stream_until_answer(port, _upload_head(port, length=1 << 30, auth=True), _body_chunks(1 << 30), chunked=False, stop_after_bytes=10 * MB)
            assert status == 413 and sent < 10 * MB, (status, sent)
            # Authenticated chunked upload: read up to the 64 MiB limit, then 413.
            status, sent, _ = _stream_until_answer(port, _upload_head(port, length=None, auth=True), _multipart_chunks(1 << 30), chunked=True, stop_after_bytes=200 * MB)
            assert status == 413 and sent < 100 * MB, (status, sent)
            figures["1 GiB authenticated, chunked (limit 64 MiB): client sent"] = sent
            # 200 MiB JSON body, declared and chunked: 413 at 64 KiB.
            status, sent, _ = _stream_until_answer(port, _upload_head(port, length=200 * MB, auth=True, path="/recordings", ctype="application/json"),
                                                   _body_chunks(200 * MB), chunked=False, stop_after_bytes=10 * MB)
            assert status == 413 and sent < 10 * MB, (status, sent)
            status, sent, _ = _stream_until_answer(port, _upload_head(port, length=None, auth=True, path="/recordings", ctype="application/json"),
                                                   (b'{"name": "' + b"a" * (256 * 1024) for _ in range(800)), chunked=True, stop_after_bytes=50 * MB)
            assert status == 413 and sent < 10 * MB, (status, sent)
            figures["200 MiB JSON, chunked (limit 64 KiB): client sent"] = sent
            # A PNG bomb: 30000 x 30000 declared in under a megabyte, refused from its header.
            bomb = _png_bomb()
            r = client.post("/calibration/jobs", headers=AUTH, data={"kind": "camera", "board": "checkerboard:9x6:25mm"},
                            files=[("files", ("bomb.png", bomb, "image/png"))])
            assert r.status_code == 413 and "900000000 pixels" in r.json()["detail"] and "api.max_image_mpixel" in r.json()["detail"]
            figures["PNG bomb bytes"] = len(bomb)
            r = client.post("/calibration/jobs", headers=AUTH, data={"kind": "camera", "board": "checkerboard:9x6:25mm"},
                            files=[("files", ("big.png", _png_bomb(side=8000), "image/png"))])  # under Pillow's own guard: ours speaks
            assert r.status_code == 413 and "8000x8000 px is 64 Mpixel" in r.json()["detail"], r.json()
        assert client.get("/status").status_code == 200  # still serving
        grown = rss.peak - idle
        print(f"\nidle RSS {idle / MB:.0f} MB, peak {rss.peak / MB:.0f} MB (+{grown / MB:.0f} MB); body bytes sent before the answer: "
              + ", ".join(f"{k}: {v / MB:.2f} MB" if "sent" in k else f"{k}: {v}" for k, v in figures.items()))
        assert grown < 200 * MB


def test_caps_audit_and_job_expiry(tmp_path):
    api = {"max_jobs_running": 2, "max_recordings": 1, "job_expiry_s": 1.0}
    with server(tmp_path, api) as (client, proc, port, work, log_path):
        live = {"kind": "camera", "board": "checkerboard:9x6:25mm", "live_seconds": "30", "live_fps": "5"}
        ids = [client.post("/calibration/jobs", headers=AUTH, data=live).json()["id"] for _ in range(2)]
        r = client.post("/calibration/jobs", headers=AUTH, data=live)
        assert r.status_code == 429 and "api.max_jobs_running" in r.json()["detail"]
        for job_id in ids:
            assert client.delete(f"/calibration/jobs/{job_id}", headers=AUTH).status_code == 200
        deadline = time.monotonic() + 10
        while any(client.get(f"/calibration/jobs/{i}").json().get("state") != "cancelled" for i in ids):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(1.1)  # past job_expiry_s: finished jobs are forgotten
        assert client.get("/calibration/jobs").json() == []
        assert client.get(f"/calibration/jobs/{ids[0]}").status_code == 404

        assert client.post("/recordings", headers=AUTH, json={"name": "case1"}).status_code == 201
        r = client.post("/recordings", headers=AUTH, json={"name": "case2"})
        assert r.status_code == 429 and "api.max_recordings" in r.json()["detail"]
        assert client.delete("/recordings/case1", headers=AUTH).status_code == 200
        assert client.post("/carm/shots", headers=AUTH, json={"view": "inlet"}).status_code == 201
        assert client.post("/registration/refresh", headers=AUTH).status_code == 202
        assert client.post("/registration/refresh", headers={"Authorization": "Bearer nope"}).status_code == 403

        path = work / "audit" / "audit.jsonl"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600 and stat.S_IMODE(path.parent.stat().st_mode) == 0o700
        entries = [json.loads(line) for line in path.read_text().splitlines()]
        actions = [e["action"] for e in entries]
        assert actions == ["calibration-job-submitted", "calibration-job-submitted", "calibration-job-cancelled", "calibration-job-cancelled",
                           "recording-started", "recording-stopped", "shot-requested", "registration-refreshed", "auth-failed"]
        assert entries[4]["detail"]["name"] == "case1" and entries[4]["actor"].startswith("127.0.0.1")
        assert all(isinstance(e["stamp_ns"], int) for e in entries)


def test_https_and_mutual_tls(tmp_path):
    pki = make_test_pki(tmp_path / "pki")
    api = {"tls_cert": str(pki.server_cert), "tls_key": str(pki.server_key), "tls_client_ca": str(pki.ca)}
    with server(tmp_path, api, scheme="https", client_kwargs={"verify": _client_ssl(pki)}) as (client, proc, port, work, log_path):
        assert client.post("/registration/refresh", headers=AUTH).status_code == 202
        no_cert = _client_ssl(pki, with_cert=False)
        with pytest.raises(httpx.TransportError):  # mutual TLS: no client certificate, no connection
            httpx.get(f"https://127.0.0.1:{port}/health", verify=no_cert, timeout=10)
        with pytest.raises(httpx.TransportError):  # plain HTTP to the HTTPS port
            httpx.get(f"http://127.0.0.1:{port}/health", timeout=10)


def _client_ssl(pki, with_cert=True):
    import ssl

    ctx = ssl.create_default_context(cafile=str(pki.ca))
    if with_cert:
        ctx.load_cert_chain(str(pki.client_cert), str(pki.client_key))
    return ctx
