"""pack_build_photos.yaml through the runner.

A folder made from the real-texture clip (fixtures/realface/astro.mp4, 48 frames with the true mesh per
frame): most frames as PNG, some as JPEG stored turned with an EXIF Orientation tag (3, 6, 8), one wider
photo and one smaller one (so the frames are letterboxed): the published pack loads and its points agree
with the true points carried into the frames and the pack, within the video builder's tolerance; adding
a photo re-runs the graph. And a folder of the astronaut photo moved by similarities with two faces of
other proportions among them: the identity warning names those two.
"""

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from runner.cache import CacheStore
from runner.config import ConfigError, bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.plan import make_plan
from runner.registry import Registry
from stages.actor_pack import load_pack
from stages.geometry.compensate import apply_similarity
from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
from stages.landmarks.stage import FaceLandmarks, LayoutPoints
from stages.layout import load_layout
from stages.packbuild.photos import PhotoIdentity, PhotosDecode, photo_to_frame
from stages.packbuild.stage import PackFilter, PackSelect, PackWrite
from stages.video import VideoDecode
from tests.memory_stream import files_context

REPO = Path(__file__).resolve().parents[3]
CLIP = REPO / "fixtures" / "realface" / "astro.mp4"
TOLERANCE_MEAN_PX = 6.0  # tests/stages/packbuild/test_build.py's, for the same clip from video
TOLERANCE_EYES_PX = 3.0
STORED_TURNED = {1: (6, 1), 3: (3, 2), 5: (8, -1)}  # frame % 8 -> (EXIF orientation, np.rot90 k of the stored pixels)
WIDE, SMALL = 6, 10  # a 640x512 photo (the clip's frame padded), a 384x384 one (the frame shrunk)


def registry():
    return Registry(
        classes=[PhotosDecode, PhotoIdentity, VideoDecode, FaceLandmarks, LayoutPoints, PackFilter, PackSelect, PackWrite]
    )


def test_in_binds_the_photo_folder_and_a_folder_is_not_a_clip(tmp_path):
    photos = load_pipeline(REPO / "pack_build_photos.yaml", registry())
    assert bind_inputs(photos, clip=tmp_path, named=[]) == {"photos": tmp_path}
    video = load_pipeline(REPO / "pack_build.yaml", registry())
    with pytest.raises(ConfigError, match=rf"inputs\.clip: wrong input: {tmp_path}: a folder, not a file"):
        bind_inputs(video, clip=tmp_path, named=[])


def save_jpeg(path, rgb, *, orientation=None):
    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    Image.fromarray(rgb).save(path, quality=95, exif=exif.tobytes())


def run(folder, tmp, **options):
    pipeline = load_pipeline(REPO / "pack_build_photos.yaml", registry(), overrides=["select.pose_deg=30"])
    runner = Runner(
        pipeline,
        bind_inputs(pipeline, clip=folder, named=[]),  # --in FOLDER
        Options(cache=CacheStore(tmp / "cache"), out=tmp / "out", **options),
    )
    return runner, runner.run()


def plan(folder, tmp):
    """The dry run's report per stage (:func:`runner.plan.make_plan`) for the photos in ``folder``."""
    pipeline = load_pipeline(REPO / "pack_build_photos.yaml", registry(), overrides=["select.pose_deg=30"])
    tasks = make_plan(pipeline, bind_inputs(pipeline, clip=folder, named=[]), cache=CacheStore(tmp / "cache"), device="cpu")
    return [task.report() for task in tasks]


@pytest.fixture(scope="module")
def clip_folder(tmp_path_factory):
    """The clip's frames as photos ``f000.*``..``f047.*``, and each photo's upright size."""
    folder = tmp_path_factory.mktemp("photos")
    decode = VideoDecode()
    frames = decode.process(0, 48, {"video": CLIP}, {}, files_context(folder))["frames"]
    sizes = []
    for t, frame in enumerate(frames):
        if t == WIDE:
            frame = cv2.copyMakeBorder(frame, 0, 0, 64, 64, cv2.BORDER_REPLICATE)
        elif t == SMALL:
            frame = cv2.resize(frame, (384, 384), interpolation=cv2.INTER_AREA)
        sizes.append((frame.shape[1], frame.shape[0]))
        if t % 8 in STORED_TURNED and t not in (WIDE, SMALL):
            orientation, k = STORED_TURNED[t % 8]
            save_jpeg(folder / f"f{t:03d}.jpg", np.ascontiguousarray(np.rot90(frame, k)), orientation=orientation)
        else:
            cv2.imwrite(str(folder / f"f{t:03d}.png"), frame[..., ::-1])
    (folder / "README.txt").write_text("not a photo")
    return folder, sizes


@pytest.fixture(scope="module")
def built(clip_folder, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pack_build_photos")
    runner, _ = run(clip_folder[0], tmp)
    return tmp, runner


def true_frame_points(sizes):
    """The clip's true layout points carried into each photo's frame: ``(48, 134, 2)`` px."""
    with np.load(CLIP.with_name("astro_truth.npz"), allow_pickle=False) as truth:
        mesh = truth["points"]
    layout = load_layout("zhang134")
    xy = layout_from_mesh(mesh, load_correspondence("zhang134_mediapipe", layout=layout))
    frame = (640, 512)
    out = []
    for t, points in enumerate(xy):
        if t == WIDE:
            points = points + [64, 0]
        elif t == SMALL:  # cv2.resize by 0.75: pixel centres (x + 0.5) * 0.75 - 0.5
            points = (points + 0.5) * 0.75 - 0.5
        sx, sy, tx, ty = photo_to_frame(sizes[t], frame)
        out.append(points * [sx, sy] + [tx, ty])
    return np.stack(out)


def test_the_pack_from_photos_agrees_with_the_truth(built, clip_folder):
    tmp, runner = built
    pack = load_pack(tmp / "out" / "pack")
    selection = runner.values[("select", "selection")].get()
    assert pack.image_size == (384, 512) and len(pack.examples) == 12
    size = runner.values[("landmarks", "landmarks")].get()["size"]
    assert size.tolist() == [640, 512]
    true_xy = true_frame_points(clip_folder[1])
    chosen = [selection["neutral"], selection["standard"], *selection["examples"]]
    errors = []
    for expression, t in zip([pack.neutral, pack.standard, *pack.examples], chosen):
        params = selection["to_pack"][int(t)]
        errors.append(
            np.linalg.norm(expression.points - apply_similarity(params, true_xy[int(t)]), axis=-1)
            / np.hypot(params[0], params[1])
        )
    errors = np.stack(errors)  # frame pixels, (chosen, 134)
    layout = load_layout("zhang134")
    eyes = [layout.index(f"eye_{s}_{k}") for s in "lr" for k in range(12)]
    assert errors.mean() < TOLERANCE_MEAN_PX
    assert errors[:, eyes].mean() < TOLERANCE_EYES_PX
    # every photo's points, the turned, wide and small ones included, where the truth says (frame px)
    points = runner.values[("points", "points")].get()
    assert points["valid"].all()
    per_photo = np.linalg.norm(points["xy"] - true_xy, axis=-1)[:, eyes].mean(axis=1)
    assert per_photo.max() < TOLERANCE_EYES_PX, per_photo.round(1)


def test_identity_names_the_photos_in_frame_order(built, clip_folder):
    _, runner = built
    identity = runner.values[("identity", "identity")].get()
    assert identity["names"].tolist() == sorted(p.name for p in clip_folder[0].iterdir() if p.suffix != ".txt")
    assert identity["distance"].shape == (48,) and np.isfinite(identity["distance"]).all()


def test_adding_a_photo_reruns_the_graph(built, clip_folder, tmp_path):
    tmp, _ = built
    folder = tmp_path / "photos"
    folder.mkdir()
    for photo in clip_folder[0].iterdir():
        (folder / photo.name).symlink_to(photo)
    stages = ("landmarks", "identity", "filter", "select", "pack")
    reports = plan(folder, tmp)  # same bytes, another folder: cached
    assert {r.stage: r.status for r in reports if r.stage in stages} == dict.fromkeys(stages, "cached")
    (folder / "f048.png").symlink_to(clip_folder[0] / "f000.png")
    reports = plan(folder, tmp)
    status = {r.stage: r.status for r in reports}
    assert status["landmarks"] == "will run" and status["identity"] in ("will run", "may run")


def astronaut_variants():
    """The astronaut photo under five similarities, and two faces of other proportions (x 0.8 wide;
    x 0.85 wide and x 1.1 high, about the face)."""
    from skimage.data import astronaut

    rgb = astronaut()

    def similarity(angle, scale, shift):
        m = cv2.getRotationMatrix2D((256, 256), angle, scale)
        m[:, 2] += shift
        return cv2.warpAffine(rgb, m, (512, 512), borderMode=cv2.BORDER_REPLICATE)

    def proportions(sx, sy):
        m = np.array([[sx, 0, (1 - sx) * 220], [0, sy, (1 - sy) * 130]])
        return cv2.warpAffine(rgb, m, (512, 512), borderMode=cv2.BORDER_REPLICATE)

    same = [
        rgb,
        similarity(8, 1, (0, 0)),
        similarity(-6, 0.8, (20, 10)),
        similarity(0, 1.2, (-30, 20)),
        similarity(4, 0.9, (10, -10)),
    ]
    return same, [proportions(0.8, 1.0), proportions(0.85, 1.1)]


def test_photos_of_another_face_are_named(tmp_path, caplog):
    folder = tmp_path / "photos"
    folder.mkdir()
    same, other = astronaut_variants()
    names = ["a.png", "b.jpg", "c.png", "e.png", "g.png"]
    for name, rgb in zip(names, same):
        if name == "b.jpg":  # stored turned, EXIF 8
            save_jpeg(folder / name, np.ascontiguousarray(np.rot90(rgb, -1)), orientation=8)
        else:
            cv2.imwrite(str(folder / name), rgb[..., ::-1])
    cv2.imwrite(str(folder / "d.png"), other[0][..., ::-1])
    cv2.imwrite(str(folder / "f.png"), cv2.resize(other[1], (400, 400))[..., ::-1])  # and smaller
    (folder / "h.jpg").write_bytes(b"\xff\xd8\xff broken")
    with caplog.at_level(logging.WARNING):
        runner, _ = run(folder, tmp_path, until=("identity",))
    identity = runner.values[("identity", "identity")].get()
    assert identity["names"].tolist() == ["a.png", "b.jpg", "c.png", "d.png", "e.png", "f.png", "g.png"]
    assert identity["differs"].tolist() == [False, False, False, True, False, True, False]
    assert identity["distance"][~identity["differs"]].max() < 0.02
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    named = [w for w in warnings if "photos.identity" in w]
    assert len(named) == 1 and "2 of 7 faces may be another person's" in named[0]
    assert "d.png (frame 3," in named[0] and "f.png (frame 5," in named[0]
    assert sum("1 unreadable image files skipped: h.jpg" in w for w in warnings) == 1
