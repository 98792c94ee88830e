"""Tiling maths on small synthetic frames: grid, tile rectangles, composition, box mapping."""

import numpy as np
import pytest

from dcuscope.plugins.tiling import compose, grid_shape, map_boxes, tile_rects, tiles_for_slots


@pytest.mark.parametrize("n, expected", [
    (1, (1, 1)), (2, (1, 2)), (3, (2, 2)), (4, (2, 2)), (5, (2, 3)), (6, (2, 3)),
    (7, (3, 3)), (9, (3, 3)), (10, (3, 4)), (16, (4, 4)), (0, (1, 1)),
])
def test_automatic_grid_is_near_square_and_holds_every_source(n, expected):
    rows, columns = grid_shape(n)
    assert (rows, columns) == expected
    assert rows * columns >= max(n, 1)


def test_grid_with_one_side_fixed_grows_the_other():
    assert grid_shape(5, rows=1) == (1, 5)
    assert grid_shape(5, columns=2) == (3, 2)
    assert grid_shape(5, rows=4, columns=1) == (4, 1)  # both given: as asked, even if too small


def test_tile_rects_row_major_exact():
    rects = tile_rects(2, 2, 1280, 720)
    assert rects.tolist() == [[0, 0, 640, 360], [640, 0, 640, 360], [0, 360, 640, 360], [640, 360, 640, 360]]


def test_tile_rects_cover_uneven_sizes_without_gaps():
    rects = tile_rects(2, 3, 100, 51)
    assert rects.tolist() == [
        [0, 0, 33, 25], [33, 0, 33, 25], [66, 0, 34, 25],
        [0, 25, 33, 26], [33, 25, 33, 26], [66, 25, 34, 26],
    ]
    cover = np.zeros((51, 100), int)
    for x, y, w, h in rects:
        cover[y : y + h, x : x + w] += 1
    assert (cover == 1).all()


def test_tile_of_a_slot_is_its_source_and_out_of_grid_sources_are_dropped():
    assert tiles_for_slots([3, 0, 1], 3, 4).tolist() == [3, 0, 1]
    assert tiles_for_slots([0, 7, 2], 3, 4).tolist() == [0, -1, 2]
    # without identity, slot order
    assert tiles_for_slots([], 3, 4).tolist() == [0, 1, 2]


def _frames(n, h=6, w=8):
    return [np.full((h, w, 3), (i + 1) * 40, np.uint8) for i in range(n)]


def test_compose_puts_frame_i_in_tile_of_its_source_and_blackens_empty_tiles():
    out = np.full((12, 16, 3), 99, np.uint8)  # stale pooled data
    rects = tile_rects(2, 2, 16, 12)
    frames = _frames(3, 12, 16)  # scaled down 2x
    compose(frames, np.array([3, 0, 1]), rects, out)
    assert (out[6:, 8:] == 40).all()  # slot 0, source 3 -> bottom-right
    assert (out[:6, :8] == 80).all()  # slot 1, source 0 -> top-left
    assert (out[:6, 8:] == 120).all()  # slot 2, source 1 -> top-right
    assert (out[6:, :8] == 0).all()  # no source 2 in this batch: black


def test_compose_scales_content_into_the_tile():
    frame = np.zeros((40, 40, 3), np.uint8)
    frame[:20, :20] = 255  # top-left quarter white
    out = np.zeros((20, 40, 3), np.uint8)
    compose([frame], np.array([1]), tile_rects(1, 2, 40, 20), out)
    assert (out[:, :20] == 0).all()  # tile 0 empty
    assert (out[:10, 20:30] == 255).all()  # quarter of tile 1
    assert (out[10:, 20:] == 0).all() and (out[:, 30:] == 0).all()


def test_compose_writes_through_a_padded_view():
    # A mapped buffer with row padding arrives as a strided view: writes must land in it.
    raw = np.zeros((12, 16 * 3 + 4), np.uint8)
    out = raw[:, : 16 * 3].reshape(12, 16, 3)
    compose(_frames(4, 12, 16), np.arange(4), tile_rects(2, 2, 16, 12), out)
    assert (raw[:6, :24] == 40).all() and (raw[6:, 24:48] == 160).all()
    assert (raw[:, 48:] == 0).all()  # padding untouched


def test_map_boxes_exact_numbers():
    rects = tile_rects(2, 2, 1280, 720)
    tiles = tiles_for_slots([2, 0], 2, 4)
    boxes = np.array([[100, 50, 300, 250], [0, 0, 1920, 1080], [960, 540, 1000, 600]], np.float32)
    slots = np.array([0, 0, 1])
    mapped, keep = map_boxes(boxes, slots, tiles, rects, 1920, 1080)
    assert keep.tolist() == [True, True, True]
    # 1920x1080 -> 640x360 tile: scale 1/3; source 2 is the bottom-left tile (0, 360).
    np.testing.assert_allclose(mapped, [
        [100 / 3, 360 + 50 / 3, 100, 360 + 250 / 3],
        [0, 360, 640, 720],
        [320, 180, 1000 / 3, 200],
    ], rtol=0, atol=1e-3)


def test_map_boxes_drops_boxes_of_frames_left_out_and_clips_to_the_tile():
    rects = tile_rects(1, 2, 200, 100)
    tiles = tiles_for_slots([1, 5], 2, 2)  # source 5 does not fit a 1x2 grid
    boxes = np.array([[-10, -10, 50, 120], [1, 1, 2, 2]], np.float32)
    mapped, keep = map_boxes(boxes, np.array([0, 1]), tiles, rects, 100, 100)
    assert keep.tolist() == [True, False]
    np.testing.assert_allclose(mapped, [[100, 0, 150, 100]])
