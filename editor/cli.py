"""``expression-editor``: start the editor's local web server and print its URL.

    expression-editor --pack PACK [--performance RUN/data/data.npz] [--host 127.0.0.1]
                      [--port 0] [--device cpu] [--threads 1] [--processes 2] [--jpeg-quality 90]
                      [--preview-scale 1] [--allow-remote]

The URL carries a random token made for this run; the server answers no request without it.
It binds to 127.0.0.1 unless ``--host`` names another address, which also needs
``--allow-remote`` (and prints a warning: anyone who can reach the port and learns the URL can
use the editor). ``--port 0`` picks a free port.
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import logging
import os
import re
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from aiohttp import web

from runner.stage import StageError

if TYPE_CHECKING:
    from editor.engine import EditorEngine


def is_loopback(host: str) -> bool:
    """True for a loopback address or ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="expression-editor", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--pack", type=Path, required=True, help="the target's actor pack (folder with pack.yaml)")
    parser.add_argument(
        "--performance", type=Path, help="a run's data/data.npz whose frames (target_xy) can be loaded and touched up"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=0, help="port (default 0: any free port)")
    parser.add_argument("--allow-remote", action="store_true", help="allow a --host that is not a loopback address")
    parser.add_argument("--device", default="cpu", help="torch device of the synthesis (cpu, cuda)")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch/OpenCV threads of the synthesis (default 1; more needs --processes 0, see docs/editor.md)",
    )
    parser.add_argument(
        "--processes",
        type=int,
        default=2,
        choices=range(0, 9),
        metavar="0..8",
        help="renderer processes (default 2; 0: render on the server's threads, sharing the GIL; see docs/editor.md)",
    )
    parser.add_argument(
        "--jpeg-quality",
        type=int,
        default=90,
        choices=range(1, 101),
        metavar="1..100",
        help="quality of the JPEG images sent to the page (while dragging, in-betweens); when the mouse stops the image is PNG",
    )
    parser.add_argument(
        "--preview-scale",
        type=float,
        default=1.0,
        help="size of the images shown while dragging, fraction of the pack's image size, in (0, 1] (default 1: the pack's size; see docs/editor.md)",
    )
    return parser.parse_args(argv)


async def serve(args: argparse.Namespace, engine: EditorEngine) -> None:
    from editor.server import make_app

    token = secrets.token_urlsafe(24)
    runner = web.AppRunner(make_app(engine, token=token, processes=args.processes), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, args.host, args.port)
    await site.start()
    port = runner.addresses[0][1]
    shown = f"[{args.host}]" if ":" in args.host else args.host
    print(f"expression editor: http://{shown}:{port}/?token={token}", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()


def main(argv: list[str] | None = None) -> int:
    """The command; exit 0, 1 (the server failed), 2 (a bad command line, ``--pack`` or
    ``--performance``), 130 (interrupted: SIGINT, also when the process was started in the
    background of a script, which starts it with SIGINT ignored)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if not is_loopback(args.host):
        if not args.allow_remote:
            print(
                f"expression-editor: --host {args.host} is not a loopback address; add --allow-remote to bind it", file=sys.stderr
            )
            return 2
        print(
            f"WARNING: binding {args.host}: anyone who can reach this port and learns the URL (its token) can use the editor",
            file=sys.stderr,
            flush=True,
        )
    if not (args.pack / "pack.yaml").is_file():
        print(f"expression-editor: --pack {args.pack}: no pack.yaml there", file=sys.stderr)
        return 2
    import cv2
    import torch

    from editor.engine import EditorEngine

    torch.set_num_threads(max(args.threads, 1))
    cv2.setNumThreads(max(args.threads, 1))
    try:  # what --pack and --performance name: exit 2, as a bad command line
        engine = EditorEngine(
            args.pack,
            device=args.device,
            jpeg_quality=args.jpeg_quality,
            preview_scale=args.preview_scale,
            performance=args.performance,
        )
    except (ValueError, OSError, StageError) as exc:
        print(f"expression-editor: {exc}", file=sys.stderr)
        return 2
    try:
        asyncio.run(serve(args, engine))
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError, StageError) as exc:
        print(f"expression-editor: {exc}", file=sys.stderr)
        return 1
    return 0


def spawn(pack: Path, *options: str, timeout_s: float = 300.0) -> tuple[subprocess.Popen, str]:
    """Start ``python -m editor.cli --pack PACK OPTIONS`` (tests, benchmarks) and return the
    process and the URL it printed (with its token). The process's stderr is discarded."""
    repo = Path(__file__).resolve().parent.parent
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")])))
    process = subprocess.Popen(
        [sys.executable, "-m", "editor.cli", "--pack", str(pack), *options],
        cwd=repo,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    deadline = time.monotonic() + timeout_s
    line = ""
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        match = re.search(r"http://\S+/\?token=\S+", line)
        if match:
            return process, match.group(0)
        if not line and process.poll() is not None:
            break
    process.kill()
    raise RuntimeError(f"the editor did not start (exit code {process.poll()}, last line {line!r})")


if __name__ == "__main__":
    raise SystemExit(main())
