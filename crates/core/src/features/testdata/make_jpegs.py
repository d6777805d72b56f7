#!/usr/bin/env python3
"""Writes the small chroma-subsampled JPEG fixtures of `image_io`'s tests (the `image` crate's
encoder only writes 4:4:4) and, for each, the Y plane libjpeg-turbo decodes from it
(OpenCV `IMREAD_GRAYSCALE`), as a binary PGM: an independent anchor for seasonloc's Y-only
decoding. Run once with OpenCV 4.x (never a dependency of seasonloc):

    python make_jpegs.py   # in this folder
"""
import cv2
import numpy as np

W, H = 45, 29  # odd sizes: partial MCUs on both axes
rng = np.random.default_rng(7)
x, y = np.meshgrid(np.arange(W), np.arange(H))
bgr = np.stack(
    [
        (x * 255 // W) ^ (y * 3 % 64),
        (128 + 100 * np.sin(x / 4.0) * np.cos(y / 3.0)).astype(int),
        np.where((x // 9 + y // 7) % 2 == 0, 220, 30),
    ],
    axis=-1,
)
bgr = np.clip(bgr + rng.integers(-12, 13, size=bgr.shape), 0, 255).astype(np.uint8)
for name, factor in [
    ("420", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420),
    ("422", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422),
    ("440", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_440),
    ("444", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
]:
    ok, data = cv2.imencode(
        ".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, factor]
    )
    assert ok
    path = f"sampling_{name}.jpg"
    data.tofile(path)
    gray = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    with open(f"sampling_{name}_y.pgm", "wb") as f:
        f.write(b"P5\n%d %d\n255\n" % (W, H))
        f.write(gray.tobytes())
