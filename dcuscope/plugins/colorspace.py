"""Colour conversion and scaling between the raw video formats the convert element handles.

Plain numpy + OpenCV (multi-threaded C++), no GStreamer: an :class:`Image` is a list of plane
views, usually straight into a mapped buffer, and a :class:`Converter` writes one image into
another of a given format and size.

Colour matrix: YUV written here is always ITU-R BT.601, limited range (Y 16-235, UV 16-240),
what OpenCV's I420 encoder produces; the convert element says so in its caps
(``colorimetry=bt601``), which is also GStreamer's default for SD sizes. YUV read here may be
any matrix and range: BT.601 limited range takes OpenCV's fast path, others (BT.709 from HD
decoders, full-range JPEG) a 3x4 matrix applied with ``cv2.transform``. Chroma is subsampled
as OpenCV does (one sample per 2x2 block) and upsampled by repetition on the fast path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

FORMATS = ("RGB", "BGR", "RGBA", "BGRA", "RGBx", "BGRx", "I420", "NV12", "GRAY8")
PACKED = {"RGB": ("RGB", 3), "BGR": ("BGR", 3), "RGBA": ("RGB", 4), "RGBx": ("RGB", 4),
          "BGRA": ("BGR", 4), "BGRx": ("BGR", 4)}
YUV420 = ("I420", "NV12")

# Shrinking by 2x or more with bilinear sampling skips source pixels (aliasing on edges and
# text); INTER_AREA averages them, at about the price of a C scaler with a proper filter.
AREA_BELOW = 0.5


@dataclass(frozen=True)
class YuvMatrix:
    """How a YUV image encodes colour: luma weights of red and blue, and the value range."""

    kr: float = 0.299
    kb: float = 0.114
    full_range: bool = False

    @property
    def is_bt601_limited(self) -> bool:
        return abs(self.kr - 0.299) < 1e-4 and abs(self.kb - 0.114) < 1e-4 and not self.full_range


BT601 = YuvMatrix()
BT709 = YuvMatrix(0.2126, 0.0722)


@dataclass
class Image:
    """One video frame as plane views: packed (H, W, C); GRAY8 (H, W); I420 Y, U, V (H/2, W/2);
    NV12 Y and interleaved UV (H/2, W/2, 2).

    ``block`` is an I420 frame's three planes as one (3H/2, W) array, OpenCV's I420 layout,
    when they lie back to back in memory (GStreamer's own layout for widths divisible by 8).
    """

    fmt: str
    planes: list[np.ndarray]
    block: np.ndarray | None = None

    @property
    def width(self) -> int:
        return int(self.planes[0].shape[1])

    @property
    def height(self) -> int:
        return int(self.planes[0].shape[0])


def plane_shapes(fmt: str, width: int, height: int) -> list[tuple[int, ...]]:
    """Array shape of each plane of a ``fmt`` frame."""
    if fmt in PACKED:
        return [(height, width, PACKED[fmt][1])]
    if fmt == "GRAY8":
        return [(height, width)]
    cw, ch = (width + 1) // 2, (height + 1) // 2
    if fmt == "I420":
        return [(height, width), (ch, cw), (ch, cw)]
    if fmt == "NV12":
        return [(height, width), (ch, cw, 2)]
    raise ValueError(f"unsupported format {fmt!r}; supported: {', '.join(FORMATS)}")


def new_image(fmt: str, width: int, height: int) -> Image:
    """A zeroed, contiguous image (I420 with its ``block``)."""
    shapes = plane_shapes(fmt, width, height)
    sizes = [int(np.prod(s)) for s in shapes]
    data = np.zeros(sum(sizes), np.uint8)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    strides = [s[1] * (s[2] if len(s) == 3 else 1) for s in shapes]
    return image_from_memory(data, fmt, width, height, offsets, strides)


def image_from_memory(data: np.ndarray, fmt: str, width: int, height: int,
                      offsets: Sequence[int], strides: Sequence[int]) -> Image:
    """Plane views into a 1-D uint8 array laid out with the given plane offsets and strides
    (bytes, as in ``GstVideoInfo``). Writable when ``data`` is."""
    planes = []
    for shape, off, stride in zip(plane_shapes(fmt, width, height), offsets, strides):
        pixel = shape[2] if len(shape) == 3 else 1
        st = (int(stride), pixel, 1) if len(shape) == 3 else (int(stride), 1)
        planes.append(np.ndarray(shape, np.uint8, buffer=data, offset=int(off), strides=st))
    block = None
    if fmt == "I420" and width % 2 == 0 and height % 2 == 0:
        o, s = [int(v) for v in offsets[:3]], [int(v) for v in strides[:3]]
        if s == [width, width // 2, width // 2] and o[1] == o[0] + width * height \
                and o[2] == o[1] + width * height // 4:
            block = np.ndarray((height * 3 // 2, width), np.uint8, buffer=data, offset=o[0])
    return Image(fmt, planes, block)


def interpolation_for(src_w: int, src_h: int, dst_w: int, dst_h: int) -> int:
    """OpenCV interpolation for scaling (src_w, src_h) to (dst_w, dst_h)."""
    if dst_w <= src_w * AREA_BELOW and dst_h <= src_h * AREA_BELOW:
        return cv2.INTER_AREA
    return cv2.INTER_LINEAR


def _into(result: np.ndarray, dst: np.ndarray) -> None:
    # OpenCV writes into dst= when it can and returns it; anything else is a fresh array
    # that must still land in the frame.
    if result is not dst:
        np.copyto(dst, result.reshape(dst.shape))


def _code(name: str) -> int:
    return getattr(cv2, f"COLOR_{name}")


def _packed_name(fmt: str) -> str:
    order, channels = PACKED[fmt]
    return order + ("A" if channels == 4 else "")


def yuv_to_rgb_matrix(m: YuvMatrix) -> np.ndarray:
    """3x4 float32 matrix taking (Y, U, V, 1) in 0..255 code values to (R, G, B)."""
    kg = 1.0 - m.kr - m.kb
    ys, yo, cs = (1.0, 0.0, 1.0) if m.full_range else (255 / 219, 16.0, 255 / 224)
    a = np.array([
        [ys, 0.0, 2 * (1 - m.kr) * cs],
        [ys, -2 * m.kb * (1 - m.kb) / kg * cs, -2 * m.kr * (1 - m.kr) / kg * cs],
        [ys, 2 * (1 - m.kb) * cs, 0.0],
    ])
    offset = -a @ np.array([yo, 128.0, 128.0])
    return np.hstack([a, offset[:, None]]).astype(np.float32)


class Converter:
    """Writes a ``src_fmt`` image of ``src_size`` into a ``dst_fmt`` image of ``dst_size``.

    Holds the scratch arrays a conversion needs, so a stream of frames allocates nothing.
    ``matrix`` is the colour matrix of YUV input (ignored for other input).
    """

    def __init__(self, src_fmt: str, src_size: tuple[int, int], dst_fmt: str, dst_size: tuple[int, int],
                 matrix: YuvMatrix = BT601):
        for fmt, (w, h) in ((src_fmt, src_size), (dst_fmt, dst_size)):
            plane_shapes(fmt, w, h)
            if fmt in YUV420 and (w % 2 or h % 2):
                raise ValueError(f"{fmt} needs an even width and height, got {w}x{h}")
        self.src_fmt, self.dst_fmt, self.matrix = src_fmt, dst_fmt, matrix
        self.src_size, self.dst_size = tuple(src_size), tuple(dst_size)
        self.tmp = None
        self.shrink = dst_size[0] * dst_size[1] <= src_size[0] * src_size[1]
        if self.src_size != self.dst_size and src_fmt != dst_fmt:
            # Scale where there are fewer pixels: before converting when shrinking, after when growing.
            fmt, size = (src_fmt, dst_size) if self.shrink else (dst_fmt, src_size)
            self.tmp = new_image(fmt, *size)
        self._scratch: dict[tuple, np.ndarray] = {}

    def __call__(self, src: Image, dst: Image) -> None:
        if self.src_size == self.dst_size:
            self.convert(src, dst)
        elif self.tmp is None:
            self.resize(src, dst)
        elif self.shrink:
            self.resize(src, self.tmp)
            self.convert(self.tmp, dst)
        else:
            self.convert(src, self.tmp)
            self.resize(self.tmp, dst)

    @staticmethod
    def resize(src: Image, dst: Image) -> None:
        """Scale every plane of ``src`` into the same plane of ``dst`` (same format)."""
        for s, d in zip(src.planes, dst.planes):
            h, w = d.shape[:2]
            _into(cv2.resize(s, (w, h), dst=d, interpolation=interpolation_for(s.shape[1], s.shape[0], w, h)), d)

    def convert(self, src: Image, dst: Image) -> None:
        """Convert ``src`` into ``dst`` of the same size."""
        s, d = src.fmt, dst.fmt
        if s == d:
            for a, b in zip(src.planes, dst.planes):
                np.copyto(b, a)
        elif s in PACKED and d in PACKED:
            a, b = _packed_name(s), _packed_name(d)
            if a == b:  # RGBA <-> RGBx: same bytes
                np.copyto(dst.planes[0], src.planes[0])
            else:
                _into(cv2.cvtColor(src.planes[0], _code(f"{a}2{b}"), dst=dst.planes[0]), dst.planes[0])
        elif s in PACKED and d == "GRAY8":
            _into(cv2.cvtColor(src.planes[0], _code(f"{_packed_name(s)}2GRAY"), dst=dst.planes[0]), dst.planes[0])
        elif s == "GRAY8" and d in PACKED:
            code = cv2.COLOR_GRAY2RGB if PACKED[d][1] == 3 else cv2.COLOR_GRAY2RGBA
            _into(cv2.cvtColor(src.planes[0], code, dst=dst.planes[0]), dst.planes[0])
        elif s in PACKED and d in YUV420:
            self._packed_to_yuv(src, dst)
        elif s in YUV420 and d in PACKED:
            if self.matrix.is_bt601_limited:
                self._yuv_to_packed(src, dst)
            else:
                self._yuv_to_packed_matrix(src, dst)
        elif s in YUV420 and d in YUV420:
            self._yuv_to_yuv(src, dst)
        elif s in YUV420 and d == "GRAY8":
            y = src.planes[0]
            if self.matrix.full_range:
                np.copyto(dst.planes[0], y)
            else:
                _into(cv2.LUT(y, _LIMITED_TO_FULL, dst=dst.planes[0]), dst.planes[0])
        elif s == "GRAY8" and d in YUV420:
            _into(cv2.LUT(src.planes[0], _FULL_TO_LIMITED, dst=dst.planes[0]), dst.planes[0])
            for p in dst.planes[1:]:
                p[...] = 128
        else:  # pragma: no cover - every pair of FORMATS is handled above
            raise ValueError(f"no conversion from {s} to {d}")

    def _block(self, width: int, height: int) -> np.ndarray:
        key = (height * 3 // 2, width)
        if key not in self._scratch:
            self._scratch[key] = np.empty(key, np.uint8)
        return self._scratch[key]

    def _packed_to_yuv(self, src: Image, dst: Image) -> None:
        code = _code(f"{_packed_name(src.fmt)}2YUV_I420")
        w, h = src.width, src.height
        block = dst.block if dst.block is not None else self._block(w, h)
        _into(cv2.cvtColor(src.planes[0], code, dst=block), block)
        if block is dst.block:
            return
        y, u, v = _i420_planes(block, w, h)
        np.copyto(dst.planes[0], y)
        if dst.fmt == "I420":
            np.copyto(dst.planes[1], u)
            np.copyto(dst.planes[2], v)
        else:
            _into(cv2.merge((u, v), dst=dst.planes[1]), dst.planes[1])

    def _yuv_to_packed(self, src: Image, dst: Image) -> None:
        target = _packed_name(dst.fmt)
        out = dst.planes[0]
        if src.fmt == "NV12":
            code = _code(f"YUV2{target}_NV12")
            _into(cv2.cvtColorTwoPlane(src.planes[0], src.planes[1], code, dst=out), out)
            return
        block = src.block
        if block is None:
            block = self._block(src.width, src.height)
            for plane, part in zip(src.planes, _i420_planes(block, src.width, src.height)):
                np.copyto(part, plane)
        _into(cv2.cvtColor(block, _code(f"YUV2{target}_I420"), dst=out), out)

    def _yuv_to_packed_matrix(self, src: Image, dst: Image) -> None:
        w, h = src.width, src.height
        if src.fmt == "I420":
            u, v = src.planes[1], src.planes[2]
        else:
            u, v = cv2.split(src.planes[1])
        up = [cv2.resize(c, (w, h), interpolation=cv2.INTER_LINEAR) for c in (u, v)]
        rgb = cv2.transform(cv2.merge([src.planes[0], *up]), yuv_to_rgb_matrix(self.matrix))
        order, channels = PACKED[dst.fmt]
        if order == "RGB" and channels == 3:
            np.copyto(dst.planes[0], rgb)
        else:
            code = _code(f"RGB2{_packed_name(dst.fmt)}")
            _into(cv2.cvtColor(rgb, code, dst=dst.planes[0]), dst.planes[0])

    @staticmethod
    def _yuv_to_yuv(src: Image, dst: Image) -> None:
        np.copyto(dst.planes[0], src.planes[0])
        if dst.fmt == "NV12":  # from I420
            _into(cv2.merge((src.planes[1], src.planes[2]), dst=dst.planes[1]), dst.planes[1])
        else:  # NV12 -> I420
            for i in (0, 1):
                _into(cv2.extractChannel(src.planes[1], i, dst=dst.planes[1 + i]), dst.planes[1 + i])


def _i420_planes(block: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    flat = block.reshape(-1)
    n, q = width * height, width * height // 4
    return (flat[:n].reshape(height, width), flat[n : n + q].reshape(height // 2, width // 2),
            flat[n + q : n + 2 * q].reshape(height // 2, width // 2))


# GRAY8 is full range (GStreamer's default colorimetry for it), Y of BT.601 limited is not.
_LIMITED_TO_FULL = np.clip(np.round((np.arange(256) - 16) * 255 / 219), 0, 255).astype(np.uint8)
_FULL_TO_LIMITED = np.round(16 + np.arange(256) * 219 / 255).astype(np.uint8)


def convert(src: Image, dst: Image, matrix: YuvMatrix = BT601) -> None:
    """One-off conversion (and scaling) of ``src`` into ``dst``; use a :class:`Converter` for streams."""
    Converter(src.fmt, (src.width, src.height), dst.fmt, (dst.width, dst.height), matrix)(src, dst)
