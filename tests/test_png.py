"""The hand-written PNG encoder: exact round trips through two independent decoders."""

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from tdof20.formats.io import decode_png, encode_png


@pytest.mark.parametrize("shape,dtype", [((1, 1, 3), np.uint8), ((5, 3, 3), np.uint8), ((48, 64, 3), np.uint8),
                                         ((1, 1), np.uint16), ((7, 9), np.uint16), ((48, 64), np.uint16),
                                         ((7, 9), np.uint8), ((48, 64), np.uint8)])
@pytest.mark.parametrize("level", [0, 1, 3])
def test_round_trip_exact(shape, dtype, level):
    rng = np.random.default_rng(sum(shape) + level)
    img = rng.integers(0, np.iinfo(dtype).max + 1, size=shape, dtype=np.int64).astype(dtype)
    img.flat[0] = np.iinfo(dtype).max  # the extremes survive the Sub filter's wrap-around
    img.flat[-1] = 0
    data = encode_png(img, level)
    assert np.array_equal(decode_png(data), img)  # OpenCV (libpng)
    pil = np.asarray(Image.open(io.BytesIO(data)))  # Pillow, its own decoder
    assert np.array_equal(pil.astype(dtype), img)
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == dtype


def test_smooth_images_compress():
    y, x = np.mgrid[0:120, 0:160]
    depth = (500 + x + 2 * y).astype(np.uint16)
    assert len(encode_png(depth)) < depth.nbytes / 10


def test_rejects_what_png_cannot_hold():
    for bad in (np.zeros((4, 4, 4), np.uint8), np.zeros((4, 4), np.float32), np.zeros((0, 4), np.uint8),
                np.zeros((4, 4, 3), np.uint16)):
        with pytest.raises(ValueError):
            encode_png(bad)


def test_header_check_reads_kind_and_size_without_decoding(tmp_path):
    from tdof20.errors import TdofError
    from tdof20.formats.io import png_header, write_png

    write_png(tmp_path / "rgb.png", np.zeros((5, 7, 3), np.uint8))
    write_png(tmp_path / "depth.png", np.zeros((5, 7), np.uint16))
    write_png(tmp_path / "mask.png", np.zeros((5, 7), np.uint8))
    assert png_header(tmp_path / "rgb.png", "rgb") == (5, 7)
    assert png_header(tmp_path / "depth.png", "depth") == (5, 7)
    assert png_header(tmp_path / "mask.png", "mask") == (5, 7)
    with pytest.raises(TdofError, match=r"mask\.png: expected a 16-bit single-channel depth PNG, found a grey PNG "
                                        r"of 8 bits per sample$"):
        png_header(tmp_path / "mask.png", "depth")
    with pytest.raises(TdofError, match=r"depth\.png: expected an 8-bit colour PNG, found a grey PNG of 16 bits"):
        png_header(tmp_path / "depth.png", "rgb")
    ok, jpg = cv2.imencode(".jpg", np.zeros((5, 7, 3), np.uint8))
    (tmp_path / "photo.png").write_bytes(jpg.tobytes())
    with pytest.raises(TdofError, match=r"photo\.png: not a PNG file \(bad signature\): it holds a JPEG image"):
        png_header(tmp_path / "photo.png")
    with pytest.raises(TdofError, match="it holds a JPEG image"):  # the full decoder says the same
        decode_png(jpg.tobytes(), tmp_path / "photo.png")
    (tmp_path / "cut.png").write_bytes((tmp_path / "rgb.png").read_bytes()[:20])
    with pytest.raises(TdofError, match=r"cut\.png: corrupt PNG: no image header"):
        png_header(tmp_path / "cut.png")
