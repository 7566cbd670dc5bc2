"""The renderer processes (editor/renderers.py): a job answered by a forked process is the job
answered in this thread and the pipeline's synthesis; bad jobs and faults come back as errors
and the process keeps serving; the processes exit when closed."""

from __future__ import annotations

import json
import struct
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

from editor.engine import EditorEngine
from editor.geometry import edited_geometry
from editor.renderers import Renderers, answer
from tests.editor.conftest import PACK, assert_is_pipeline_image, decode, synthesize_stage


def unpack(body: bytes) -> tuple[dict, list[bytes]]:
    (length,) = struct.unpack_from("<I", body)
    meta = json.loads(body[4 : 4 + length])
    offset, images = 4 + length, []
    for size in meta["sizes"]:
        images.append(body[offset : offset + size])
        offset += size
    assert offset == len(body)
    return meta, images


@pytest.fixture(scope="module")
def engine():
    return EditorEngine(PACK)


@pytest.fixture(scope="module")
def renderers(engine):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the editor's server: renderers fork from one torch thread
    pool = Renderers(engine, processes=2)
    yield pool
    pool.close()
    torch.set_num_threads(threads)


def edit_job(engine: EditorEngine, seq: int, dy: float, *, preview: bool = False) -> dict:
    index = engine.layout.point_names.index("mouth_outer_12")
    x, y = engine.pca.neutral[index]
    return {"op": "edit", "seq": seq, "pinned": [[index, float(x), float(y + dy)]], "base": None, "preview": preview}


def test_process_answer_is_the_thread_answer_and_the_pipeline_image(engine, renderers, pipeline):
    job = edit_job(engine, 7, 6.0)
    meta, images = unpack(renderers.run(job))
    local_meta, local_images = unpack(answer(engine, job))
    assert meta["seq"] == 7 and meta["types"] == ["image/png"]
    assert images == local_images
    index = job["pinned"][0][0]
    pinned = {index: np.array(job["pinned"][0][1:])}
    expected = edited_geometry(engine.pca, pinned, propagate=engine.propagation)
    np.testing.assert_array_equal(meta["points"], expected)
    np.testing.assert_array_equal(local_meta["points"], expected)
    np.testing.assert_allclose(expected, edited_geometry(engine.pca, pinned), rtol=0, atol=1e-9)  # the library's propagate_edit
    assert_is_pipeline_image(decode(images[0]), synthesize_stage(pipeline[0], expected[None])[0])


def test_inbetweens_and_previews_from_two_threads_at_once(engine, renderers):
    neutral = engine.pca.neutral
    moved = neutral + np.array([0.0, 3.0])
    jobs = [
        {"op": "inbetweens", "seq": 1, "from": neutral.tolist(), "to": moved.tolist()},
        edit_job(engine, 2, 4.0, preview=True),
    ]
    with ThreadPoolExecutor(2) as pool:
        answers = list(pool.map(renderers.run, jobs))
    (meta_in, images_in), (meta_pre, images_pre) = map(unpack, answers)
    assert meta_in["types"] == ["image/jpeg"] * 5 + ["image/png"] and len(images_in) == 6
    np.testing.assert_array_equal(meta_in["points"], moved)
    assert meta_pre["types"] == ["image/jpeg"] and images_pre == unpack(answer(engine, jobs[1]))[1]
    assert decode(images_pre[0]).shape[:2] == engine.previewer.size[::-1]


def test_bad_job_and_fault_are_errors_and_the_processes_go_on(engine, renderers):
    with pytest.raises(ValueError, match="'edit' or 'inbetweens'"):
        renderers.run({"op": "explode", "seq": 1})
    with pytest.raises(RuntimeError, match="renderer process: KeyError"):
        renderers.run({"op": "edit", "seq": 1})
    for seq in range(3):  # both processes still answer
        assert unpack(renderers.run(edit_job(engine, seq, 1.0, preview=True)))[0]["seq"] == seq


def test_no_processes_runs_in_the_caller_and_close_ends_the_processes(engine):
    job = edit_job(engine, 3, 2.0, preview=True)
    meta, images = unpack(Renderers(engine, processes=0).run(job))
    assert meta["seq"] == 3 and images == unpack(answer(engine, job))[1]
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with pytest.raises(ValueError, match="one torch thread"):
            Renderers(engine, processes=1)
        torch.set_num_threads(1)
        pool = Renderers(engine, processes=1)
    finally:
        torch.set_num_threads(threads)
    (process,) = pool.processes
    assert process.is_alive()
    pool.close()
    process.join(timeout=10)
    assert not process.is_alive() and process.exitcode == 0
    with pytest.raises(ValueError, match="integer >= 0"):
        Renderers(engine, processes=-1)
