"""Against a real ``pbrsr serve`` (uvicorn) process: an upload over the limit is refused with
413 while it streams - long before the client has sent it all - and leaves no file."""

from __future__ import annotations

import select
import socket
import time

import httpx

from tests.service_support import api_server, asset_bytes, cleanup_redis, make_settings

MB = 1024 * 1024


def _read_response(sock: socket.socket, timeout: float) -> bytes:
    sock.settimeout(timeout)
    data = b""
    try:
        while b"\r\n\r\n" not in data or not data.endswith(b"}"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return data


def test_oversized_upload_is_refused_while_streaming(tmp_path):
    settings = make_settings(tmp_path, max_upload_mb=1)
    try:
        with api_server(settings, tmp_path / "api.log") as base:
            port = int(base.rsplit(":", 1)[1])
            boundary = "pbrsrtestboundary"
            head = (
                f"--{boundary}\r\n"
                'Content-Disposition: form-data; name="file"; filename="big.glb"\r\n'
                "Content-Type: application/octet-stream\r\n\r\n"
            ).encode()
            sock = socket.create_connection(("127.0.0.1", port))
            # chunked: no Content-Length, so only the streaming check can catch it
            sock.sendall(
                b"POST /v1/jobs HTTP/1.1\r\nHost: localhost\r\n"
                + f"Content-Type: multipart/form-data; boundary={boundary}\r\n".encode()
                + b"Transfer-Encoding: chunked\r\n\r\n"
            )

            def send_chunk(payload: bytes) -> None:
                sock.sendall(f"{len(payload):x}\r\n".encode() + payload + b"\r\n")

            send_chunk(head)
            total, planned, block = 0, 256 * MB, b"\0" * (64 * 1024)
            answered = False
            try:
                while total < planned:
                    send_chunk(block)
                    total += len(block)
                    readable, _, _ = select.select([sock], [], [], 0)
                    if readable:
                        answered = True
                        break
            except (BrokenPipeError, ConnectionResetError):
                answered = True  # the server answered and closed while we were sending
            response = _read_response(sock, 10)
            sock.close()
            assert answered and total < planned / 4, f"sent {total / MB:.0f} MB first"
            assert response.startswith(b"HTTP/1.1 413"), response[:200]
            assert b"application/problem+json" in response
            assert b"limit-exceeded" in response

            # nothing was kept, and the server still serves normal uploads
            time.sleep(0.2)
            assert list((settings.storage_dir / "uploads").iterdir()) == []
            ok = httpx.post(
                base + "/v1/jobs",
                files={"file": ("a.glb", asset_bytes(tmp_path), "application/octet-stream")},
                data={"options": '{"method": "bicubic"}'},
                timeout=60,
            )
            assert ok.status_code == 202, ok.text
            too_big = httpx.post(  # declared Content-Length over the limit: refused at once
                base + "/v1/jobs",
                files={"file": ("b.glb", b"\0" * (2 * MB), "application/octet-stream")},
                timeout=60,
            )
            assert too_big.status_code == 413
    finally:
        cleanup_redis(settings)
