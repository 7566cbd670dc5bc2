"""The editor's web server (aiohttp): the page, and the JSON/binary API behind it.

Every request needs the per-run token (header ``X-Editor-Token`` or query ``token``); bodies
are bounded (``MAX_BODY`` bytes) and validated (:mod:`editor.validate`); every error is a JSON
``{"error": message}`` with a 4xx status (5xx for a fault of the server's own), and the server
keeps serving.

API (POST bodies are JSON)
--------------------------
``GET  /``                 the page (``editor/static/index.html``)
``GET  /static/NAME``      its script and style
``GET  /api/describe``     size, point names, neutral, subregion outlines, performance frames
``GET  /api/frame?index=K`` frame K's geometry of the ``--performance`` data.npz
``POST /api/render``       ``{client, seq, base, pinned, preview}`` -> propagated geometry + its
                           image: with ``preview: true`` (while dragging) a JPEG at
                           ``--preview-scale`` of the pack's size, 1 by default
                           (``EditorEngine.preview``), else the pipeline's synthesis at the
                           pack's size, lossless (PNG)
``POST /api/inbetweens``   ``{client, seq, from, to}`` -> the five in-between images (Sec. 14.2,
                           JPEG) and the image of ``to`` (PNG)
``POST /api/export``       ``{fps, keyframes: [{time_s, points}]}`` -> the points file (.npz), at
                           most ``MAX_EXPORT_FRAMES`` frames, built on a thread, one at a time,
                           and streamed; at most ``EXPORTS_PENDING`` exports held at once
                           (built or being sent), a further one answered 503 with Retry-After

Image answers are ``application/octet-stream``: a little-endian uint32 byte count, that many
bytes of UTF-8 JSON (``points``, ``seq``, ``work_ms``: wall-clock time of propagation,
synthesis and encoding, ``synth_ms`` and ``synth_cpu_ms``: wall-clock and CPU time of synthesis
and encoding, ``propagate_cpu_ms``: CPU time of the propagation,
``sizes``: the byte count of each image, ``types``: their MIME types), then the images back to
back. Stale work is dropped: a request whose ``seq`` is
older than the newest one seen from its ``client`` is answered 409 ``superseded`` without
being computed, also when a newer one arrives while it waits for a renderer.
Propagation, synthesis and encoding run in ``RENDERERS`` renderer processes
(:mod:`editor.renderers`; one torch thread each by default), so the work of two consecutive
requests overlaps on two cores without contending for the GIL.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import sys
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Awaitable, Callable

from aiohttp import web

from editor import validate
from editor.engine import EditorEngine
from editor.geometry import interpolate_keyframes
from stages.geometry.points_file import points_file_bytes
from editor.renderers import Renderers
from runner.notes import bounded

STATIC = Path(__file__).resolve().parent / "static"
MAX_BODY = 4 * 1024 * 1024  # bytes; an export of MAX_KEYFRAMES keyframes of 134 points fits
MAX_CLIENTS = 64  # clients whose newest sequence number is remembered
RENDERERS = 2  # renderer processes (and threads waiting on them): a page keeps up to this many requests in flight
TOKEN_HEADER = "X-Editor-Token"
log = logging.getLogger("editor.server")

ENGINE = web.AppKey("engine", EditorEngine)
TOKEN = web.AppKey("token", str)
NEWEST = web.AppKey("newest", OrderedDict)
EXECUTOR = web.AppKey("executor", ThreadPoolExecutor)
RENDERER = web.AppKey("renderer", Renderers)
EXPORTS = web.AppKey("exports", asyncio.Semaphore)
EXPORTS_AT_ONCE = 1  # exports built at once (each up to ~77 MB): the others wait their turn
PENDING = web.AppKey("pending", list)
EXPORTS_PENDING = 2  # exports held at once, from the request until the last byte is sent
EXPORT_RETRY_S = 5  # the Retry-After of an export refused while EXPORTS_PENDING are held
EXPORT_BLOCK = 1 << 20  # bytes of an export written at a time (each waits for the client to take them)


def json_error(status: int, message: str, headers: dict[str, str] | None = None) -> web.Response:
    """``{"error": message}`` with ``status``; the message on one line, cut at 400 characters
    (:func:`runner.notes.bounded`: a bad value is quoted, never echoed whole)."""
    return web.json_response({"error": bounded(message)}, status=status, headers={"Cache-Control": "no-store", **(headers or {})})


@web.middleware
async def guard(request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]) -> web.StreamResponse:
    """Token check, errors as JSON, no caching, a restrictive content policy."""
    token = request.app[TOKEN]
    given = request.headers.get(TOKEN_HEADER) or request.query.get("token", "")
    # a header's bytes that are not UTF-8 come as surrogate escapes: compared as the bytes sent
    if not hmac.compare_digest(given.encode("utf-8", "surrogateescape"), token.encode()):
        return json_error(403, "missing or wrong token")
    try:
        response = await handler(request)
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        return json_error(exc.status, exc.reason)
    except ValueError as exc:  # validation (json.JSONDecodeError is one)
        return json_error(400, str(exc))
    except Exception:  # a fault of ours: logged, answered, and the server goes on
        log.exception("error serving %s %s", request.method, request.path)
        return json_error(500, "internal error (see the server's log)")
    if not response.prepared:  # a streamed answer set its headers before its first byte
        _secure(response)
    return response


def _secure(response: web.StreamResponse) -> None:
    """The headers of every answer: no caching, no referrer, a restrictive content policy."""
    response.headers["Cache-Control"] = "no-store"
    response.headers["Referrer-Policy"] = "no-referrer"
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Content-Security-Policy"] = "default-src 'self'; img-src 'self' blob: data:; frame-ancestors 'none'"


async def read_json(request: web.Request) -> Any:
    """The request's JSON body; 413 past MAX_BODY (aiohttp's client_max_size), 415 if not JSON,
    400 if it does not parse (nested too deep for the parser included)."""
    if request.content_type != "application/json":
        raise web.HTTPUnsupportedMediaType(reason=f"expected Content-Type application/json, got {request.content_type!r}")
    text = await request.text()
    try:
        return json.loads(text, parse_int=_parse_int)
    except RecursionError:
        raise ValueError("the JSON body is nested too deeply") from None


def _parse_int(text: str) -> int:
    """An integer of a JSON body; one longer than Python converts (its digit limit) is a 400
    saying so, not Python's own message."""
    try:
        return int(text)
    except ValueError:
        limit = sys.get_int_max_str_digits()
        raise ValueError(f"an integer of {len(text)} characters in the JSON body: at most {limit} digits") from None


def claim(app: web.Application, client: str, seq: int) -> bool:
    """Record ``seq`` as ``client``'s newest request; False when a newer one was seen."""
    newest = app[NEWEST]
    if seq < newest.get(client, -1):
        return False
    newest[client] = seq
    newest.move_to_end(client)
    while len(newest) > MAX_CLIENTS:
        newest.popitem(last=False)
    return True


async def render_images(request: web.Request, client: str, seq: int, job: dict[str, Any]) -> web.Response:
    """The image answer of ``job`` (:mod:`editor.renderers`), made by a renderer, or 409
    ``superseded`` when a newer request of ``client`` arrived before the work started."""
    app = request.app

    def run() -> bytes | None:
        return app[RENDERER].run({**job, "seq": seq}) if app[NEWEST].get(client) == seq else None

    body = await asyncio.get_running_loop().run_in_executor(app[EXECUTOR], run)
    if body is None:
        return json_error(409, "superseded")
    return web.Response(body=body, content_type="application/octet-stream")


def _limit(engine: EditorEngine) -> float:
    return 4.0 * max(engine.size)


async def handle_render(request: web.Request) -> web.Response:
    engine = request.app[ENGINE]
    body = await read_json(request)
    client, seq = validate.sequence_number(body)
    base, pinned = validate.render_request(body, n_points=engine.pca.n_points, limit=_limit(engine))
    preview = validate.flag(body, "preview")
    if not claim(request.app, client, seq):
        return json_error(409, "superseded")
    job = {
        "op": "edit",
        "pinned": [[i, *map(float, xy)] for i, xy in pinned.items()],
        "preview": preview,
        "base": None if base is None else base.tolist(),
    }
    return await render_images(request, client, seq, job)


async def handle_inbetweens(request: web.Request) -> web.Response:
    engine = request.app[ENGINE]
    body = await read_json(request)
    client, seq = validate.sequence_number(body)
    previous, current = validate.inbetween_request(body, n_points=engine.pca.n_points, limit=_limit(engine))
    if not claim(request.app, client, seq):
        return json_error(409, "superseded")
    return await render_images(request, client, seq, {"op": "inbetweens", "from": previous.tolist(), "to": current.tolist()})


def export_bytes(engine: EditorEngine, body: Any) -> bytes:
    """The points file of an export request ``body`` (validated: at most
    :data:`editor.validate.MAX_EXPORT_FRAMES` frames)."""
    times, geometries, fps = validate.export_request(body, n_points=engine.pca.n_points, limit=_limit(engine))
    return points_file_bytes(interpolate_keyframes(times, geometries, fps=fps), engine.layout.point_names, fps=fps)


async def handle_export(request: web.Request) -> web.StreamResponse:
    """The export, validated and built on a thread (``EXPORTS`` at once), not the event loop:
    the other requests go on being answered meanwhile. Its bytes are held until the client
    has taken the last of them, so at most :data:`EXPORTS_PENDING` exports are held at once
    (a slow reader holds one); a further request is answered 503 with ``Retry-After``."""
    pending = request.app[PENDING]
    if len(pending) >= EXPORTS_PENDING:
        message = f"{EXPORTS_PENDING} exports are being built or sent: try again in {EXPORT_RETRY_S} s"
        return json_error(503, message, {"Retry-After": str(EXPORT_RETRY_S)})
    pending.append(request)
    try:
        body = await read_json(request)
        async with request.app[EXPORTS]:
            data = await asyncio.get_running_loop().run_in_executor(None, export_bytes, request.app[ENGINE], body)
        return await _send(request, data)
    finally:
        pending.remove(request)


async def _send(request: web.Request, data: bytes) -> web.StreamResponse:
    """Stream ``data`` as the export's download, :data:`EXPORT_BLOCK` bytes at a time, each
    write waiting until the client has taken enough of the previous ones; a client that goes
    away ends it."""
    response = web.StreamResponse(headers={"Content-Disposition": 'attachment; filename="keyframes.npz"'})
    response.content_type = "application/octet-stream"
    response.content_length = len(data)
    _secure(response)
    await response.prepare(request)
    view = memoryview(data)
    try:
        for start in range(0, len(data), EXPORT_BLOCK):
            await response.write(view[start : start + EXPORT_BLOCK])
        await response.write_eof()
    except ConnectionResetError:  # the client went away: its export is let go
        pass
    return response


async def handle_describe(request: web.Request) -> web.Response:
    return web.json_response(request.app[ENGINE].description())


async def handle_frame(request: web.Request) -> web.Response:
    performance = request.app[ENGINE].performance
    if performance is None:
        return json_error(404, "no performance loaded (start the editor with --performance RUN/data/data.npz)")
    text = request.query.get("index", "")
    if not text.isdigit() or int(text) >= len(performance):
        raise ValueError(f"query 'index': expected an integer in 0..{len(performance) - 1}, got {text!r}")
    return web.json_response({"index": int(text), "points": performance[int(text)].tolist()})


async def handle_index(request: web.Request) -> web.Response:
    page = (STATIC / "index.html").read_text(encoding="utf-8").replace("__TOKEN__", request.app[TOKEN])
    return web.Response(text=page, content_type="text/html")


async def _shutdown(app: web.Application) -> None:
    app[EXECUTOR].shutdown(wait=False, cancel_futures=True)
    app[RENDERER].close()


def make_app(engine: EditorEngine, *, token: str, processes: int = RENDERERS) -> web.Application:
    """The editor's application, serving ``engine`` to holders of ``token``; ``processes``
    renderer processes forked now (0: the renderer threads render, sharing the GIL)."""
    if len(token) < 16:
        raise ValueError(f"token must have at least 16 characters, got {len(token)}")
    app = web.Application(middlewares=[guard], client_max_size=MAX_BODY)
    app[ENGINE] = engine
    app[TOKEN] = token
    app[NEWEST] = OrderedDict()
    app[EXECUTOR] = ThreadPoolExecutor(max_workers=processes or RENDERERS, thread_name_prefix="editor-render")
    app[RENDERER] = Renderers(engine, processes=processes)
    app[EXPORTS] = asyncio.Semaphore(EXPORTS_AT_ONCE)
    app[PENDING] = []
    app.on_cleanup.append(_shutdown)
    app.router.add_get("/", handle_index)
    app.router.add_get("/api/describe", handle_describe)
    app.router.add_get("/api/frame", handle_frame)
    app.router.add_post("/api/render", handle_render)
    app.router.add_post("/api/inbetweens", handle_inbetweens)
    app.router.add_post("/api/export", handle_export)
    app.router.add_static("/static/", STATIC, show_index=False, follow_symlinks=False)
    return app
