"""Drawing on small synthetic frames: outlines, labels, class colours, clock."""

import re
import time

import numpy as np
import pytest

from dcuscope.plugins.drawing import PALETTE, class_color, clock_text, draw_clock, draw_detections, to_format


def test_same_class_same_colour_and_neighbours_differ():
    assert class_color(3) == class_color(3) == class_color(3 + len(PALETTE))
    colours = {class_color(c) for c in range(len(PALETTE))}
    assert len(colours) == len(PALETTE)


@pytest.mark.parametrize("fmt, expected", [
    ("RGB", (1, 2, 3)), ("BGR", (3, 2, 1)), ("RGBA", (1, 2, 3, 255)), ("RGBx", (1, 2, 3, 255)),
    ("BGRA", (3, 2, 1, 255)), ("BGRx", (3, 2, 1, 255)),
])
def test_colour_follows_channel_order(fmt, expected):
    assert to_format((1, 2, 3), fmt) == expected


def test_unknown_format_is_refused():
    with pytest.raises(ValueError, match="I420"):
        to_format((1, 2, 3), "I420")


@pytest.mark.parametrize("fmt", ["RGB", "BGRx", "RGBA"])
@pytest.mark.parametrize("line_width", [1, 2, 5])
def test_outline_in_class_colour_and_interior_untouched(fmt, line_width):
    channels = 3 if fmt in ("RGB", "BGR") else 4
    img = np.full((60, 80, channels), 7, np.uint8)
    cls = 4
    draw_detections(img, fmt, np.array([[20, 25, 60, 50]]), np.array([cls]), np.array([0.9]), ["car"],
                    line_width=line_width, display_text=False)
    colour = np.array(class_color(cls, fmt), np.uint8)
    for y, x in [(25, 20), (25, 40), (50, 40), (37, 20), (37, 60), (50, 60)]:  # on each edge
        assert (img[y, x] == colour).all(), (y, x)
    inner = img[25 + line_width : 50 - line_width + 1, 20 + line_width : 60 - line_width + 1]
    assert (inner == 7).all()
    outer = np.ones(img.shape[:2], bool)
    outer[25 - line_width : 50 + line_width + 1, 20 - line_width : 60 + line_width + 1] = False
    assert (img[outer] == 7).all()


def test_label_with_score_is_drawn_above_the_box_in_its_colour():
    img = np.zeros((80, 120, 3), np.uint8)
    draw_detections(img, "RGB", np.array([[10, 40, 100, 70]]), np.array([2]), np.array([0.87]), ["person"],
                    line_width=2, display_text=True, font_scale=0.4)
    above = img[20:39, 9:100]
    colour = np.array(class_color(2, "RGB"))
    assert (above == colour).all(-1).sum() > 100  # the label's background
    assert (img[44:67, 14:97] == 0).all()  # the box interior is still untouched


def test_label_moves_inside_when_the_box_touches_the_top():
    img = np.zeros((80, 120, 3), np.uint8)
    draw_detections(img, "RGB", np.array([[10, 0, 100, 70]]), np.array([1]), np.array([0.5]), [""],
                    display_text=True)
    colour = np.array(class_color(1, "RGB"))
    assert (img[2:15, 10:60] == colour).all(-1).sum() > 100


def test_draws_into_a_padded_strided_view():
    raw = np.zeros((40, 50 * 4 + 8), np.uint8)
    img = raw[:, : 50 * 4].reshape(40, 50, 4)
    draw_detections(img, "BGRA", np.array([[5, 5, 30, 30]]), np.array([0]), np.array([1.0]), ["a"],
                    display_text=False)
    assert (img[5, 10] == class_color(0, "BGRA")).all()
    assert (raw[:, 200:] == 0).all()


def test_clock_text_is_local_wall_clock_with_milliseconds():
    ns = time.time_ns()
    text = clock_text(ns)
    assert re.fullmatch(r"\d\d:\d\d:\d\d\.\d\d\d", text)
    assert text.startswith(time.strftime("%H:%M", time.localtime(ns // 1_000_000_000)))
    assert clock_text(1_700_000_000_123_456_789).endswith(".123")


def test_clock_drawn_top_left_only():
    img = np.full((60, 200, 4), 50, np.uint8)
    draw_clock(img, "RGBx", "12:34:56.789", font_scale=0.5)
    corner = img[:25, :120]
    assert (corner[..., :3] == 255).all(-1).any()  # white text
    assert (corner[..., :3] == 0).all(-1).any()  # black background
    assert (img[30:, :] == 50).all() and (img[:, 150:] == 50).all()
