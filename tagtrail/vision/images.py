"""Undecoded frames and their decoding to 8-bit grayscale.

A :class:`RawImage` is what a source hands out for an image frame: the pixel bytes of a
``sensor_msgs/Image``, the bytes of a ``sensor_msgs/CompressedImage`` or an image file path. It is
small to pickle and is decoded by :meth:`RawImage.decode` — in a worker process, so that the
parent only reads the bag.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from tagtrail.errors import SourceError

U8 = NDArray[np.uint8]

# encoding → (channels, bytes per channel, cv2 conversion to gray or None)
_RAW: dict[str, tuple[int, int, int | None]] = {
    "mono8": (1, 1, None),
    "8UC1": (1, 1, None),
    "mono16": (1, 2, None),
    "16UC1": (1, 2, None),
    "rgb8": (3, 1, cv2.COLOR_RGB2GRAY),
    "bgr8": (3, 1, cv2.COLOR_BGR2GRAY),
    "8UC3": (3, 1, cv2.COLOR_BGR2GRAY),
    "rgba8": (4, 1, cv2.COLOR_RGBA2GRAY),
    "bgra8": (4, 1, cv2.COLOR_BGRA2GRAY),
    "8UC4": (4, 1, cv2.COLOR_BGRA2GRAY),
    "rgb16": (3, 2, cv2.COLOR_RGB2GRAY),
    "bgr16": (3, 2, cv2.COLOR_BGR2GRAY),
    "16UC3": (3, 2, cv2.COLOR_BGR2GRAY),
    "rgba16": (4, 2, cv2.COLOR_RGBA2GRAY),
    "bgra16": (4, 2, cv2.COLOR_BGRA2GRAY),
    # OpenCV names Bayer patterns by the second row; this is cv_bridge's mapping.
    "bayer_rggb8": (1, 1, cv2.COLOR_BayerBG2GRAY),
    "bayer_bggr8": (1, 1, cv2.COLOR_BayerRG2GRAY),
    "bayer_gbrg8": (1, 1, cv2.COLOR_BayerGR2GRAY),
    "bayer_grbg8": (1, 1, cv2.COLOR_BayerGB2GRAY),
    "yuv422": (2, 1, cv2.COLOR_YUV2GRAY_UYVY),
    "uyvy": (2, 1, cv2.COLOR_YUV2GRAY_UYVY),
    "yuv422_yuy2": (2, 1, cv2.COLOR_YUV2GRAY_YUY2),
    "yuyv": (2, 1, cv2.COLOR_YUV2GRAY_YUY2),
}
ENCODINGS = tuple(_RAW)


@dataclass(frozen=True)
class RawImage:
    """An undecoded image frame.

    ``kind="raw"``: ``data`` = pixel bytes of a ``sensor_msgs/Image`` with ``encoding``, ``width``,
    ``height``, ``step`` (bytes per row) and ``bigendian``; ``kind="compressed"``: ``data`` = bytes
    of a ``sensor_msgs/CompressedImage``, ``encoding`` = its ``format``; ``kind="file"``:
    ``data`` = a path to a jpg/png file.
    """

    kind: Literal["raw", "compressed", "file"]
    data: bytes | str
    encoding: str = ""
    width: int = 0
    height: int = 0
    step: int = 0
    bigendian: bool = False

    def decode(self) -> U8:
        """The frame as a C-contiguous ``(height, width)`` uint8 grayscale image."""
        if self.kind == "file":
            path = str(self.data)
            img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise SourceError(f"{path}: cannot read image (not a jpg/png?)")
            return np.ascontiguousarray(img)
        assert isinstance(self.data, bytes), "a raw or compressed image holds bytes"
        if self.kind == "compressed":
            return decode_compressed(bytes(self.data), self.encoding)
        return decode_raw(
            bytes(self.data), self.encoding, self.width, self.height, self.step, self.bigendian
        )


def frame_size(raw: RawImage) -> tuple[int, int] | None:
    """``(width, height)`` that ``raw`` will decode to, read without decoding it: a raw
    ``Image``'s fields, a PNG's IHDR or a JPEG's start-of-frame (:func:`encoded_size`) of a
    ``CompressedImage`` (after ``compressedDepth``'s 12-byte prefix) or of an image file. None
    when no such header says (another format, a cut header, an unreadable file).

    Both the offline extract (``detect_chunk``) and the live localize node check this size
    against the camera's before decoding: a small file can claim a huge image."""
    if raw.kind == "raw":
        return raw.width, raw.height
    if raw.kind == "compressed":
        assert isinstance(raw.data, bytes)
        data = bytes(raw.data)
        return encoded_size(data[12:] if "compresseddepth" in raw.encoding.lower() else data)
    try:
        with open(str(raw.data), "rb") as f:
            head = f.read(1 << 16)
            size = encoded_size(head)
            if size is None and len(head) == 1 << 16:  # a JPEG's frame header after big EXIF
                size = encoded_size(head + f.read())
    except OSError:
        return None
    return size


def decode_compressed(data: bytes, fmt: str) -> U8:
    """``sensor_msgs/CompressedImage`` bytes (jpeg/png; ``compressedDepth`` too) → gray uint8."""
    if "compresseddepth" in fmt.lower():
        data = data[12:]  # image_transport's compressedDepth prefixes a 12-byte config header
    if not data:
        raise SourceError(f"an empty CompressedImage (format {fmt!r}): no image bytes")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise SourceError(f"cannot decode a CompressedImage of format {fmt!r} (jpeg/png expected)")
    return np.ascontiguousarray(img)


def decode_raw(
    data: bytes, encoding: str, width: int, height: int, step: int = 0, bigendian: bool = False
) -> U8:
    """``sensor_msgs/Image`` pixel bytes → gray uint8 ``(height, width)``.

    Rows are ``step`` bytes apart (padding ignored). 16-bit images are scaled by their maximum to
    use the full 8-bit range (the detector thresholds locally, so only contrast matters).
    """
    enc = encoding.strip()
    spec = _RAW.get(enc) or _RAW.get(enc.lower())
    if spec is None:
        raise SourceError(
            f"unsupported Image encoding {encoding!r} (supported: {', '.join(ENCODINGS)})"
        )
    ch, bpc, code = spec
    row = width * ch * bpc
    step = step or row
    buf = np.frombuffer(data, np.uint8)
    if width <= 0 or height <= 0 or step < row or buf.size < step * (height - 1) + row:
        raise SourceError(
            f"Image {width}x{height} {enc} step {step}: {buf.size} data bytes is too few"
        )
    if buf.size < step * height:  # a last row without padding
        buf = np.concatenate([buf, np.zeros(step * height - buf.size, np.uint8)])
    rows = buf[: step * height].reshape(height, step)[:, :row]
    if bpc == 2:
        wide = np.ascontiguousarray(rows).view(">u2" if bigendian else "<u2")
        top = max(int(wide.max()), 1)
        rows = (wide.astype(np.float32) * (255.0 / top) + 0.5).astype(np.uint8)
    img = np.ascontiguousarray(rows).reshape(height, width, ch)
    if code is None:
        return np.ascontiguousarray(img[:, :, 0])
    return np.ascontiguousarray(cv2.cvtColor(img if ch > 1 else img[:, :, 0], code))


_PNG = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (C4 DHT, C8 JPG, CC DAC are not frames)
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def encoded_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG's IHDR or a JPEG's start-of-frame, without decoding;
    None if ``data`` is neither (or its header is cut)."""
    if data[:8] == _PNG:
        if data[12:16] != b"IHDR" or len(data) < 24:
            return None
        w, h = struct.unpack_from(">II", data, 16)
        return w, h
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before
            return None
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            i += 2
            continue
        if marker in _SOF:  # length (2), precision (1), height (2), width (2)
            h, w = struct.unpack_from(">HH", data, i + 5)
            return (w, h) if w and h else None  # height 0: given later by a DNL (unsupported)
        i += 2 + struct.unpack_from(">H", data, i + 2)[0]
    return None
