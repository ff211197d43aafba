"""Decoding of sensor_msgs/Image and CompressedImage payloads to 8-bit gray."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagtrail.errors import SourceError
from tagtrail.vision.images import RawImage, decode_compressed, decode_raw


@pytest.fixture(scope="module")
def bgr(realdata: Path) -> np.ndarray:
    img = cv2.imread(str(realdata / "upenn_ar_tag36h11_id12_seq/frames/frame0000.jpg"))
    return np.ascontiguousarray(img[100:160, 200:280])  # small crop, 60x80x3


def raw(img: np.ndarray, encoding: str, pad: int = 0) -> RawImage:
    h = img.shape[0]
    rows = img.reshape(h, -1).view(np.uint8)
    data = np.zeros((h, rows.shape[1] + pad), np.uint8)
    data[:, : rows.shape[1]] = rows
    return RawImage(
        "raw",
        data.tobytes(),
        encoding,
        img.shape[1],
        h,
        rows.shape[1] + pad,
        bigendian=img.dtype.byteorder == ">",
    )


@pytest.mark.parametrize(
    ("encoding", "convert"),
    [
        ("bgr8", lambda b: b),
        ("8UC3", lambda b: b),
        ("rgb8", lambda b: b[..., ::-1]),
        ("bgra8", lambda b: cv2.cvtColor(b, cv2.COLOR_BGR2BGRA)),
        ("rgba8", lambda b: cv2.cvtColor(b, cv2.COLOR_BGR2RGBA)),
    ],
)
def test_color_encodings_give_the_same_gray(bgr: np.ndarray, encoding: str, convert) -> None:
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    for pad in (0, 5):  # step > width * channels: padding ignored
        img = raw(np.ascontiguousarray(convert(bgr)), encoding, pad).decode()
        assert img.dtype == np.uint8 and img.flags.c_contiguous
        np.testing.assert_array_equal(img, want)


def test_mono_encodings(bgr: np.ndarray) -> None:
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(raw(gray, "mono8", pad=3).decode(), gray)
    np.testing.assert_array_equal(raw(gray, "8UC1").decode(), gray)
    # 16-bit: scaled by the image maximum (e.g. a 10-bit IR camera uses the full 8-bit range)
    want = gray * 255.0 / gray.max()
    for scale, enc in ((257, "mono16"), (4, "16UC1")):
        wide = gray.astype(np.uint16) * scale
        for dtype in ("<u2", ">u2"):  # is_bigendian honoured
            out = raw(wide.astype(dtype), enc).decode()
            assert np.abs(out.astype(int) - want).max() <= 1


def test_compressed_jpeg_and_png(bgr: np.ndarray) -> None:
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    png = cv2.imencode(".png", gray)[1].tobytes()
    np.testing.assert_array_equal(decode_compressed(png, "png"), gray)
    png = cv2.imencode(".png", bgr)[1].tobytes()
    assert np.abs(decode_compressed(png, "bgr8; png compressed").astype(int) - gray).max() <= 1
    jpg = cv2.imencode(".jpg", bgr)[1].tobytes()
    want = cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(
        RawImage("compressed", jpg, "rgb8; jpeg compressed bgr8").decode(), want
    )


def test_raw_image_is_small_to_pickle() -> None:
    r = RawImage("file", "/some/frame0001.jpg")
    assert pickle.loads(pickle.dumps(r)) == r
    assert len(pickle.dumps(r)) < 200


def test_bad_images_raise_source_error(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="unsupported Image encoding '32FC1'"):
        decode_raw(b"\0" * 16, "32FC1", 2, 2)
    with pytest.raises(SourceError, match="too few"):
        decode_raw(b"\0" * 10, "mono8", 4, 4)
    with pytest.raises(SourceError, match="cannot decode a CompressedImage of format 'jpeg'"):
        decode_compressed(b"not a jpeg", "jpeg")
    bad = tmp_path / "x.png"
    bad.write_bytes(b"garbage")
    with pytest.raises(SourceError, match=r"x\.png: cannot read image"):
        RawImage("file", str(bad)).decode()
