"""The editor's renderers: propagation, synthesis and encoding of one request, in worker processes.

The convex-hull QP (eq. 2-5) and the motion propagation (Sec. 10.1) are hundreds of small torch
operations dispatched from Python, so two renderer *threads* of one process mostly wait for each
other on the GIL: measured on the 600x800 demo target, two threads made 9 images/s where one
made 12. Each renderer here is a process forked from the server once its engine is built (the
models are shared copy-on-write), fed over a pipe: a job goes as JSON, the answer comes back as
the image answer's bytes (``Connection.send_bytes`` / ``recv_bytes``: nothing is pickled). With
``processes=0`` the jobs run in the calling thread (one process, as before). The server must
run one torch thread when it forks them (``--threads 1``, the default): OpenMP's thread pool
does not survive ``fork``, and a parallel region in a renderer would wait for it forever.

A job is a JSON object:

``{"op": "edit", "seq", "pinned": [[i, x, y], ...], "base": null | (N, 2), "preview": bool}``
    the propagated geometry of the pinned points (:func:`editor.geometry.edited_geometry`) and
    its image: the preview (JPEG) with ``preview``, else the pipeline's synthesis (PNG);
``{"op": "inbetweens", "seq", "from": (N, 2), "to": (N, 2)}``
    the five in-between images (Sec. 14.2, JPEG) and the image of ``to`` (PNG).

Coordinates are px; JSON carries Python floats exactly (shortest round-trip repr), so a worker
renders the very geometry the server validated.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import queue
import signal
import struct
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import torch

from editor.engine import EditorEngine, Rendered
from editor.geometry import edited_geometry, inbetweens

__all__ = ["answer", "Renderers"]

log = logging.getLogger("editor.renderers")
OK, BAD_INPUT, FAULT = b"\x00", b"\x01", b"\x02"  # first byte of a worker's reply


def pack_images(meta: dict[str, Any], rendered: Rendered) -> bytes:
    """The binary image answer: a little-endian uint32 byte count, that many bytes of UTF-8 JSON
    (``meta`` with ``sizes`` and ``types`` of the images), then the images back to back."""
    header = json.dumps({**meta, "sizes": [len(i) for i in rendered.images], "types": rendered.types}).encode()
    return b"".join([struct.pack("<I", len(header)), header, *rendered.images])


def answer(engine: EditorEngine, job: dict[str, Any]) -> bytes:
    """The image answer (:func:`pack_images`) of one job (module docstring): the images, the last
    geometry (``points``), ``seq``, and the times ``work_ms`` (wall clock of the whole job),
    ``synth_ms`` / ``synth_cpu_ms`` (synthesis and encoding) and ``propagate_cpu_ms``."""
    wall, start = time.perf_counter(), time.thread_time()
    if job["op"] == "edit":
        pinned = {int(i): np.array([x, y], np.float64) for i, x, y in job["pinned"]}
        base = None if job["base"] is None else np.asarray(job["base"], np.float64)
        points = edited_geometry(engine.pca, pinned, base=base, propagate=engine.propagation)[None]
    elif job["op"] == "inbetweens":
        previous, current = (np.asarray(job[key], np.float64) for key in ("from", "to"))
        points = np.concatenate([inbetweens(previous, current), current[None]])
    else:
        raise ValueError(f"job 'op' must be 'edit' or 'inbetweens', got {job['op']!r}")
    propagate_cpu = time.thread_time() - start
    rendered = engine.preview(points[0]) if job.get("preview") else engine.render(points, lossless_last=True)
    meta = {
        "seq": job["seq"],
        "work_ms": (time.perf_counter() - wall) * 1e3,
        "propagate_cpu_ms": propagate_cpu * 1e3,
        "synth_ms": rendered.wall_s * 1e3,
        "synth_cpu_ms": rendered.cpu_s * 1e3,
        "points": points[-1].tolist(),
    }
    return pack_images(meta, rendered)


def _worker(engine: EditorEngine, conn: Connection, inherited: list[Connection]) -> None:
    """A renderer process: answer jobs from ``conn`` until the server closes it (or exits)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl+C stops the server, which closes the pipe
    for other in inherited:  # the server's ends: the pipe must reach EOF when the server goes
        other.close()
    while True:
        try:
            job = json.loads(conn.recv_bytes())
        except EOFError:
            return
        try:
            reply = OK + answer(engine, job)
        except ValueError as exc:
            reply = BAD_INPUT + str(exc).encode()
        except Exception as exc:  # noqa: BLE001 - a fault: reported to the server, which logs it and answers 500
            reply = FAULT + f"{type(exc).__name__}: {exc}".encode()
        conn.send_bytes(reply)


class Renderers:
    """``processes`` renderer processes forked with ``engine``, or none (jobs run in the caller).

    :meth:`run` is blocking and thread-safe: call it from up to ``processes`` threads at once
    (the server's renderer threads); each call takes an idle process for its job.

    Parameters
    ----------
    engine : EditorEngine
    processes : int
        Worker processes, >= 0 (0: :func:`answer` in the calling thread).
    timeout_s : float
        How long :meth:`run` waits for an idle process before giving up (RuntimeError).
    """

    def __init__(self, engine: EditorEngine, *, processes: int, timeout_s: float = 60.0) -> None:
        if not isinstance(processes, int) or processes < 0:
            raise ValueError(f"processes must be an integer >= 0, got {processes!r}")
        if processes and torch.get_num_threads() != 1:
            raise ValueError(
                f"renderer processes fork from a server with one torch thread (--threads 1), got {torch.get_num_threads()}"
            )
        self.engine = engine
        self.timeout_s = timeout_s
        self.idle: queue.SimpleQueue[Connection] = queue.SimpleQueue()
        self.ends: list[Connection] = []
        self.processes: list[multiprocessing.process.BaseProcess] = []
        context = multiprocessing.get_context("fork")  # the engine is shared, not sent
        for k in range(processes):
            ours, theirs = context.Pipe(duplex=True)
            self.ends.append(ours)
            process = context.Process(
                target=_worker, args=(engine, theirs, list(self.ends)), name=f"editor-render-{k}", daemon=True
            )
            process.start()
            theirs.close()
            self.processes.append(process)
            self.idle.put(ours)

    def run(self, job: dict[str, Any]) -> bytes:
        """The image answer of ``job`` (:func:`answer`). Raises ValueError for a job the
        renderer rejects, RuntimeError when a renderer process failed or none became idle."""
        if not self.processes:
            return answer(self.engine, job)
        try:
            conn = self.idle.get(timeout=self.timeout_s)
        except queue.Empty:
            raise RuntimeError(f"no renderer process became idle in {self.timeout_s} s") from None
        try:
            conn.send_bytes(json.dumps(job).encode())
            reply = conn.recv_bytes()
        except (EOFError, OSError) as exc:  # the process died: it is not used again
            raise RuntimeError(f"a renderer process exited ({exc!r})") from exc
        self.idle.put(conn)
        if reply[:1] == BAD_INPUT:
            raise ValueError(reply[1:].decode())
        if reply[:1] == FAULT:
            raise RuntimeError(f"renderer process: {reply[1:].decode()}")
        return reply[1:]

    def close(self) -> None:
        """Close the pipes (the processes exit at EOF) and wait for the processes."""
        for conn in self.ends:
            conn.close()
        for process in self.processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()
