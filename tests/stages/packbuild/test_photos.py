"""photos.decode's pieces against independent truth: EXIF orientation (the EXIF 2.3 table applied with
numpy to the stored pixels; Pillow's exif_transpose as a second opinion), which files are frames and in
which order, unreadable files named and skipped, the frame-size rule and the letterbox's point map (a
dot's centroid), and the face-shape signature's invariance to a similarity."""

import logging

import numpy as np
import pytest
from PIL import Image, ImageOps

from runner.config import ConfigError, bind_inputs, load_pipeline
from runner.registry import Registry
from runner.stage import StageError
from stages.packbuild.identity import face_signature, majority_outliers, signature_distance
from stages.packbuild.photos import PhotosDecode, frame_size, letterbox, list_photos, photo_to_frame, read_photo, scan_photos
from tests.memory_stream import files_context

ORIENTATION_TAG = 0x0112
# EXIF 2.3, tag 274: how the stored pixels are turned for display (numpy, rows down).
UPRIGHT = {1: lambda a: a, 3: lambda a: np.rot90(a, 2), 6: lambda a: np.rot90(a, -1), 8: lambda a: np.rot90(a, 1)}


def asymmetric_image(h=40, w=60):
    """An image that no turn or flip maps onto itself: a gradient, a white top-left block, a red dot."""
    y, x = np.mgrid[:h, :w]
    image = np.stack([x * 4, y * 5, (x + y) * 2], axis=-1).astype(np.uint8)
    image[:8, :12] = 255
    image[h - 6 : h - 3, w - 9 : w - 5] = (255, 0, 0)
    return image


def save(path, pixels, *, orientation=None, **options):
    """Write ``pixels`` (RGB) with Pillow, with the EXIF Orientation tag when given."""
    image = Image.fromarray(pixels)
    if orientation is not None:
        exif = Image.Exif()
        exif[ORIENTATION_TAG] = orientation
        options["exif"] = exif.tobytes()
    image.save(path, **options)


@pytest.mark.parametrize("suffix", [".png", ".tif", ".webp"])
@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_lossless_photos_come_out_upright(tmp_path, suffix, orientation):
    stored = asymmetric_image()
    path = tmp_path / f"photo{suffix}"
    save(path, stored, orientation=orientation, **({"lossless": True} if suffix == ".webp" else {}))
    got = read_photo(path)
    np.testing.assert_array_equal(got, UPRIGHT[orientation](stored))
    np.testing.assert_array_equal(got, np.asarray(ImageOps.exif_transpose(Image.open(path)).convert("RGB")))


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_jpeg_photos_come_out_upright(tmp_path, orientation):
    import cv2

    path = tmp_path / "photo.JPG"
    save(path, asymmetric_image(), orientation=orientation, quality=95)
    as_stored = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)[..., ::-1]
    got = read_photo(path)
    np.testing.assert_array_equal(got, UPRIGHT[orientation](as_stored))
    assert got.shape[:2] == ((60, 40) if orientation in (6, 8) else (40, 60))


def test_frames_are_the_image_files_sorted_by_name(tmp_path):
    for name in ("b.png", "A.jpeg", "c.TIFF", "a10.webp", "a9.JPG"):
        (tmp_path / name).touch()
    for ignored in ("notes.txt", ".hidden.jpg", "clip.mp4", "raw.cr2"):
        (tmp_path / ignored).touch()
    (tmp_path / "sub.png").mkdir()
    assert [p.name for p in list_photos(tmp_path)] == ["A.jpeg", "a10.webp", "a9.JPG", "b.png", "c.TIFF"]
    with pytest.raises(ValueError, match="not a folder"):
        list_photos(tmp_path / "b.png")


def test_a_photo_that_is_not_a_regular_file_is_refused_before_the_run(tmp_path):
    """A link to /dev/zero among the photos: the folder is refused in one line naming the file
    and what it is, when the inputs are bound (never read, never skipped silently)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    save(photos / "a.png", asymmetric_image())
    (photos / "z.jpg").symlink_to("/dev/zero")
    with pytest.raises(ValueError, match=rf"^{photos / 'z.jpg'}: a character device, not a regular file$"):
        list_photos(photos)
    pipeline = tmp_path / "p.yaml"
    pipeline.write_text("inputs: {photos: {type: dir}}\nstages:\n  decode: {uses: photos.decode, inputs: {photos: photos}}\n")
    loaded = load_pipeline(pipeline, Registry(classes=[PhotosDecode]))
    with pytest.raises(ConfigError) as info:
        bind_inputs(loaded, clip=photos, named=[])
    assert str(info.value) == (
        f"{pipeline}:1:10: inputs.photos: wrong input: {photos / 'z.jpg'}: a character device, not a regular file"
    )
    (photos / "z.jpg").unlink()
    assert bind_inputs(loaded, clip=photos, named=[]) == {"photos": photos}


def test_unreadable_files_are_named_and_skipped(tmp_path, caplog):
    save(tmp_path / "1.png", asymmetric_image())
    (tmp_path / "2.jpg").write_bytes(b"\xff\xd8 not a jpeg at all")
    (tmp_path / "3.png").write_bytes(b"")
    save(tmp_path / "4.jpg", asymmetric_image(), quality=90)
    (tmp_path / "5.txt").write_text("ignored, not named")
    stage = PhotosDecode()
    with caplog.at_level(logging.WARNING):
        info = stage.stream_info({"photos": tmp_path}, {"max_side": 1920})
    assert (info.frames, info.width, info.height, info.fps) == (2, 60, 40, 1.0)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "2 unreadable image files skipped: 2.jpg, 3.png" in warnings[0]
    frames = stage.process(0, 2, {"photos": tmp_path}, {"max_side": 1920}, files_context(tmp_path))["frames"]
    assert frames.shape == (2, 40, 60, 3) and frames.dtype == np.uint8
    np.testing.assert_array_equal(frames[0], asymmetric_image())


def test_a_folder_without_a_readable_photo_is_an_error(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(StageError, match=r"photos\.decode: input 'photos': .*no photos in it \(looked for \.jpg"):
        PhotosDecode().stream_info({"photos": tmp_path}, {"max_side": 1920})
    (tmp_path / "a.jpg").write_bytes(b"broken")
    with pytest.raises(StageError, match=r"none of its 1 image files could be read \(a\.jpg\)"):
        PhotosDecode().stream_info({"photos": tmp_path}, {"max_side": 1920})


def test_frame_size_is_the_largest_width_and_height_capped():
    assert frame_size([(60, 40), (30, 50)], max_side=1920) == (60, 50)
    assert frame_size([(4032, 3024), (3024, 4032)], max_side=1920) == (1920, 1920)
    assert frame_size([(4000, 3000)], max_side=1000) == (1000, 750)
    with pytest.raises(ValueError, match="at least one photo"):
        frame_size([], max_side=100)


@pytest.mark.parametrize("size, frame", [((200, 100), (300, 300)), ((90, 120), (60, 60)), ((64, 48), (64, 48))])
def test_letterbox_maps_photo_points_as_photo_to_frame_says(size, frame):
    w, h = size
    y, x = np.mgrid[:h, :w]
    dot = np.array([0.3 * w, 0.7 * h])
    image = np.exp(-((x - dot[0]) ** 2 + (y - dot[1]) ** 2) / (2 * (0.05 * w) ** 2))
    rgb = np.repeat((image * 255).round().astype(np.uint8)[..., None], 3, axis=2)
    boxed = letterbox(rgb, frame)
    assert boxed.shape == (frame[1], frame[0], 3)
    sx, sy, tx, ty = photo_to_frame(size, frame)
    weight = boxed[..., 0].astype(float)
    weight[weight < 20] = 0  # the replicated border carries no dot
    fy, fx = np.mgrid[: frame[1], : frame[0]]
    centroid = np.array([(weight * fx).sum(), (weight * fy).sum()]) / weight.sum()
    np.testing.assert_allclose(centroid, [sx * dot[0] + tx, sy * dot[1] + ty], atol=0.05 * max(sx, 1) + 0.1)
    assert abs(sx - sy) < 0.02 and min(frame[0] - sx * w, frame[1] - sy * h) < 1  # uniform, fills one side


def test_letterbox_replicates_the_edges_and_leaves_a_fitting_photo_alone():
    rgb = asymmetric_image()
    assert letterbox(rgb, (60, 40)) is rgb
    boxed = letterbox(rgb, (60, 50))  # 5 rows above and below
    np.testing.assert_array_equal(boxed[5:45], rgb)
    np.testing.assert_array_equal(boxed[:5], np.broadcast_to(rgb[0], (5, 60, 3)))
    np.testing.assert_array_equal(boxed[45:], np.broadcast_to(rgb[-1], (5, 60, 3)))


def test_scan_sizes_are_upright(tmp_path):
    save(tmp_path / "a.jpg", asymmetric_image(), orientation=6)
    save(tmp_path / "b.png", asymmetric_image(30, 30))
    photos = scan_photos(tmp_path, max_side=1920)
    assert photos.sizes == ((40, 60), (30, 30)) and photos.frame_size == (40, 60) and not photos.unreadable


def test_a_folder_is_decoded_once_while_unchanged(tmp_path, monkeypatch):
    """photos.decode and photos.identity both scan the folder: the second scan decodes nothing,
    a photo changed in place is decoded again."""
    from stages.packbuild import photos as module

    save(tmp_path / "a.jpg", asymmetric_image())
    save(tmp_path / "b.png", asymmetric_image(30, 30))
    decoded = []
    monkeypatch.setattr(module, "read_photo", lambda path, read=module.read_photo: decoded.append(path.name) or read(path))
    first = scan_photos(tmp_path, max_side=1920)
    assert scan_photos(tmp_path, max_side=64).sizes == first.sizes and sorted(decoded) == ["a.jpg", "b.png"]
    save(tmp_path / "b.png", asymmetric_image(20, 30))  # changed in place: another size
    assert scan_photos(tmp_path, max_side=1920).sizes == ((60, 40), (30, 20))  # (width, height)
    assert sorted(decoded) == ["a.jpg", "a.jpg", "b.png", "b.png"]


def test_signature_ignores_a_similarity_and_sees_other_proportions():
    rng = np.random.default_rng(1)
    mesh = rng.normal(size=(478, 3)) * 50
    angle = np.radians(25)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = 1.7 * mesh @ rotation.T + [300, -20, 7]
    squeezed = mesh * [0.8, 1, 1]
    meshes = np.stack([mesh, moved, squeezed])
    signatures = face_signature(meshes[..., :2], meshes[..., 2])
    assert signature_distance(signatures[1:2], signatures[0])[0] < 1e-12
    assert signature_distance(signatures[2:3], signatures[0])[0] > 0.03
    with pytest.raises(ValueError, match="expected xy"):
        face_signature(meshes[..., :2], meshes[:, :5, 2])


def test_the_majority_names_the_minority():
    rng = np.random.default_rng(2)
    majority = 1 + rng.normal(scale=0.005, size=(7, 78))
    other = 1.05 + rng.normal(scale=0.005, size=(2, 78))
    signatures = np.concatenate([majority[:3], other[:1], majority[3:], other[1:], np.full((1, 78), np.nan)])
    distance, differs = majority_outliers(signatures, threshold=0.03)
    assert differs.tolist() == [False] * 3 + [True] + [False] * 4 + [True, False]
    assert np.isnan(distance[-1])


def test_a_photo_beyond_the_pixel_limit_is_skipped_undecoded(tmp_path, caplog, monkeypatch):
    """A 12000x12000 PNG (144 MP, a few kB) among two photos: skipped from its header with one
    warning line saying its size, never decoded; the others are the frames."""
    import cv2

    from tests.stages.image_files import big_png

    save(tmp_path / "a.png", asymmetric_image())
    big_png(tmp_path / "b.png", 12000, 12000)
    save(tmp_path / "c.png", asymmetric_image())
    decoded = []
    real = cv2.imdecode
    monkeypatch.setattr(cv2, "imdecode", lambda data, flags: decoded.append(data.size) or real(data, flags))
    with caplog.at_level(logging.WARNING):
        info = PhotosDecode().stream_info({"photos": tmp_path}, {"max_side": 1920})
    assert (info.frames, info.width, info.height) == (2, 60, 40)
    assert len(decoded) == 2 and (tmp_path / "b.png").stat().st_size not in decoded
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert (
        len(warnings) == 1 and "1 image files of more than 100000000 px skipped undecoded: b.png (12000x12000 px)" in warnings[0]
    )


def test_skipped_photos_are_counted_and_the_first_five_named(tmp_path, caplog):
    save(tmp_path / "a.png", asymmetric_image())
    for k in range(40):
        (tmp_path / f"broken{k:02d}.jpg").write_bytes(b"not a jpeg")
    with caplog.at_level(logging.WARNING):
        PhotosDecode().stream_info({"photos": tmp_path}, {"max_side": 1920})
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and warnings[0].endswith(
        "40 unreadable image files skipped: broken00.jpg, broken01.jpg, broken02.jpg, broken03.jpg, broken04.jpg and 35 more"
    )


def test_a_damaged_png_is_skipped_without_libpng_printing(tmp_path, capfd):
    """A PNG whose data chunk is damaged: skipped as unreadable, found by its chunks' check
    before OpenCV decodes it (libpng prints its own `libpng error:` line on stderr)."""
    import cv2

    save(tmp_path / "a.png", asymmetric_image())
    data = bytearray(cv2.imencode(".png", asymmetric_image())[1].tobytes())
    data[60:70] = bytes(10)  # inside IDAT
    (tmp_path / "b.png").write_bytes(bytes(data))
    photos = scan_photos(tmp_path, max_side=1920)
    assert [p.name for p in photos.paths] == ["a.png"] and [p.name for p in photos.unreadable] == ["b.png"]
    assert "libpng" not in capfd.readouterr().err
