"""Raw HTTP/1.1 over a loopback socket, for the tests that send what no HTTP client would (hostile heads,
stalled bodies, quiet connections)."""

from __future__ import annotations

import json
import select
import socket


def http_head(path: str, headers: dict[str, str], *, method: str = "POST") -> bytes:
    lines = [f"{method} {path} HTTP/1.1", "Host: 127.0.0.1", *[f"{k}: {v}" for k, v in headers.items()]]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin1")


def read_answer(sock: socket.socket) -> tuple[int, dict[str, str], bytes]:
    """Status, headers and body of one HTTP/1.1 answer (until Content-Length or the connection closes)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin1").split("\r\n")
    if not lines[0].startswith("HTTP/1.1 "):
        raise AssertionError(f"no HTTP answer, got {data[:200]!r}")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    length = int(headers.get("content-length", "-1"))
    while length < 0 or len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return int(lines[0].split()[1]), headers, body


def raw_exchange(port: int, pieces: list[bytes], *, pause_s: float = 0.0, timeout_s: float = 30.0
                 ) -> tuple[int, dict[str, str], bytes]:
    """Send ``pieces`` (``pause_s`` apart), stopping early once the server answers; read its answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as sock:
        for piece in pieces:
            if select.select([sock], [], [], pause_s)[0]:
                break  # answered (and about to close): stop sending
            try:
                sock.sendall(piece)
            except (BrokenPipeError, ConnectionResetError):
                break
        return read_answer(sock)


def json_error(status: int, headers: dict[str, str], body: bytes, expected: int) -> dict:
    assert status == expected, (status, body[:300])
    assert headers["content-type"].startswith("application/json"), headers
    parsed = json.loads(body)
    assert set(parsed) >= {"error", "detail"} and parsed["detail"], parsed
    return parsed


def chunks(data: bytes, size: int) -> list[bytes]:
    return [data[i:i + size] for i in range(0, len(data), size)]
