"""The editor's server in-process on 127.0.0.1 with a stand-in engine: what a bad or hostile
request gets back (bounded error text, a 503 past the pending exports), and the exports held
by slow readers let go once they leave."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import types
from typing import Any, Awaitable, Callable

import pytest
from aiohttp.test_utils import TestClient, TestServer

from editor import server
from editor.server import TOKEN_HEADER

TOKEN = "t" * 16
ENGINE = types.SimpleNamespace(
    pca=types.SimpleNamespace(n_points=3), size=(40, 30), layout=types.SimpleNamespace(point_names=("a", "b", "c"))
)
EXPORT = {"fps": 10, "keyframes": [{"time_s": 0.0, "points": [[1, 2], [3, 4], [5, 6]]}]}


def serve(scenario: Callable[[TestClient], Awaitable[Any]]) -> Any:
    """``scenario(client)``'s result, against the editor's app on 127.0.0.1, on an event loop of
    its own thread (the session may run a loop on this one)."""

    async def main() -> Any:
        client = TestClient(TestServer(server.make_app(ENGINE, token=TOKEN, processes=0), host="127.0.0.1"))
        await client.start_server()
        try:
            return await scenario(client)
        finally:
            await client.close()

    results: list[Any] = []
    thread = threading.Thread(target=lambda: results.append(asyncio.run(main())))
    thread.start()
    thread.join()
    return results[0]


def post(client: TestClient, path: str, data: bytes) -> Awaitable[Any]:
    return client.post(path, data=data, headers={TOKEN_HEADER: TOKEN, "Content-Type": "application/json"})


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        (
            json.dumps({"client": "x" * 1_000_000, "seq": 1, "base": None, "pinned": []}).encode(),
            "field 'client': expected a string of 1-64 characters, got 'xxxx",
        ),
        (b'{"client": "t", "seq": ' + b"9" * 5000 + b"}", "an integer of 5000 characters in the JSON body: at most 4300 digits"),
    ],
    ids=["a 1 MB string", "a 5000-digit integer"],
)
def test_a_bad_value_is_quoted_in_a_bounded_400_not_echoed(body, expected):
    async def scenario(client: TestClient) -> tuple[int, dict]:
        answer = await post(client, "/api/render", body)
        return answer.status, await answer.json()

    status, answer = serve(scenario)
    assert status == 400 and answer["error"].startswith(expected)
    assert len(answer["error"]) <= 450 and "\n" not in answer["error"]


def test_exports_held_by_slow_readers_are_bounded_and_let_go(monkeypatch):
    """Two clients that never read their 24 MB export hold both places; a third is refused with
    503 and Retry-After (nothing built for it); once the two leave, their exports are let go and
    an export is served whole again."""
    data = bytes(24 << 20)  # more than the sockets' buffers hold: a reader that does not read holds it
    built = []
    monkeypatch.setattr(server, "export_bytes", lambda engine, body: built.append(1) or data)
    request = json.dumps(EXPORT).encode()
    raw = (
        f"POST /api/export HTTP/1.1\r\nHost: 127.0.0.1\r\n{TOKEN_HEADER}: {TOKEN}\r\n"
        f"Content-Type: application/json\r\nContent-Length: {len(request)}\r\n\r\n"
    ).encode() + request

    async def slow_reader(port: int) -> asyncio.StreamWriter:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
        _, writer = await asyncio.open_connection(sock=sock)
        writer.write(raw)
        await writer.drain()
        return writer

    async def pending_becomes(app: Any, count: int) -> None:
        for _ in range(2000):  # a bound on the wait, not a timing assertion
            if len(app[server.PENDING]) == count:
                return
            await asyncio.sleep(0.01)
        raise AssertionError(f"pending exports stayed {len(app[server.PENDING])}, expected {count}")

    async def scenario(client: TestClient) -> tuple[int, str | None, int, int, int]:
        app = client.server.app
        slow = [await slow_reader(client.server.port) for _ in range(server.EXPORTS_PENDING)]
        await pending_becomes(app, server.EXPORTS_PENDING)
        refused = await post(client, "/api/export", request)
        refused_status, retry = refused.status, refused.headers.get("Retry-After")
        builds = len(built)
        for writer in slow:
            writer.transport.abort()
        await pending_becomes(app, 0)
        served = await post(client, "/api/export", request)
        return refused_status, retry, builds, served.status, len(await served.read())

    refused, retry, builds, status, size = serve(scenario)
    assert (refused, retry, builds) == (503, str(server.EXPORT_RETRY_S), server.EXPORTS_PENDING)
    assert (status, size) == (200, len(data))
