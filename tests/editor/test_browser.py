"""The editor in Debian's Chromium: drag the nose tip, pin/unpin, undo/redo, export keyframes
and render them with the pipeline (editor/render_keyframes.yaml)."""

from __future__ import annotations

import importlib.metadata

import cv2
import numpy as np
import pytest

from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.registry import ENTRY_POINT_GROUP, Registry
from stages.layout import load_layout
from tests.editor.conftest import PACK, REPO, assert_is_pipeline_image, synthesize_stage

LAYOUT = load_layout("zhang134")
NOSE = [i for i, n in enumerate(LAYOUT.point_names) if n.startswith("nose_")]


@pytest.fixture()
def page(browser, editor_server):
    context = browser.new_context(accept_downloads=True, viewport={"width": 900, "height": 700}, bypass_csp=True)
    page = context.new_page()
    page.goto(editor_server.url)
    page.wait_for_function("window.editor && window.editor.stats.updates.length > 0", timeout=120_000)
    yield page
    context.close()


def canvas_image(page) -> np.ndarray:
    """The image canvas as (H, W, 3) uint8 RGB, read back from the page."""
    png = page.locator("#image").screenshot()
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def canvas_pixels(page) -> np.ndarray:
    """The image canvas's pixels as (H, W, 3) uint8 RGB (without the overlay on top of it)."""
    width, height = page.evaluate("window.editor.layout().size")
    data = page.evaluate(
        "(() => { const c = document.getElementById('image'); return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data); })()"
    )
    return np.array(data, np.uint8).reshape(height, width, 4)[..., :3]


def screen_position(page, xy) -> tuple[float, float]:
    box = page.locator("#overlay").bounding_box()
    return box["x"] + xy[0] + 0.5, box["y"] + xy[1] + 0.5


def drag(page, index: int, offset, *, steps: int = 12) -> None:
    """Drag point ``index`` of the shown geometry by ``offset`` px, then wait until idle."""
    start = np.array(page.evaluate("window.editor.geometry()")[index])
    x, y = screen_position(page, start)
    page.mouse.move(x, y)
    page.mouse.down()
    for k in range(1, steps + 1):
        page.mouse.move(x + offset[0] * k / steps, y + offset[1] * k / steps)
    page.mouse.up()
    page.evaluate("window.editor.idle()")


def render_keyframes(points_file, *, out, cache) -> None:
    """Run editor/render_keyframes.yaml as `runner run` does, with ``points.load`` registered
    whether or not the installed distribution declares it yet."""
    targets = {ep.name: ep.value for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    targets.setdefault("points.load", "stages.geometry.points_file:LoadPoints")
    pipeline = load_pipeline(REPO / "editor" / "render_keyframes.yaml", Registry(entry_points=targets))
    bound = bind_inputs(pipeline, clip=None, named=[f"keyframes={points_file}", f"target={PACK}"])
    Runner(pipeline, bound, Options(cache=CacheStore(cache), out=out)).run()


def geometry(page) -> np.ndarray:
    return np.array(page.evaluate("window.editor.geometry()"), np.float64)


def test_dragging_a_nose_wing_moves_the_nose_together_and_changes_the_image(page):
    # The fixture target's nose tip and bridge never move in its captured geometries (the
    # synthetic face's nose is rigid), so propagation rightly holds the rest still when the tip
    # is dragged; the nose wing does move (sneer, smile), and the nose moves with it.
    ala_l, ala_r = LAYOUT.index("nose_ala_l"), LAYOUT.index("nose_ala_r")
    before_xy, before_image = geometry(page), canvas_image(page)
    played = page.evaluate("window.editor.stats.played")
    drag(page, ala_l, (0.0, -5.0))
    after_xy, after_image = geometry(page), canvas_image(page)
    # On release the five in-betweens (Sec. 14.2) and the final frame were played.
    assert page.evaluate("window.editor.stats.played") - played == 6
    np.testing.assert_allclose(after_xy[ala_l] - before_xy[ala_l], [0.0, -5.0], atol=0.51)
    moved = after_xy - before_xy
    together = [ala_r] + [LAYOUT.index(n) for n in ("nose_alar_crease_l", "nose_alar_crease_r", "nose_base")]
    assert (moved[together, 1] < -0.5).all(), moved[together]
    assert moved[[ala_r, LAYOUT.index("nose_alar_crease_l"), LAYOUT.index("nose_alar_crease_r")], 1].mean() < -1.5
    rigid = [LAYOUT.index(n) for n in ("nose_tip", "nose_bridge_0", "nose_bridge_1")]
    np.testing.assert_allclose(moved[rigid], 0.0, atol=0.05)
    assert page.evaluate("window.editor.pinned()") == [ala_l]
    changed = np.abs(after_image.astype(int) - before_image.astype(int)).max(axis=2) > 12
    assert changed.sum() > 50
    ys, xs = np.nonzero(changed)
    centre = after_xy[NOSE].mean(axis=0)
    assert np.median(np.hypot(xs - centre[0], ys - centre[1])) < 60  # the change is around the nose


def test_dragging_the_lower_lip_opens_the_mouth(page):
    lip = LAYOUT.index("mouth_outer_12")
    before_xy = geometry(page)
    drag(page, lip, (0.0, 10.0))
    moved = geometry(page) - before_xy
    lower_lip = [LAYOUT.index(f"mouth_outer_{k}") for k in (10, 11, 13, 14)]
    assert (moved[lower_lip, 1] > 2.0).all(), moved[lower_lip]
    brows = [i for i, n in enumerate(LAYOUT.point_names) if n.startswith("brow_")]
    assert moved[LAYOUT.index("contour_8"), 1] > 1.0  # the chin follows (the jaw opens)
    assert np.abs(moved[brows, 1]).max() < 0.25 * moved[lower_lip, 1].mean()  # the brows hardly rise


def test_full_size_jpegs_while_dragging_then_the_pipelines_image_when_the_mouse_stops(page, pipeline):
    width, height = page.evaluate("window.editor.layout().size")
    updates = len(page.evaluate("window.editor.stats.updates"))
    drag(page, LAYOUT.index("mouth_outer_12"), (0.0, 8.0), steps=20)
    widths = page.evaluate("window.editor.stats.widths")[updates:]
    types = page.evaluate("window.editor.stats.types")[updates:]
    # JPEGs at the pack's size were drawn while dragging (and the PNG, were the pointer to rest
    # 150 ms between two moves on a loaded machine).
    assert "image/jpeg" in types and set(types) <= {"image/jpeg", "image/png"} and set(widths) == {width}
    assert page.evaluate("window.editor.shown()") == {"type": "image/png", "width": width, "height": height}
    frame = synthesize_stage(pipeline[0], geometry(page)[None])[0]
    assert_is_pipeline_image(canvas_pixels(page), frame)


def test_click_unpins_and_undo_redo_reset(page):
    neutral = geometry(page)
    drag(page, LAYOUT.index("mouth_outer_12"), (0.0, 6.0))
    dragged = geometry(page)
    page.mouse.click(*screen_position(page, dragged[LAYOUT.index("mouth_outer_12")]))  # a click on a pinned point unpins it
    page.evaluate("window.editor.idle()")
    assert page.evaluate("window.editor.pinned()") == []
    np.testing.assert_allclose(geometry(page), neutral, atol=1e-6)
    page.click("#undo")
    page.evaluate("window.editor.idle()")
    np.testing.assert_allclose(geometry(page), dragged, atol=1e-6)
    page.click("#undo")
    page.evaluate("window.editor.idle()")
    np.testing.assert_allclose(geometry(page), neutral, atol=1e-6)
    page.click("#redo")
    page.evaluate("window.editor.idle()")
    np.testing.assert_allclose(geometry(page), dragged, atol=1e-6)
    page.click("#reset")
    page.evaluate("window.editor.idle()")
    np.testing.assert_allclose(geometry(page), neutral, atol=1e-6)
    assert page.evaluate("window.editor.stats.errors") == 0


def test_exported_keyframes_render_with_the_pipeline(page, tmp_path):
    page.fill("#key-time", "0")
    page.click("#save-key")
    drag(page, LAYOUT.index("mouth_outer_12"), (0.0, 8.0))
    page.fill("#key-time", "0.3")
    page.click("#save-key")
    page.fill("#fps", "10")
    keys = page.evaluate("window.editor.keyframes()")
    assert [k["time_s"] for k in keys] == [0.0, 0.3]
    with page.expect_download() as download:
        page.click("#export")
    path = tmp_path / "keyframes.npz"
    download.value.save_as(path)
    with np.load(path, allow_pickle=False) as data:
        xy, names, fps = data["xy"], data["names"], float(data["fps"])
    assert xy.shape == (4, LAYOUT.n_points, 2) and fps == 10.0 and tuple(names) == LAYOUT.point_names
    np.testing.assert_allclose(xy[0], keys[0]["points"])
    np.testing.assert_allclose(xy[3], keys[1]["points"], atol=1e-9)
    np.testing.assert_allclose(xy[1], (2 * xy[0] + xy[3]) / 3, atol=1e-9)  # linear in time
    out = tmp_path / "out"
    render_keyframes(path, out=out, cache=tmp_path / "cache")
    frames = sorted((out / "exr").glob("frame.*.exr"))
    assert len(frames) == 4
    assert (out / "video" / "keyframes.mp4").stat().st_size > 0


def test_touching_up_a_performance_frame(page, performance):
    with np.load(performance, allow_pickle=False) as data:
        frame = data["target_xy"][2]
    page.fill("#frame-index", "2")
    page.click("#load-frame")
    page.evaluate("window.editor.idle()")
    np.testing.assert_allclose(geometry(page), frame, atol=1e-9)
    lip = LAYOUT.index("mouth_outer_12")
    drag(page, lip, (0.0, 6.0))
    moved = geometry(page) - frame
    np.testing.assert_allclose(moved[lip], [0.0, 6.0], atol=0.51)
    assert (moved[[LAYOUT.index("mouth_outer_11"), LAYOUT.index("mouth_outer_13")], 1] > 1.0).all()
    page.click("#undo")
    page.evaluate("window.editor.idle()")
    np.testing.assert_allclose(geometry(page), frame, atol=1e-9)
