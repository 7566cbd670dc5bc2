"""The editor's server as started by its command: token, bounded and validated bodies, 4xx JSON
errors, stale requests dropped, and still serving after all of them."""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
import urllib.error
import urllib.request

import numpy as np
import pytest

from editor.server import MAX_BODY, TOKEN_HEADER
from stages.actor_pack import load_pack
from tests.editor.conftest import PACK, REPO, assert_is_pipeline_image, decode, synthesize_stage

N = load_pack(PACK).layout.n_points


def call(editor, path, body=None, *, token=None, raw: bytes | None = None, content_type="application/json"):
    """(status, headers, body bytes) of one request."""
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    request = urllib.request.Request(editor.base + path, data=data, method="POST" if data is not None else "GET")
    request.add_header(TOKEN_HEADER, editor.token if token is None else token)
    if data is not None:
        request.add_header("Content-Type", content_type)
    try:
        with urllib.request.urlopen(request, timeout=120) as response:
            return response.status, response.headers, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.headers, error.read()


def unpack(body: bytes) -> tuple[dict, list[bytes]]:
    (length,) = struct.unpack("<I", body[:4])
    meta = json.loads(body[4 : 4 + length])
    images, offset = [], 4 + length
    for size in meta["sizes"]:
        images.append(body[offset : offset + size])
        offset += size
    assert offset == len(body)
    return meta, images


SEQ = iter(range(1, 10**6))


def render_body(pinned, *, base=None, client="tests"):
    return {"client": client, "seq": next(SEQ), "base": base, "pinned": pinned}


def test_the_image_when_the_mouse_stops_is_the_pipelines_synthesis(editor_server, pipeline):
    from stages.propagation.propagate import propagate_edit

    model, pca = pipeline
    neutral = load_pack(PACK).neutral.points
    pinned = {40: neutral[40] + [1.0, 4.0], 90: neutral[90] + [-2.0, 0.5]}
    status, headers, body = call(editor_server, "/api/render", render_body([[i, *xy] for i, xy in pinned.items()]))
    assert status == 200 and headers["Content-Type"] == "application/octet-stream"
    meta, (png,) = unpack(body)
    assert meta["types"] == ["image/png"] and png[:8] == b"\x89PNG\r\n\x1a\n"
    points = np.array(meta["points"])
    np.testing.assert_allclose(points, propagate_edit(pca, neutral, pinned), rtol=0, atol=1e-9)
    np.testing.assert_allclose(points[40], neutral[40] + [1.0, 4.0])
    assert_is_pipeline_image(decode(png), synthesize_stage(model, points[None])[0])


def test_the_image_while_dragging_is_the_pipelines_synthesis_as_jpeg(editor_server, pipeline):
    neutral = load_pack(PACK).neutral.points
    body = dict(render_body([[40, neutral[40][0], neutral[40][1] + 4.0]]), preview=True)
    status, _, answer = call(editor_server, "/api/render", body)
    assert status == 200
    meta, (jpeg,) = unpack(answer)
    assert meta["types"] == ["image/jpeg"] and jpeg[:3] == b"\xff\xd8\xff"
    image = decode(jpeg).astype(np.float64)
    frame = synthesize_stage(pipeline[0], np.array(meta["points"])[None])[0].astype(np.float64) * 255.0
    assert image.shape == frame.shape  # the pack's size (the default --preview-scale 1)
    # JPEG (quality 90) of the pipeline's frame: off by a few levels at edges, about one on average
    error = np.abs(image - frame)
    assert error.mean() < 1.5 and np.percentile(error, 99) < 12, (error.mean(), np.percentile(error, 99))
    neutral_frame = synthesize_stage(pipeline[0], neutral[None])[0].astype(np.float64) * 255.0
    assert np.abs(image - neutral_frame).mean() > error.mean()  # and it shows the edit


@pytest.mark.parametrize(
    "body, expected",
    [
        ({"client": "t", "seq": 1, "base": None, "pinned": [[N, 1.0, 2.0]]}, "index"),
        ({"client": "t", "seq": 1, "base": None, "pinned": [[-1, 1.0, 2.0]]}, "index"),
        ({"client": "t", "seq": 1, "base": None, "pinned": [[3, 1.0, 1e9]]}, "number in"),
        ({"client": "t", "seq": 1, "base": None, "pinned": [[3, "1", 2.0]]}, "finite number"),
        ({"client": "t", "seq": 1, "base": None, "pinned": [[3, 1.0, 2.0], [3, 1.0, 2.0]]}, "twice"),
        ({"client": "t", "seq": 1, "base": [[0.0, 0.0]], "pinned": []}, "field 'base'"),
        ({"client": "t", "seq": -1, "base": None, "pinned": []}, "seq"),
        ({"client": "t", "base": None, "pinned": []}, "seq"),
        ([1, 2, 3], "JSON object"),
        ({"client": "t", "seq": 1, "base": None, "pinned": [], "preview": "yes"}, "field 'preview'"),
    ],
)
def test_bad_render_bodies_are_400_json(editor_server, body, expected):
    status, headers, answer = call(editor_server, "/api/render", body)
    assert status == 400 and headers["Content-Type"].startswith("application/json")
    assert expected in json.loads(answer)["error"]


def test_nan_malformed_oversized_and_unauthorised_requests(editor_server):
    nan = b'{"client": "t", "seq": 1, "base": null, "pinned": [[3, NaN, 2.0]]}'
    status, _, answer = call(editor_server, "/api/render", raw=nan)
    assert status == 400 and "finite" in json.loads(answer)["error"]
    status, _, answer = call(editor_server, "/api/render", raw=b'{"client": "t", "seq": 1,')
    assert status == 400 and "error" in json.loads(answer)
    status, _, answer = call(editor_server, "/api/render", raw=b"x" * (MAX_BODY + 1))
    assert status == 413 and "error" in json.loads(answer)
    status, _, _ = call(editor_server, "/api/render", raw=b"{}", content_type="text/plain")
    assert status == 415
    for token in ("", "wrong" * 8):
        status, _, answer = call(editor_server, "/api/describe", token=token)
        assert status == 403 and json.loads(answer)["error"] == "missing or wrong token"
    status, _, _ = call(editor_server, "/static/editor.js", token="")
    assert status == 403
    for index in ("5", "-1", "x"):
        status, _, answer = call(editor_server, f"/api/frame?index={index}")
        assert status == 400 and "0..4" in json.loads(answer)["error"]
    # ...and it still serves.
    status, _, answer = call(editor_server, "/api/describe")
    assert status == 200 and len(json.loads(answer)["names"]) == N


def test_a_request_older_than_the_newest_is_dropped(editor_server):
    newer = render_body([], client="stale-test")
    older = dict(newer, seq=newer["seq"] - 1)
    assert call(editor_server, "/api/render", newer)[0] == 200
    status, _, answer = call(editor_server, "/api/render", older)
    assert status == 409 and json.loads(answer)["error"] == "superseded"


def test_inbetweens_are_five_frames_and_the_current_one_lossless(editor_server):
    neutral = load_pack(PACK).neutral.points
    current = neutral + [0.0, 1.5]
    status, _, body = call(
        editor_server, "/api/inbetweens", {"client": "tests", "seq": next(SEQ), "from": neutral.tolist(), "to": current.tolist()}
    )
    assert status == 200
    meta, images = unpack(body)
    assert len(images) == 6 and all(image[:3] == b"\xff\xd8\xff" for image in images[:5])
    assert meta["types"] == ["image/jpeg"] * 5 + ["image/png"]
    np.testing.assert_allclose(meta["points"], current)


def test_export_answers_a_points_file(editor_server):
    neutral = load_pack(PACK).neutral.points
    keys = [{"time_s": 0.0, "points": neutral.tolist()}, {"time_s": 0.5, "points": (neutral + 2.0).tolist()}]
    status, headers, body = call(editor_server, "/api/export", {"fps": 4, "keyframes": keys})
    assert status == 200 and "keyframes.npz" in headers["Content-Disposition"]
    with np.load(io.BytesIO(body), allow_pickle=False) as data:
        np.testing.assert_allclose(data["xy"][:, 0], [neutral[0], neutral[0] + 1.0, neutral[0] + 2.0])
        assert float(data["fps"]) == 4.0
    status, _, answer = call(editor_server, "/api/export", {"fps": 4, "keyframes": keys[::-1]})
    assert status == 400 and "increase" in json.loads(answer)["error"]


def test_frames_of_the_performance(editor_server, performance):
    status, _, answer = call(editor_server, "/api/frame?index=3")
    assert status == 200
    with np.load(performance, allow_pickle=False) as data:
        np.testing.assert_array_equal(json.loads(answer)["points"], data["target_xy"][3])


@pytest.mark.subprocess
def test_binding_a_remote_address_needs_an_explicit_option():
    result = subprocess.run(
        [sys.executable, "-m", "editor.cli", "--pack", str(PACK), "--host", "0.0.0.0"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "--allow-remote" in result.stderr


@pytest.mark.subprocess
def test_an_allowed_remote_address_is_warned_about(tmp_path):
    # A folder without pack.yaml: the command warns, then stops before building anything.
    result = subprocess.run(
        [sys.executable, "-m", "editor.cli", "--pack", str(tmp_path), "--host", "0.0.0.0", "--allow-remote"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "WARNING: binding 0.0.0.0" in result.stderr
    assert result.returncode == 2 and "no pack.yaml" in result.stderr


@pytest.mark.subprocess
@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated"])
def test_an_empty_or_truncated_performance_is_one_line_exit_2(tmp_path, content):
    performance = tmp_path / "data.npz"
    performance.write_bytes(content)
    result = subprocess.run(
        [sys.executable, "-m", "editor.cli", "--pack", str(PACK), "--performance", str(performance)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        f"expression-editor: {performance}: not a readable .npz (File is not a zip file)"
    )


# -- bad requests answered as JSON 4xx; exports bounded and built off the event loop -----------


def raw_request(editor, lines: list[bytes], body: bytes = b"") -> tuple[int, bytes]:
    """(status, body) of a request written byte for byte (urllib refuses non-ASCII headers)."""
    import socket
    from urllib.parse import urlsplit

    where = urlsplit(editor.base)
    with socket.create_connection((where.hostname, where.port), timeout=60) as conn:
        head = b"\r\n".join([*lines, b"Host: x", b"Connection: close", f"Content-Length: {len(body)}".encode(), b"", b""])
        conn.sendall(head + body)
        answer = b""
        while chunk := conn.recv(65536):
            answer += chunk
    status = int(answer.split(b" ", 2)[1])
    return status, answer.partition(b"\r\n\r\n")[2]


def test_a_token_header_that_is_not_utf8_is_refused_as_json(editor_server):
    status, body = raw_request(editor_server, [b"GET /api/describe HTTP/1.1", TOKEN_HEADER.encode() + b": \xff\xfe"])
    assert status == 403 and json.loads(body) == {"error": "missing or wrong token"}


def test_a_huge_integer_coordinate_is_a_400(editor_server):
    status, _, answer = call(editor_server, "/api/render", render_body([[40, 10**400, 3.0]]))
    assert status == 400 and "expected a finite number" in json.loads(answer)["error"]


def test_a_body_nested_too_deep_is_a_400(editor_server):
    raw = b"[" * 100_000 + b"]" * 100_000
    status, _, answer = call(editor_server, "/api/render", raw=raw)
    assert status == 400 and json.loads(answer) == {"error": "the JSON body is nested too deeply"}


def test_an_export_beyond_the_frame_bound_is_refused(editor_server):
    neutral = load_pack(PACK).neutral.points.tolist()
    keys = [{"time_s": 0.0, "points": neutral}, {"time_s": 600.0, "points": neutral}]
    status, _, answer = call(editor_server, "/api/export", {"fps": 240, "keyframes": keys})
    assert status == 400 and "144001 frames" in json.loads(answer)["error"] and "at most 36000" in json.loads(answer)["error"]


def test_exports_are_built_off_the_event_loop_one_at_a_time(monkeypatch):
    """In-process, with a stand-in engine: the export is built on another thread than the
    event loop's, and two requests at once are built one after the other."""
    import asyncio
    import threading
    import types

    from aiohttp.test_utils import TestClient, TestServer

    from editor import server

    engine = types.SimpleNamespace(
        pca=types.SimpleNamespace(n_points=3), size=(40, 30), layout=types.SimpleNamespace(point_names=("a", "b", "c"))
    )
    built, busy = [], []
    real = server.points_file_bytes

    def spy(*args, **kwargs):
        busy.append(1)
        built.append((threading.current_thread(), len(busy)))
        threading.Event().wait(0.05)
        busy.pop()
        return real(*args, **kwargs)

    monkeypatch.setattr(server, "points_file_bytes", spy)
    body = {
        "fps": 10,
        "keyframes": [{"time_s": 0.0, "points": [[1, 2], [3, 4], [5, 6]]}, {"time_s": 2.0, "points": [[2, 2], [3, 5], [5, 7]]}],
    }

    async def exercise():
        client = TestClient(TestServer(server.make_app(engine, token="t" * 16, processes=0)))
        await client.start_server()
        try:
            answers = await asyncio.gather(
                *[client.post("/api/export", json=body, headers={TOKEN_HEADER: "t" * 16}) for _ in range(2)]
            )
            assert [a.status for a in answers] == [200, 200]
            return threading.current_thread()
        finally:
            await client.close()

    threads = []  # the event loop's thread: one of its own (the session may run a loop on this one)
    runner = threading.Thread(target=lambda: threads.append(asyncio.run(exercise())))
    runner.start()
    runner.join()
    (loop_thread,) = threads
    assert len(built) == 2 and all(thread is not loop_thread for thread, _ in built)
    assert [at_once for _, at_once in built] == [1, 1]


@pytest.mark.subprocess
def test_the_editor_started_in_the_background_stops_on_sigint():
    """A script's background job starts with SIGINT ignored (here: `trap "" INT`, then exec);
    the editor honours it anyway: exit 130."""
    import signal

    command = ["bash", "-c", 'trap "" INT; exec "$0" "$@"', sys.executable, "-m", "editor.cli", "--pack", str(PACK)]
    process = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        while "?token=" not in (line := process.stdout.readline()):
            assert line, "the editor ended before serving"
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=30) == 130
    finally:
        process.kill()
        process.wait()
