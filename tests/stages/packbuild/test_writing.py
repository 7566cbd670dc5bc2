"""Pack writing pieces: the similarity image warp against the point map, exposure gains in linear light,
the contact sheet's layout."""

import numpy as np
import pytest

from stages.color import linear_to_srgb, srgb_to_linear
from stages.geometry.compensate import apply_similarity
from stages.packbuild.writing import align_image, apply_gains, contact_sheet, exposure_gains


def test_align_image_moves_a_pixel_where_the_similarity_moves_its_point():
    image = np.zeros((60, 80, 3), np.uint8)
    image[20, 30] = 255
    params = np.array([1.2 * np.cos(0.3), 1.2 * np.sin(0.3), 12.0, -4.0])
    out, matte = align_image(image, params, (100, 90))
    assert out.shape == (90, 100, 3) and matte.shape == (90, 100)
    y, x = np.unravel_index(np.argmax(out[..., 0].astype(float)), out.shape[:2])
    np.testing.assert_allclose((x, y), apply_similarity(params, np.array([30.0, 20.0])), atol=0.75)


def test_pixels_beyond_the_footage_are_marked_in_the_matte_and_filled_not_repeated_from_the_edge():
    """A frame whose bottom row is a random colour pattern, mapped 20 px up: the last 20 rows of
    the pack image have no source. They must be marked (matte 0) and be no copy of the edge row
    (an edge-replicated crop repeats it in every such row: vertical streaks)."""
    rng = np.random.default_rng(2)
    image = np.full((60, 80, 3), 120, np.uint8)
    image[-1] = rng.integers(0, 256, (80, 3))
    params = np.array([1.0, 0.0, 0.0, -20.0])  # up by 20 px: pack rows 40.. come from beyond the frame's bottom
    out, matte = align_image(image, params, (80, 60))
    assert (matte[:40] == 255).all() and (matte[41:] == 0).all()
    np.testing.assert_array_equal(out[:39], np.full((39, 80, 3), 120, np.uint8))  # real pixels as they were
    edge = image[-1].astype(float)
    beyond = out[45:].astype(float)
    assert np.abs(beyond - edge).mean() > 0.5 * np.abs(edge - edge.mean(0)).mean()  # not the edge row repeated
    assert np.abs(np.diff(beyond, axis=1)).mean() < 0.2 * np.abs(np.diff(edge, axis=0)).mean()  # a smooth fill


def test_exposure_gains_undo_a_known_linear_gain_per_channel():
    rng = np.random.default_rng(1)
    reference = rng.integers(40, 200, (32, 32, 3)).astype(np.uint8)
    gain = np.array([0.7, 0.9, 1.3])
    lin = srgb_to_linear(reference / 255.0) * gain
    darker = np.round(np.clip(linear_to_srgb(lin), 0, 1) * 255).astype(np.uint8)
    mask = np.zeros((32, 32), bool)
    mask[4:28, 4:28] = True
    g = exposure_gains(darker, reference, mask)
    np.testing.assert_allclose(g, 1 / gain, rtol=0.01)
    restored = apply_gains(darker, g)
    assert np.abs(restored.astype(int) - reference.astype(int)).max() <= 2
    assert exposure_gains(darker, reference, mask, max_gain=1.2)[0] == pytest.approx(1.2)  # limited
    with pytest.raises(ValueError, match="no pixel"):
        exposure_gains(darker, reference, np.zeros((32, 32), bool))


def test_contact_sheet_rows_columns_and_blank_cells():
    images = [(f"im{k}", np.full((80, 60, 3), 10 * k, np.uint8)) for k in range(5)]
    sheet = contact_sheet(images, columns=3, thumb_height=60)
    # thumbnails 45 x 60 px with a 2 px white border each side: 2 rows of 3 cells of 49 x 64
    assert sheet.shape == (2 * 64, 3 * 49, 3)
    assert np.all(sheet[64 + 2 : 64 + 62, 2 * 49 + 2 : 2 * 49 + 47] == 255)  # the sixth cell is blank
    assert np.all(sheet[64 + 50, 49 + 40] == 40)  # the fifth image, below its label
    assert np.all(sheet[0:2] == 255) and np.all(sheet[50, 40] == 0)  # border; the first image


def test_a_letterboxed_photos_border_is_not_counted_as_real():
    """photos.decode fills the border of a photo brought to the frame size by repeating its edge;
    its 'valid' frame marks that border, and the pack's matte does not count it as real."""
    from stages.packbuild.photos import letterbox, placed

    rng = np.random.default_rng(4)
    photo = rng.integers(0, 256, (30, 20, 3)).astype(np.uint8)
    frame, valid = letterbox(photo, (40, 30)), placed((20, 30), (40, 30))[..., 0]
    assert (valid[:, :10] == 0).all() and (valid[:, 10:30] == 255).all() and (valid[:, 30:] == 0).all()
    out, matte = align_image(frame, np.array([1.0, 0.0, 0.0, 0.0]), (40, 30), valid=valid)
    np.testing.assert_array_equal(matte, valid)
    np.testing.assert_array_equal(out[:, 10:30], photo)
    assert (
        np.abs(np.diff(out[:, :8].astype(float), axis=1)).mean()
        < 0.5 * np.abs(np.diff(frame[:, 10:30].astype(float), axis=1)).mean()
    )
