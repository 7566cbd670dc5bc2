"""The EXR writer's bytes are a function of the pixels and parameters only: the same frame gives
the same file whatever thread, stack, process or order writes it.

The regression case: ISA-L's level-1 deflate (the writer's deflater before zlib and zlib-ng) gave other,
equally valid bytes for some chunks when its stream state lay in certain 64 KiB windows of the
address space; python-isal keeps that state on the calling thread's C stack, so which thread of
which process wrote a frame could change its bytes (docs/writers.md, "Deterministic bytes").
``ODD_BLOCK`` is one such chunk, measured: 16 scanlines (240 px, RGBA half, two rows of a face's
edge) of ``bench.py batch``'s ``live_landmarks`` job, frame 33. With the state in the window
0x7ff48d1c0000..0x7ff48d1d0000, which a thread whose stack ends at ``ODD_STACK_TOPS`` reaches,
ISA-L gave 417 instead of 414 bytes for it; the test runs the writer on such threads.
"""

import base64
import ctypes
import io
import platform
import random
import subprocess
import sys
import threading
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from stages.writers.exr_file import ZIP_LEVEL, chunk_data, write_scanline_exr

REPO = Path(__file__).resolve().parents[3]
ODD_BLOCK = (  # zlib stream of the raw scanlines (16, 1920) uint8
    "eNrt1b1LAnEcx/HzOu9+9+h5KpI6hIieghwN4lou0hpOjUVQUSk5SC1tQbQ09bBJ0BxBRDQVUUtODTXVHBSFSy1B/Qutyvv1"
    "J7y/8P1IEgAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAP6naa+N1Qunfs8/97v+R6GTG89QZXhEpZtQ"
    "WW1p+9qdmNBftLZSCVFleKSlC3lLzOkbetL8NBXjUn3ivkOkJDWUZXPaWrDe7Vcna5/pwQhVBl89nc81fL1YK2bKoeAq6AXn"
    "QTdQg/XyYqlTOMzncxV2eID9SlXlR5sUCdE3+3bWiTgzEeEeOfP2ppkWq+q2MsWfHmAHoRNVNkYNxXi2a+6KO+u2oxVPRJPu"
    "l90yHkVMC8tUGlzX8p7+Zj1YO9axe+85sW9vKV5NFOO3XiratMNWytgdoh3+A3iHOHo="
)
ODD_LINES = (16, 1920)
ODD_STACK_TOPS = [0x7FF48D1D0000 + k * 0x4000 for k in range(12)]  # the old writer was odd on 4 of them


def _odd_lines() -> np.ndarray:
    return np.frombuffer(zlib.decompress(base64.b64decode(ODD_BLOCK)), np.uint8).reshape(ODD_LINES)


def _frame(seed: int, height: int = 70, width: int = 48) -> dict[str, np.ndarray]:
    """An RGBA half frame: zero rows above and below, a smooth blob with noise between."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    blob = np.exp(-(((y - height / 2) / (height / 4)) ** 2 + ((x - width / 2) / (width / 3)) ** 2))
    blob[blob < 0.2] = 0
    rgba = np.stack([blob * (0.3 + 0.2 * c) + blob * rng.random((height, width)) / 32 for c in range(3)] + [blob], axis=2).astype(
        np.float16
    )
    return {name: rgba[..., c] for c, name in enumerate("RGBA")}


def _file_bytes(channels: dict[str, np.ndarray]) -> bytes:
    out = io.BytesIO()
    write_scanline_exr(out, channels, attributes={"exmap:frame": 1}, compression="zip", level=ZIP_LEVEL)
    return out.getvalue()


def _run_on_stack(function, top: int, size: int = 4 << 20):
    """``function()`` on a new thread whose stack is the mapping ``[top - size, top)``; skips the
    test where that range is taken or the platform has no such call."""
    libc = ctypes.CDLL(None)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
    libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    libc.pthread_attr_setstack.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
    libc.pthread_create.argtypes = [ctypes.POINTER(ctypes.c_ulong), ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    libc.pthread_join.argtypes = [ctypes.c_ulong, ctypes.c_void_p]
    base = top - size
    prot_rw, private_anonymous, fixed_noreplace = 3, 0x22, 0x100000
    if libc.mmap(base, size, prot_rw, private_anonymous | fixed_noreplace, -1, 0) != base:
        pytest.skip(f"address range {base:#x}..{top:#x} is taken in this process")
    try:
        attr = ctypes.create_string_buffer(64)  # pthread_attr_t: 56 bytes on x86-64 glibc
        assert libc.pthread_attr_init(attr) == 0 and libc.pthread_attr_setstack(attr, base, size) == 0
        result = []

        def call(_: int | None) -> None:
            try:
                result.append(function())
            except BaseException as error:  # noqa: BLE001 - re-raised on the calling thread
                result.append(error)

        start = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)(call)
        thread = ctypes.c_ulong()
        assert libc.pthread_create(ctypes.byref(thread), attr, start, None) == 0
        libc.pthread_join(thread.value, None)
        libc.pthread_attr_destroy(attr)
    finally:
        libc.munmap(base, size)
    if isinstance(result[0], BaseException):
        raise result[0]
    return result[0]


@pytest.mark.skipif(sys.platform != "linux" or platform.machine() != "x86_64", reason="glibc x86-64 stacks")
def test_a_chunk_gets_the_same_bytes_on_threads_whose_stacks_isal_made_odd() -> None:
    """The measured case (module docstring): the chunk's data on the threads where ISA-L's state
    fell in the odd window equal the main thread's (with ISA-L 4 of the 12 did not)."""
    lines = _odd_lines()
    expected = [bytes(c) for c in chunk_data(lines, compression="zip", level=ZIP_LEVEL)]
    for top in ODD_STACK_TOPS:
        got = _run_on_stack(lambda: [bytes(c) for c in chunk_data(lines, compression="zip", level=ZIP_LEVEL)], top)
        assert got == expected, f"stack ending at {top:#x}"


def test_files_are_equal_across_repeats_threads_and_interleaved_frames() -> None:
    """Frames of two images written again, on 4 threads with stacks of other sizes, in shuffled
    order: every file equals the first, serial write of its frame."""
    frames = [_frame(1), _frame(2, 33, 17)]
    expected = [_file_bytes(f) for f in frames]
    assert expected[0] != expected[1]
    order = [i % 2 for i in range(16)]
    random.Random(3).shuffle(order)
    saved = threading.stack_size()
    try:
        for stack in (0, 1 << 20, (1 << 20) + 3 * 65536):
            threading.stack_size(stack)
            with ThreadPoolExecutor(4) as pool:
                got = list(pool.map(lambda i: _file_bytes(frames[i]), order))
            assert got == [expected[i] for i in order]
    finally:
        threading.stack_size(saved)


@pytest.mark.subprocess
def test_a_fresh_process_writes_the_same_bytes(tmp_path: Path) -> None:
    """The same frame written by a new interpreter (other addresses, other caches) is the same file,
    and OpenImageIO reads its half floats back bit for bit."""
    path = tmp_path / "child.exr"
    script = (
        "import sys; from pathlib import Path; from tests.stages.writers.test_exr_determinism import "
        "_file_bytes, _frame; Path(sys.argv[1]).write_bytes(_file_bytes(_frame(1)))"
    )
    subprocess.run([sys.executable, "-c", script, str(path)], cwd=REPO, check=True)
    assert path.read_bytes() == _file_bytes(_frame(1))
    inp = oiio.ImageInput.open(str(path))
    stored = inp.read_image(oiio.HALF)
    inp.close()
    rgba = np.stack([_frame(1)[name] for name in "RGBA"], axis=2)
    np.testing.assert_array_equal(stored.view(np.uint16), rgba.view(np.uint16))
