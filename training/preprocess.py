"""The element's preprocessing in Python (numpy; pillow only to decode files): the same resampling
taps as `src/preprocess.rs` -- short-side-crop (or stretch) to IN_W x IN_H, exact area averaging
when downscaling, bilinear at pixel centres when upscaling -- so training sees what the element
feeds the model. tests/training_preprocess.rs checks it against the crate to within 1/255.
Frames are kept as uint8 HWC RGB; `normalise` gives the model's tensor ((x/255 - MEAN) / STD).
"""
import functools
import math
import os

import numpy as np

from .config import IN_H, IN_W, MEAN, RESIZE, STD


def taps(src_len, dst_len, off, span):
    """[dst_len, src_len] resampling weights, as make_taps in src/preprocess.rs."""
    scale = span / dst_len  # source pixels per output pixel
    m = np.zeros((dst_len, src_len), np.float64)
    for o in range(dst_len):
        if scale > 1.0:
            a = off + o * scale
            b = a + scale
            i0 = max(int(math.floor(a)), 0)
            i1 = min(int(math.ceil(b)), src_len)
            for i in range(i0, i1):
                m[o, i] = max(min(i + 1.0, b) - max(float(i), a), 0.0)
            m[o] /= m[o].sum()
        else:
            c = min(max(off + (o + 0.5) * scale - 0.5, 0.0), src_len - 1.0)
            i0 = int(math.floor(c))
            f = c - i0
            if i0 + 1 < src_len and f > 0.0:
                m[o, i0], m[o, i0 + 1] = 1.0 - f, f
            else:
                m[o, i0] = 1.0
    return m


@functools.lru_cache(maxsize=32)
def _weights(sw, sh, w, h, resize):
    if resize == "stretch":
        xo, xs, yo, ys = 0.0, float(sw), 0.0, float(sh)
    else:  # short-side-crop: scale the short side, centre-crop the long one
        s = min(sw / w, sh / h)
        cw, ch = w * s, h * s
        xo, xs, yo, ys = (sw - cw) / 2.0, cw, (sh - ch) / 2.0, ch
    return taps(sw, w, xo, xs), taps(sh, h, yo, ys)


def resize_array(img, w=IN_W, h=IN_H, resize=RESIZE):
    """uint8 [H, W, 3] RGB -> uint8 [h, w, 3]: the element's resampling, rounded to 8 bits."""
    sh, sw = img.shape[:2]
    wx, wy = _weights(sw, sh, w, h, resize)
    rows = wy @ img.reshape(sh, sw * 3).astype(np.float64)  # [h, sw*3]
    out = np.matmul(wx[None], rows.reshape(h, sw, 3))  # [h, w, 3]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def resize_image(im, w=IN_W, h=IN_H):
    """PIL image -> uint8 [h, w, 3]."""
    return resize_array(np.asarray(im.convert("RGB")), w, h)


def load_resized(path, w=IN_W, h=IN_H):
    from PIL import Image  # only here: the resampling itself needs numpy alone

    return resize_image(Image.open(path), w, h)


def normalise(frames_u8):
    """uint8 [N, H, W, 3] -> float32 [N, 3, H, W], (x/255 - MEAN) / STD: the tensor the model sees."""
    x = frames_u8.astype(np.float32) / 255.0
    x = (x - np.array(MEAN, np.float32)) / np.array(STD, np.float32)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))


def read_list(seq, name="rgb.txt"):
    """Image paths of a TUM-layout list, in order (relative entries resolved against `seq`)."""
    rows = []
    for line in open(os.path.join(seq, name)):
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append(os.path.join(seq, line.split()[1]))
    return rows
