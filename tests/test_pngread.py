"""The fast PNG path of the label stage and the evaluation (tdof20.annotate.pngread): the same
arrays as tdof20.formats.decode_png (OpenCV) on every PNG tdof20 writes, the usual decoder (and
its errors) on anything else, and mask IoUs equal to the whole-image count."""

import cv2
import numpy as np
import pytest

from tdof20.annotate.pngread import _filtered_rows, decode_png_fast, mask_rows, mask_rows_iou
from tdof20.errors import TdofError
from tdof20.formats import decode_png, encode_png


def _images(rng):
    depth = rng.integers(0, 65535, (37, 53), dtype=np.uint16)
    depth[5:9] = 0
    mask = np.zeros((40, 60), np.uint8)
    mask[10:20, 55:60] = 255            # touches the right border
    mask[25:31, 3:9] = 255
    rgb = rng.integers(0, 255, (23, 31, 3), dtype=np.uint8)
    grey = rng.integers(0, 255, (17, 19), dtype=np.uint8)
    return {"depth": depth, "mask": mask, "rgb": rgb, "any": grey}


@pytest.mark.parametrize("level", [0, 1, 3])
def test_fast_path_gives_the_decoders_arrays(level):
    rng = np.random.default_rng(level)
    for kind, img in _images(rng).items():
        data = encode_png(img, level)
        assert _filtered_rows(data, kind) is not None          # the fast path takes it
        fast, ref = decode_png_fast(data, "x.png", kind), decode_png(data, "x.png", kind)
        assert fast.dtype == ref.dtype and fast.shape == ref.shape and np.array_equal(fast, ref)
        assert np.array_equal(decode_png_fast(data, "x.png", "any"), decode_png(data, "x.png", "any"))


def test_other_pngs_and_broken_ones_go_the_usual_way(tmp_path):
    rng = np.random.default_rng(3)
    depth = rng.integers(0, 4000, (30, 40), dtype=np.uint16)
    ok, buf = cv2.imencode(".png", depth)                       # libpng's filters, not only Sub
    data = buf.tobytes()
    assert np.array_equal(decode_png_fast(data, "d.png", "depth"), depth)
    good = encode_png(depth)
    # a flipped byte in the image data (CRC mismatch), a short file, a JPEG: decode_png's errors
    bad = bytearray(good)
    bad[60] ^= 0xFF
    for broken in (bytes(bad), good[:len(good) // 2], b"\xff\xd8\xff\xe0" + good[4:]):
        assert _filtered_rows(broken, "depth") is None
        with pytest.raises(TdofError) as want:
            decode_png(broken, "d.png", "depth")
        with pytest.raises(TdofError) as got:
            decode_png_fast(broken, "d.png", "depth")
        assert str(got.value) == str(want.value)
    # the wrong kind: decode_png's message
    with pytest.raises(TdofError, match="expected an 8-bit single-channel mask"):
        decode_png_fast(good, "d.png", "mask")


def test_mask_rows_iou_matches_the_whole_image(tmp_path):
    rng = np.random.default_rng(5)
    h, w = 48, 64
    masks = []
    for k in range(6):
        m = np.zeros((h, w), np.uint8)
        if k:
            y, x = rng.integers(0, h - 10), rng.integers(0, w - 10)
            m[y:y + rng.integers(1, 12), x:x + rng.integers(1, 20)] = 255
        masks.append(m)
    masks.append(np.full((h, w), 255, np.uint8))
    paths = []
    for k, m in enumerate(masks):
        p = tmp_path / f"m{k}.png"
        p.write_bytes(encode_png(m))
        paths.append(p)
    ok, buf = cv2.imencode(".png", masks[2])                    # one written by OpenCV
    (tmp_path / "cv.png").write_bytes(buf.tobytes())
    paths.append(tmp_path / "cv.png")
    masks.append(masks[2])
    for a, pa in zip(masks, paths):
        for b, pb in zip(masks, paths):
            u = np.count_nonzero((a > 0) | (b > 0))
            want = 1.0 if u == 0 else np.count_nonzero((a > 0) & (b > 0)) / u
            assert mask_rows_iou(mask_rows(pa), mask_rows(pb)) == want


def test_mask_rows_holds_every_pixel_and_nothing_else(tmp_path):
    """The box mask_rows decodes holds each non-zero pixel, also of masks touching a border."""
    rng = np.random.default_rng(8)
    for k in range(40):
        m = np.zeros((30, 50), np.uint8)
        for _ in range(int(rng.integers(0, 4))):
            y, x = rng.integers(-5, 30), rng.integers(-5, 50)
            m[max(y, 0):y + rng.integers(1, 15), max(x, 0):x + rng.integers(1, 25)] = 255
        p = tmp_path / f"{k}.png"
        p.write_bytes(encode_png(m))
        v0, u0, block, shape = mask_rows(p)
        assert shape == m.shape
        whole = np.zeros(m.shape, bool)
        whole[v0:v0 + block.shape[0], u0:u0 + block.shape[1]] = block
        assert np.array_equal(whole, m > 0)
