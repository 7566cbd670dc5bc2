"""Actor packs load with their arrays intact; each kind of broken pack names the file and field."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from runner.depends import recording
from runner.stage import StageError
from stages.actor_pack import PackError, check_pack, load_pack
from stages.layout import LAYOUT_DIR, load_layout
from tests.stages.image_files import big_png, rgb_png

REPO = Path(__file__).resolve().parents[2]
W, H = 40, 30


def _write_points(path: Path, names, pts) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("name,x,y\n" + "".join(f"{n},{x},{y}\n" for n, (x, y) in zip(names, pts)))


def _make_pack(root: Path, rng: np.random.Generator) -> dict:
    """A tiny hand-made pack (random images and points) — independent of the fixture generator."""
    layout = load_layout("zhang134")
    names = layout.point_names
    n = layout.n_points
    truth = {}
    entries = []
    (root / "images").mkdir(parents=True)
    for key in ("neutral", "standard", "ex0", "ex1", "teeth0"):
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        cv2.imwrite(str(root / "images" / f"{key}.png"), img)
        pts = rng.uniform([0, 0], [W - 1, H - 1], (n, 2))
        order = rng.permutation(n)  # CSV rows in any order
        _write_points(root / "points" / f"{key}.csv", [names[i] for i in order], pts[order])
        truth[key] = (img[..., ::-1], pts)
        entries.append(f"{{name: {key}, image: images/{key}.png, points: points/{key}.csv}}")
    captured = rng.uniform([0, 0], [W - 1, H - 1], (3, n, 2))
    np.savez(root / "captured.npz", points=captured)
    model = rng.normal(size=(n, 3))
    (root / "model3d.csv").write_text("name,x,y,z\n" + "".join(f"{nm},{a},{b},{c}\n" for nm, (a, b, c) in zip(names, model)))
    (root / "pack.yaml").write_text(
        "format: actor-pack/1\nname: tiny\nlayout: zhang134\n"
        f"image_size: [{W}, {H}]\n"
        "intrinsics: [[50, 0, 19.5], [0, 50, 14.5], [0, 0, 1]]\n"
        "model3d: model3d.csv\n"
        f"neutral: {entries[0]}\nstandard: {entries[1]}\n"
        f"examples: [{entries[2]}, {entries[3]}]\nteeth_examples: [{entries[4]}]\n"
        "captured: captured.npz\n"
    )
    truth["captured"] = captured
    truth["model3d"] = model
    return truth


@pytest.fixture()
def pack_dir(tmp_path: Path):
    root = tmp_path / "pack"
    truth = _make_pack(root, np.random.default_rng(3))
    return root, truth


def test_loads_what_was_written(pack_dir):
    root, truth = pack_dir
    pack = load_pack(root)
    assert pack.name == "tiny" and pack.image_size == (W, H)
    np.testing.assert_array_equal(pack.neutral.image, truth["neutral"][0])  # RGB order
    np.testing.assert_allclose(pack.neutral.points, truth["neutral"][1], atol=1e-9)
    np.testing.assert_allclose(pack.examples[1].points, truth["ex1"][1], atol=1e-9)
    assert [e.name for e in pack.examples] == ["ex0", "ex1"]
    np.testing.assert_allclose(pack.captured_points, truth["captured"])
    np.testing.assert_allclose(pack.model3d, truth["model3d"], atol=1e-9)
    assert pack.intrinsics.shape == (3, 3) and pack.layout.n_points == 134
    assert load_pack(root / "pack.yaml").name == "tiny"


def _replace(path: Path, old: str, new: str) -> None:
    path.write_text(path.read_text().replace(old, new))


@pytest.mark.parametrize(
    "breakage, expect",
    [
        (lambda r: (r / "images" / "ex1.png").unlink(), ["pack.yaml", "examples[1].image", "file not found"]),
        (lambda r: (r / "images" / "ex0.png").write_bytes(b"not a png"), ["ex0.png", "examples[0].image", "cannot read image"]),
        (
            lambda r: rgb_png(r / "images" / "ex0.png", np.zeros((30, 40, 3), np.uint8), extra=b"\0" * 10),
            ["ex0.png", "examples[0].image", "cannot read image"],
        ),
        (
            lambda r: _replace(r / "points" / "standard.csv", "\nchin,", "\nXchin,"),
            ["standard.csv", "standard.points", "unknown point name"],
        ),
        (
            lambda r: (r / "points" / "neutral.csv").write_text(
                "".join((r / "points" / "neutral.csv").read_text().splitlines(True)[:-1])
            ),
            ["neutral.csv", "neutral.points", "expected 134 points"],
        ),
        (
            lambda r: _replace(r / "points" / "teeth0.csv", "\nnose_tip,", "\nnose_tip,900"),
            ["teeth0.csv", "teeth_examples[0].points", "outside the 40x30 image"],
        ),
        (lambda r: np.savez(r / "captured.npz", points=np.zeros((3, 100, 2))), ["captured.npz", "'captured'", "(..., 134, 2)"]),
        (lambda r: np.savez(r / "captured.npz", other=np.zeros(3)), ["captured.npz", "no array 'points'"]),
        (lambda r: _replace(r / "pack.yaml", "[0, 0, 1]]", "[0, 0, 2]]"), ["pack.yaml", "'intrinsics'"]),
        (
            lambda r: _replace(r / "pack.yaml", "[0, 50, 14.5]", "[0, .nan, 14.5]"),
            ["pack.yaml", "'intrinsics[1][1]'", "expected a finite number, got nan"],
        ),
        (lambda r: _replace(r / "pack.yaml", "image_size: [40, 30]", "image_size: [41, 30]"), ["neutral.png", "image is 40x30"]),
        (lambda r: _replace(r / "pack.yaml", "model3d: model3d.csv", "model3d: nothing.csv"), ["'model3d'", "file not found"]),
        (lambda r: _replace(r / "pack.yaml", "layout: zhang134", "layout: nosuchlayout"), ["nosuchlayout", "cannot read"]),
        (lambda r: (r / "pack.yaml").unlink(), ["pack.yaml", "cannot read manifest"]),
    ],
)
def test_broken_pack_errors_name_file_and_field(pack_dir, breakage, expect):
    """Loading the pack and checking it without decoding its images give the same one line."""
    root, _ = pack_dir
    breakage(root)
    with pytest.raises(StageError) as err:
        load_pack(root)
    msg = str(err.value)
    assert "\n" not in msg
    for part in expect:
        assert part in msg, (part, msg)
    with pytest.raises(StageError) as checked:
        check_pack(root)
    assert str(checked.value) == msg


def test_pack_error_is_a_stage_error(pack_dir):
    root, _ = pack_dir
    shutil.rmtree(root / "images")
    with pytest.raises(PackError):
        load_pack(root)


def test_committed_fixture_packs_load():
    for name in ("performer", "target"):
        pack = load_pack(REPO / "fixtures" / "packs" / name)
        assert 10 <= len(pack.examples) <= 15
        assert 30 <= pack.captured_points.shape[0] <= 40
        assert pack.teeth_examples and pack.standard.image.shape[:2] == pack.image_size[::-1]


@pytest.mark.parametrize("value", ["../outside.png", "images/../../outside.png", "ABSOLUTE"])
def test_pack_files_must_lie_inside_the_pack(pack_dir, value):
    root, _ = pack_dir
    outside = root.parent / "outside.png"
    shutil.copy(root / "images" / "neutral.png", outside)
    value = str(outside) if value == "ABSOLUTE" else value
    manifest = root / "pack.yaml"
    manifest.write_text(manifest.read_text().replace("image: images/neutral.png", f"image: {value}"))
    with pytest.raises(PackError) as info:
        load_pack(root)
    assert str(manifest) in str(info.value) and "'neutral.image'" in str(info.value) and "outside the pack" in str(info.value)


def test_a_layout_outside_the_pack_is_refused_and_a_bundled_one_is_recorded(pack_dir):
    root, _ = pack_dir
    with recording(set()) as files:
        load_pack(root)
    assert (LAYOUT_DIR / "zhang134.yaml").resolve() in files  # enters the key of the stage loading the pack
    shutil.copy(LAYOUT_DIR / "zhang134.yaml", root.parent / "mine.yaml")
    manifest = root / "pack.yaml"
    manifest.write_text(manifest.read_text().replace("layout: zhang134", "layout: ../mine.yaml"))
    with pytest.raises(PackError, match="field 'layout': '../mine.yaml' is outside the pack folder"):
        load_pack(root)


def test_yaml_aliases_in_a_manifest_are_refused_with_their_position(pack_dir):
    root, _ = pack_dir
    manifest = root / "pack.yaml"
    manifest.write_text("a: &a [1, 1, 1]\nb: [*a, *a]\n" + manifest.read_text())
    with pytest.raises(PackError, match=f"{manifest}:2:5: not valid YAML \\(alias \\*a is not allowed"):
        load_pack(root)


# -- bounds checked before anything large is read -------------------------------------------


def decoded_names(monkeypatch) -> list[str]:
    """The names of the files ``cv2.imread`` decodes from now on, as they are decoded."""
    decoded: list[str] = []
    real = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda path, *args: decoded.append(Path(path).name) or real(path, *args))
    return decoded


def test_an_image_larger_than_its_manifest_says_is_refused_undecoded(pack_dir, monkeypatch):
    pack_dir = pack_dir[0]
    """A 12000x12000 PNG as the neutral image: refused from its header, never decoded."""
    big_png(pack_dir / "images" / "neutral.png", 12000, 12000)
    decoded = decoded_names(monkeypatch)
    with pytest.raises(PackError) as info:
        load_pack(pack_dir)
    assert "neutral.image" in str(info.value) and "12000x12000" in str(info.value)
    assert "neutral.png" not in decoded


def test_image_size_beyond_the_pack_limit_is_refused(pack_dir):
    pack_dir = pack_dir[0]
    _replace(pack_dir / "pack.yaml", f"image_size: [{W}, {H}]", "image_size: [20000, 20000]")
    with pytest.raises(PackError, match=r"field 'image_size': 20000x20000 is more than the 16777216 pixels"):
        load_pack(pack_dir)


def test_captured_geometries_beyond_the_bound_are_refused_from_the_header(pack_dir):
    pack_dir = pack_dir[0]
    """An npz whose header declares a million geometries (its data truncated: nothing past the
    header is read) and a real one of 300: both refused naming the file and the count."""
    n = load_layout("zhang134").n_points
    np.savez(pack_dir / "captured.npz", points=np.zeros((300, n, 2)))
    with pytest.raises(PackError, match=r"captured\.npz: field 'captured': .*array 'points' has shape \(300, 134, 2\)"):
        load_pack(pack_dir)
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (1_000_000, n, 2)})
    with zipfile.ZipFile(pack_dir / "captured.npz", "w") as archive:
        archive.writestr("points.npy", header.getvalue() + b"\0" * 64)
    with pytest.raises(PackError, match=r"shape \(1000000, 134, 2\): 268000000 values, more than the 68608 allowed"):
        load_pack(pack_dir)


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated"])
def test_empty_or_truncated_npz_is_a_pack_error(pack_dir, content):
    pack_dir = pack_dir[0]
    (pack_dir / "captured.npz").write_bytes(content)
    with pytest.raises(PackError, match=r"captured\.npz: field 'captured': .*not a readable \.npz"):
        load_pack(pack_dir)


def test_too_many_examples_are_refused(pack_dir):
    pack_dir = pack_dir[0]
    example = "{name: ex0, image: images/ex0.png, points: points/ex0.csv}"
    many = ", ".join(example.replace("name: ex0", f"name: e{k}") for k in range(65))
    _replace(pack_dir / "pack.yaml", "examples: [", f"examples: [{many}, ")
    with pytest.raises(PackError, match=r"field 'examples': expected a list of 2 to 64 expressions, 67 given"):
        load_pack(pack_dir)


def test_examples_sharing_a_name_are_refused_by_the_loader(pack_dir):
    pack_dir = pack_dir[0]
    _replace(pack_dir / "pack.yaml", "{name: ex1,", "{name: ex0,")
    with pytest.raises(PackError, match=r"pack\.yaml: field 'examples': name 'ex0' is given to two examples"):
        load_pack(pack_dir)


@pytest.mark.parametrize("where", ["points/ex1.csv", "captured.npz"])
def test_points_that_all_coincide_are_refused_naming_the_pack(pack_dir, where):
    pack_dir = pack_dir[0]
    layout = load_layout("zhang134")
    if where.endswith(".csv"):
        _write_points(pack_dir / where, layout.point_names, np.full((layout.n_points, 2), 10.0))
    else:
        captured = np.load(pack_dir / where)["points"]
        captured[1] = 12.0
        np.savez(pack_dir / where, points=captured)
    with pytest.raises(PackError) as info:
        load_pack(pack_dir)
    assert f"{pack_dir / where}" in str(info.value) and "points all coincide" in str(info.value)


def test_image_size_of_booleans_is_refused(pack_dir):
    """YAML's `true` is no size (Python's True is an int: it would read as "TruexTrue")."""
    pack_dir = pack_dir[0]
    _replace(pack_dir / "pack.yaml", f"image_size: [{W}, {H}]", "image_size: [true, true]")
    with pytest.raises(PackError, match=r"field 'image_size': expected \[W, H\] positive integers, got \[True, True\]"):
        load_pack(pack_dir)


def test_a_pack_file_that_is_a_fifo_is_refused_unread(pack_dir):
    """A FIFO in the pack where a file is named: refused from its stat, never opened (opening
    a FIFO waits for a writer)."""
    pack_dir = pack_dir[0]
    (pack_dir / "captured.npz").unlink()
    os.mkfifo(pack_dir / "captured.npz")
    with pytest.raises(PackError) as info:
        load_pack(pack_dir)
    where = f"actor pack {pack_dir / 'pack.yaml'}: field 'captured'"
    assert str(info.value) == f"{where}: {pack_dir / 'captured.npz'}: a FIFO (named pipe), not a regular file"


@pytest.mark.parametrize("special", ["/dev/zero", "fifo"])
def test_a_manifest_that_is_not_a_regular_file_is_refused_unread(pack_dir, tmp_path, special):
    """pack.yaml linked to /dev/zero (reading it never ends) or to a FIFO: refused unread."""
    pack_dir = pack_dir[0]
    target = Path(special)
    if special == "fifo":
        target = tmp_path / "fifo"
        os.mkfifo(target)
    kind = "a character device" if special == "/dev/zero" else "a FIFO (named pipe)"
    (pack_dir / "pack.yaml").unlink()
    (pack_dir / "pack.yaml").symlink_to(target)
    with pytest.raises(PackError) as info:
        load_pack(pack_dir)
    assert str(info.value) == f"actor pack {pack_dir / 'pack.yaml'}: cannot read manifest ({kind}, not a regular file)"


def test_a_layout_that_is_a_device_is_refused_unread():
    with pytest.raises(StageError) as info:
        load_layout("/dev/zero")
    assert str(info.value) == "layout /dev/zero: cannot read file (a character device, not a regular file)"


def test_a_matte_larger_than_its_manifest_says_is_refused_undecoded(pack_dir, monkeypatch):
    """A 12000x12000 matte PNG (a few kB): refused from its header, never decoded."""
    pack_dir = pack_dir[0]
    _replace(pack_dir / "pack.yaml", "image: images/neutral.png,", "image: images/neutral.png, matte: matte.png,")
    cv2.imwrite(str(pack_dir / "matte.png"), np.full((H, W), 255, np.uint8))
    assert load_pack(pack_dir).neutral.matte.shape == (H, W)
    big_png(pack_dir / "matte.png", 12000, 12000)
    decoded = decoded_names(monkeypatch)
    with pytest.raises(PackError) as info:
        load_pack(pack_dir)
    assert "field 'neutral.matte'" in str(info.value) and "matte is 12000x12000 px" in str(info.value)
    assert "matte.png" not in decoded
