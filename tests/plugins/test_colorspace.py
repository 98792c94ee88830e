"""Colour conversion and scaling on small synthetic frames."""

import cv2
import numpy as np
import pytest

from dcuscope.plugins.colorspace import (
    BT601, BT709, FORMATS, PACKED, Converter, YuvMatrix, convert, image_from_memory, new_image,
    yuv_to_rgb_matrix,
)

W, H = 32, 24


def rgb_image(pixels: np.ndarray):
    img = new_image("RGB", pixels.shape[1], pixels.shape[0])
    img.planes[0][...] = pixels
    return img


def blocky(seed=0, w=W, h=H):
    """Random colours constant over 2x2 blocks: 4:2:0 chroma subsampling loses nothing."""
    rng = np.random.default_rng(seed)
    return np.repeat(np.repeat(rng.integers(0, 256, (h // 2, w // 2, 3), dtype=np.uint8), 2, 0), 2, 1)


def smooth(w=W, h=H):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 255 // (w - 1), y * 255 // (h - 1), (x + y) * 255 // (w + h - 2)], -1).astype(np.uint8)


def bt601_limited(rgb):
    """Reference BT.601 limited-range encoding of one RGB colour."""
    r, g, b = (float(v) for v in rgb)
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    return y, u, v


@pytest.mark.parametrize("fmt", [f for f in PACKED])
def test_packed_conversions_round_trip_exactly(fmt):
    src = rgb_image(blocky())
    mid, back = new_image(fmt, W, H), new_image("RGB", W, H)
    convert(src, mid)
    convert(mid, back)
    assert np.array_equal(back.planes[0], src.planes[0])


def test_channel_order_and_alpha():
    src = rgb_image(np.tile(np.array([10, 20, 30], np.uint8), (H, W, 1)))
    for fmt, pixel in (("RGBA", [10, 20, 30, 255]), ("BGRx", [30, 20, 10, 255]), ("BGR", [30, 20, 10]),
                       ("BGRA", [30, 20, 10, 255])):
        out = new_image(fmt, W, H)
        convert(src, out)
        assert (out.planes[0] == pixel).all(), fmt


@pytest.mark.parametrize("fmt", ["I420", "NV12"])
def test_yuv420_encoding_is_bt601_limited_range(fmt):
    colours = [(0, 0, 0), (255, 255, 255), (255, 0, 0), (0, 255, 0), (0, 0, 255), (200, 120, 40)]
    for rgb in colours:
        out = new_image(fmt, W, H)
        convert(rgb_image(np.tile(np.array(rgb, np.uint8), (H, W, 1))), out)
        y, u, v = bt601_limited(rgb)
        if fmt == "I420":
            got = out.planes[0][0, 0], out.planes[1][0, 0], out.planes[2][0, 0]
        else:
            got = out.planes[0][0, 0], out.planes[1][0, 0, 0], out.planes[1][0, 0, 1]
        assert np.allclose([float(g) for g in got], [y, u, v], atol=1.0), (rgb, got, (y, u, v))


@pytest.mark.parametrize("fmt", ["I420", "NV12"])
@pytest.mark.parametrize("target", ["RGB", "RGBA", "BGRx", "BGR"])
def test_yuv420_round_trip_within_tolerance(fmt, target):
    src = rgb_image(blocky(1))
    mid, back, ref = new_image(fmt, W, H), new_image(target, W, H), new_image(target, W, H)
    convert(src, mid)
    convert(mid, back)
    convert(src, ref)
    diff = np.abs(back.planes[0].astype(int) - ref.planes[0])
    assert diff.max() <= 3 and diff.mean() < 1.0


def test_i420_and_nv12_hold_the_same_samples():
    src = rgb_image(blocky(2))
    i420, nv12, again = new_image("I420", W, H), new_image("NV12", W, H), new_image("I420", W, H)
    convert(src, i420)
    convert(src, nv12)
    assert np.array_equal(nv12.planes[0], i420.planes[0])
    assert np.array_equal(nv12.planes[1][..., 0], i420.planes[1])
    assert np.array_equal(nv12.planes[1][..., 1], i420.planes[2])
    convert(nv12, again)
    assert all(np.array_equal(a, b) for a, b in zip(again.planes, i420.planes))


def test_gray_is_full_range_luma():
    src = rgb_image(blocky(3))
    gray = new_image("GRAY8", W, H)
    convert(src, gray)
    r, g, b = (src.planes[0][..., i].astype(float) for i in range(3))
    assert np.abs(gray.planes[0] - (0.299 * r + 0.587 * g + 0.114 * b)).max() <= 1
    via_yuv, gray2 = new_image("I420", W, H), new_image("GRAY8", W, H)
    convert(src, via_yuv)
    convert(via_yuv, gray2)  # limited-range Y expanded back to 0..255
    assert np.abs(gray2.planes[0].astype(int) - gray.planes[0]).max() <= 2


def test_strided_planes_convert_like_contiguous_ones():
    # GStreamer's I420 for width 20 has a 12-byte chroma stride (rounded up to 4), not OpenCV's layout.
    w, h = 20, 8
    ys, cs = 20, 12
    offsets = [0, ys * h, ys * h + cs * h // 2]
    data = np.zeros(offsets[2] + cs * h // 2, np.uint8)
    strided = image_from_memory(data, "I420", w, h, offsets, [ys, cs, cs])
    assert strided.block is None
    canonical = new_image("I420", w, h)
    assert canonical.block is not None
    src = rgb_image(blocky(4, w, h))
    convert(src, strided)
    convert(src, canonical)
    assert all(np.array_equal(a, b) for a, b in zip(strided.planes, canonical.planes))
    assert (data.reshape(-1)[offsets[1] : offsets[2]].reshape(h // 2, cs)[:, 10:] == 0).all()  # padding untouched
    back1, back2 = new_image("RGBA", w, h), new_image("RGBA", w, h)
    convert(strided, back1)
    convert(canonical, back2)
    assert np.array_equal(back1.planes[0], back2.planes[0])


def test_resize_and_convert_together():
    src = rgb_image(smooth(64, 48))
    for fmt in FORMATS:
        small = new_image(fmt, 32, 24)
        convert(src, small)
        direct = new_image("RGB", 32, 24)
        convert(src, direct)
        back = new_image("RGB", 32, 24)
        convert(small, back)
        same_size = new_image(fmt, 32, 24)  # the same format's losses, without scaling
        convert(direct, same_size)
        expected = new_image("RGB", 32, 24)
        convert(same_size, expected)
        diff = np.abs(back.planes[0].astype(int) - expected.planes[0])
        assert diff.max() <= 2, fmt
    big = new_image("I420", 128, 96)  # growing: converted first, then scaled
    convert(src, big)
    back = new_image("RGB", 64, 48)
    convert(big, back)
    assert np.abs(back.planes[0].astype(int) - src.planes[0]).mean() < 2


def test_shrinking_by_two_averages():
    src = rgb_image(np.tile(np.array([[0], [200]], np.uint8), (H // 2, W))[..., None].repeat(3, 2))
    out = new_image("RGB", W // 2, H // 2)
    convert(src, out)
    assert (out.planes[0] == 100).all()  # INTER_AREA: no line skipped


def test_matrix_path_agrees_with_opencv_bt601_on_smooth_frames():
    yuv = new_image("I420", W, H)
    convert(rgb_image(smooth()), yuv)
    fast, general = new_image("RGB", W, H), new_image("RGB", W, H)
    convert(yuv, fast)
    # A kr off by 1e-5 forces the general cv2.transform path with the same colours.
    Converter("I420", (W, H), "RGB", (W, H), YuvMatrix(0.29901, 0.114))(yuv, general)
    diff = np.abs(fast.planes[0].astype(int) - general.planes[0])
    assert diff.max() <= 4 and diff.mean() < 1


def test_bt709_and_full_range_matrices():
    m = yuv_to_rgb_matrix(BT709)
    np.testing.assert_allclose(m[:, :3] @ [235, 128, 128] + m[:, 3], [255, 255, 255], atol=0.01)
    np.testing.assert_allclose(m[:, :3] @ [16, 128, 128] + m[:, 3], [0, 0, 0], atol=0.01)
    # BT.709 limited red: Y 63, U 102, V 240
    np.testing.assert_allclose(m[:, :3] @ [63, 102, 240] + m[:, 3], [255, 0, 0], atol=2.5)
    full = yuv_to_rgb_matrix(YuvMatrix(BT601.kr, BT601.kb, True))
    np.testing.assert_allclose(full[:, :3] @ [128, 128, 128] + full[:, 3], [128, 128, 128], atol=1e-3)


def test_bt709_input_decodes_with_its_own_matrix():
    yuv = new_image("NV12", W, H)
    yuv.planes[0][...] = 63
    yuv.planes[1][...] = (102, 240)
    out = new_image("BGRA", W, H)
    Converter("NV12", (W, H), "BGRA", (W, H), BT709)(yuv, out)
    assert np.abs(out.planes[0].astype(int) - [0, 0, 255, 255]).max() <= 3


def test_yuv420_needs_even_sizes_and_formats_are_checked():
    with pytest.raises(ValueError, match="even"):
        Converter("RGB", (31, 24), "I420", (31, 24))
    with pytest.raises(ValueError, match="unsupported format 'YUY2'"):
        Converter("RGB", (32, 24), "YUY2", (32, 24))


def test_converter_writes_in_place_into_given_planes():
    src = rgb_image(blocky(5))
    raw = np.zeros(W * H * 4 + 7, np.uint8)
    dst = image_from_memory(raw, "RGBA", W, H, [7], [W * 4])
    convert(src, dst)
    assert (raw[:7] == 0).all()
    assert np.array_equal(raw[7:].reshape(H, W, 4)[..., :3], src.planes[0])
    assert cv2.countNonZero(raw[7:].reshape(H, W, 4)[..., 3].copy()) == W * H
