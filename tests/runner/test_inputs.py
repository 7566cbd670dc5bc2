"""Pipeline inputs that change while a run reads them (a clip renamed over, a pack or photo
folder edited): the run fails with one line and stores nothing under the old digest, so a run
on the original afterwards publishes the original's outputs; a folder holding a file name that
is not UTF-8 is hashed (by the name's bytes) instead of failing."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import textwrap
from pathlib import Path

import numpy as np
import pytest

from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.digest import tree_digest
from runner.execute import Options, Runner, StageFailed
from runner.registry import Registry
from stages.pack.stage import LoadPack
from stages.packbuild.photos import PhotosDecode
from stages.video import ImageGray, VideoDecode, WriteVideo
from tests.runner.helpers import REPO, tree_bytes

CLIPS = REPO / "fixtures" / "clips"
PACK = REPO / "fixtures" / "packs" / "target"
REGISTRY = Registry(classes=[VideoDecode, ImageGray, WriteVideo, PhotosDecode, LoadPack])

VIDEO = """
chunk_frames: 8
inputs: {clip: {type: video}}
stages:
  decode: {uses: video.decode, inputs: {video: clip}}
  gray: {uses: image.gray, inputs: {frames: decode.frames}}
  video: {uses: write.video, params: {codec: ffv1}, inputs: {frames: gray.frames}}
"""
PHOTOS = (
    VIDEO.replace("chunk_frames: 8", "chunk_frames: 2")
    .replace("clip: {type: video}", "photos: {type: dir}")
    .replace("video.decode, inputs: {video: clip}", "photos.decode, inputs: {photos: photos}")
)
PACK_LOAD = """
inputs: {pack: {type: dir}}
stages:
  load: {uses: pack.load, inputs: {pack: pack}}
"""


def run(tmp_path: Path, text: str, named: dict[str, Path], *, cache: Path, out: Path, on_event=None) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(text))
    pipeline = load_pipeline(path, REGISTRY)
    options = Options(cache=CacheStore(cache), out=out, log=on_event or (lambda event: None))
    Runner(pipeline, bind_inputs(pipeline, clip=None, named=[f"{k}={v}" for k, v in named.items()]), options).run()


def entry_count(cache: Path) -> int:
    return len(list(CacheStore(cache).iter_entries()))


def once(condition, action):
    """A log callback running ``action`` at the first event for which ``condition`` holds."""
    done = []

    def on_event(event: dict) -> None:
        if not done and condition(event):
            done.append(event)
            action()

    return on_event


def first_chunk_of(stage: str):
    return lambda event: event.get("event") == "chunk" and event.get("stage") == stage and event.get("status") == "ran"


def test_clip_replaced_while_read_fails_the_run_and_poisons_nothing(tmp_path):
    """The clip is renamed over by another clip of the same size and length after the first
    chunk is committed: the run fails naming the input; put back, the next run on the same cache
    publishes the original's frames, byte for byte those of a clean run."""
    clip, other = tmp_path / "clip.mp4", tmp_path / "other.mp4"
    shutil.copy(CLIPS / "calm.mp4", clip)
    shutil.copy(CLIPS / "live.mp4", other)
    cache = tmp_path / "cache"
    with pytest.raises(StageFailed) as info:
        run(
            tmp_path,
            VIDEO,
            {"clip": clip},
            cache=cache,
            out=tmp_path / "out",
            on_event=once(first_chunk_of("gray"), lambda: os.replace(other, clip)),
        )
    message = str(info.value)
    assert "input 'clip' changed while the run read it" in message and str(clip) in message and "\n" not in message
    shutil.copy(CLIPS / "calm.mp4", clip)  # the original back (a new inode)
    run(tmp_path, VIDEO, {"clip": clip}, cache=cache, out=tmp_path / "out")
    clean = tmp_path / "clean"
    run(tmp_path, VIDEO, {"clip": CLIPS / "calm.mp4"}, cache=clean / "cache", out=clean / "out")
    assert tree_bytes(tmp_path / "out" / "video") == tree_bytes(clean / "out" / "video")


def test_pack_edited_after_its_digest_fails_the_stage_and_stores_nothing(tmp_path):
    pack = tmp_path / "pack"
    shutil.copytree(PACK, pack)
    manifest = pack / "pack.yaml"
    original = manifest.read_text()
    cache = tmp_path / "cache"
    with pytest.raises(StageFailed) as info:
        run(
            tmp_path,
            PACK_LOAD,
            {"pack": pack},
            cache=cache,
            out=tmp_path / "out",
            on_event=once(
                lambda e: e.get("event") == "stage_start" and e.get("stage") == "load",
                lambda: manifest.write_text(original.replace("name: target", "name: edited")),
            ),
        )
    assert "input 'pack' changed while the run read it" in str(info.value) and "pack.yaml" in str(info.value)
    assert entry_count(cache) == 0


def test_photo_replaced_while_read_fails_the_run(tmp_path):
    """A photo folder whose third photo is replaced after the first chunk of two photos was
    committed: the run fails, and the rerun on the restored folder equals a clean run."""
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    import cv2

    originals = {}
    for k in range(6):
        image = rng.integers(0, 256, (40, 30, 3), dtype=np.uint8)
        cv2.imwrite(str(photos / f"p{k}.png"), image)
        originals[k] = (photos / f"p{k}.png").read_bytes()
    replacement = tmp_path / "replacement.png"
    cv2.imwrite(str(replacement), np.zeros((40, 30, 3), np.uint8))
    cache = tmp_path / "cache"
    with pytest.raises(StageFailed) as info:
        run(
            tmp_path,
            PHOTOS,
            {"photos": photos},
            cache=cache,
            out=tmp_path / "out",
            on_event=once(first_chunk_of("gray"), lambda: os.replace(replacement, photos / "p2.png")),
        )
    assert "input 'photos' changed while the run read it" in str(info.value) and "p2.png" in str(info.value)
    (photos / "p2.png").write_bytes(originals[2])
    run(tmp_path, PHOTOS, {"photos": photos}, cache=cache, out=tmp_path / "out")
    clean = tmp_path / "clean"
    shutil.copytree(photos, clean / "photos")
    run(tmp_path, PHOTOS, {"photos": clean / "photos"}, cache=clean / "cache", out=clean / "out")
    assert tree_bytes(tmp_path / "out" / "video") == tree_bytes(clean / "out" / "video")


def test_an_input_written_while_hashed_is_hashed_again(tmp_path, monkeypatch):
    """The digest is of the bytes the stat record describes: a file rewritten during its first
    hashing is hashed again."""
    from runner import inputs

    file = tmp_path / "init.csv"
    file.write_text("1,2,3")
    real = inputs.input_digest
    calls = []

    def digest_then_write(kind, path):
        calls.append(real(kind, path))
        if len(calls) == 1:
            file.write_text("4,5,6,7")
        return calls[-1]

    monkeypatch.setattr(inputs, "input_digest", digest_then_write)
    bound = inputs.BoundInput.read("init", "file", file)
    assert len(calls) == 2 and bound.digest == real("file", file) and bound.changed() is None


def test_file_name_that_is_not_utf8_is_hashed_by_its_bytes(tmp_path):
    """A Latin-1 file name in a folder input: the folder's digest covers the name's bytes (two
    such names differ), and a UTF-8 name keeps its text in the digest (entries stay valid)."""
    folder = tmp_path / "folder"
    folder.mkdir()
    latin1 = folder / os.fsdecode(b"caf\xe9.png")
    latin1.write_bytes(b"x")
    first = tree_digest(folder)
    latin1.rename(folder / os.fsdecode(b"caf\xe8.png"))
    assert tree_digest(folder) != first
    (folder / os.fsdecode(b"caf\xe8.png")).rename(folder / "café.png")
    document = json.dumps(
        [["café.png", hashlib.sha256(b"x").hexdigest()]], sort_keys=True, separators=(",", ":"), ensure_ascii=False
    )
    assert tree_digest(folder) == hashlib.sha256(document.encode()).hexdigest()


def test_pack_and_photo_folders_with_a_name_that_is_not_utf8_run(tmp_path):
    pack = tmp_path / "pack"
    shutil.copytree(PACK, pack)
    (pack / os.fsdecode(b"notes-\xe9t\xe9.txt")).write_text("a user's notes")
    run(tmp_path, PACK_LOAD, {"pack": pack}, cache=tmp_path / "cache", out=tmp_path / "out")
    photos = tmp_path / "photos"
    photos.mkdir()
    import cv2

    for k, name in enumerate([b"a.png", b"caf\xe9.png", b"z.png"]):
        (photos / os.fsdecode(name)).write_bytes(cv2.imencode(".png", np.full((20, 16, 3), 40 * k, np.uint8))[1].tobytes())
    run(tmp_path, PHOTOS, {"photos": photos}, cache=tmp_path / "cache", out=tmp_path / "out")
    import av

    with av.open(str(tmp_path / "out" / "video" / "video.mkv")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 3
