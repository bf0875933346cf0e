"""A ROS image message as what ``FrameGate.push`` takes (``leangate_client.bag``).

``sensor_msgs/msg/Image`` in rgb8, bgr8, rgba8, bgra8, mono8 (8UC1), mono16 (16UC1, either byte
order) and the 8-bit Bayer encodings; ``sensor_msgs/msg/CompressedImage`` holding a JPEG or a
PNG picture (told by its first bytes, the ``format`` field only for the message). Rows may be
padded (``step`` larger than width times the pixel size). A message this cannot read raises
``ImageError`` naming what it holds.

Header stamps are read straight from the serialised bytes (``header_stamp``): a partner camera's
messages are matched by stamp without being decoded.
"""

from __future__ import annotations

import struct
from typing import Optional, Tuple

#: The two image types, as rosbags names them.
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)

#: Image encodings → (FrameGate raw format, channels, bytes per channel).
RAW_ENCODINGS = {
    "rgb8": ("RGB", 3, 1),
    "bgr8": ("BGR", 3, 1),
    "rgba8": ("RGBA", 4, 1),
    "bgra8": ("BGRA", 4, 1),
    "mono8": ("GRAY8", 1, 1),
    "8uc1": ("GRAY8", 1, 1),
    "mono16": ("GRAY16_LE", 1, 2),
    "16uc1": ("GRAY16_LE", 1, 2),
}
#: Bayer encodings → the colour of the pixel at (row, column) (0,0), (0,1), (1,0), (1,1).
BAYER = {
    "bayer_rggb8": "RGGB",
    "bayer_bggr8": "BGGR",
    "bayer_gbrg8": "GBRG",
    "bayer_grbg8": "GRBG",
}
SUPPORTED = (
    "sensor_msgs/Image " + ", ".join(k for k in RAW_ENCODINGS if not k[0].isdigit())
    + " (8UC1, 16UC1), " + ", ".join(BAYER) + "; sensor_msgs/CompressedImage jpeg, png"
)


class ImageError(ValueError):
    """A message that is not a picture the gate can take (its encoding, or malformed)."""


def header_stamp(raw: bytes, ros2: bool) -> Optional[int]:
    """The ``header.stamp`` (ns) of a serialised message whose first field is a
    ``std_msgs/Header`` (images, camera_info, IMU, ...); None when it is zero or unreadable.
    CDR (ROS 2): 4 bytes of encapsulation, then int32 sec, uint32 nanosec (little or big
    endian, as the encapsulation says); ROS 1: uint32 seq, then uint32 secs, nsecs."""
    try:
        if ros2:
            endian = "<" if raw[1] == 1 else ">"
            sec, nsec = struct.unpack_from(endian + "iI", raw, 4)
        else:
            sec, nsec = struct.unpack_from("<II", raw, 4)
    except (struct.error, IndexError):
        return None
    if nsec >= 1_000_000_000 or sec < 0:
        return None
    t = sec * 1_000_000_000 + nsec
    return t or None


def _bayer_rgb(np, gray, pattern: str):
    """Half-size RGB of a Bayer mosaic: each 2x2 cell gives one pixel (its R, the mean of its
    two Gs, its B). Cheap, and enough to gate on (the gate scales the frame down anyway)."""
    h, w = gray.shape
    cells = gray[: h - h % 2, : w - w % 2].reshape(h // 2, 2, w // 2, 2).astype(np.uint16)
    at = {(0, 0): pattern[0], (0, 1): pattern[1], (1, 0): pattern[2], (1, 1): pattern[3]}
    out = np.empty((h // 2, w // 2, 3), dtype=np.uint8)
    g = [cells[:, r, :, c] for (r, c), col in at.items() if col == "G"]
    for (r, c), col in at.items():
        if col == "R":
            out[:, :, 0] = cells[:, r, :, c]
        elif col == "B":
            out[:, :, 2] = cells[:, r, :, c]
    out[:, :, 1] = (g[0] + g[1] + 1) // 2
    return out


def sniff(data) -> Optional[str]:
    """``"jpeg"`` or ``"png"`` from a picture's first bytes, else None."""
    head = bytes(data[:8])
    if head[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if head == b"\x89PNG\r\n\x1a\n":
        return "png"
    return None


def to_push(np, msg, msgtype: str) -> Tuple[object, str]:
    """``(image, format)`` for ``FrameGate.push`` from a deserialised image message."""
    if msgtype == COMPRESSED:
        fmt = str(msg.format)
        data = msg.data
        if "compresseddepth" in fmt.lower().replace(" ", ""):
            raise ImageError(
                f"CompressedImage format {fmt!r} is a compressed depth image, not a colour or "
                f"grey picture (supported: {SUPPORTED})"
            )
        kind = sniff(data)
        if kind is None:
            raise ImageError(
                f"CompressedImage format {fmt!r}: the data is neither a JPEG nor a PNG picture "
                f"(first bytes {bytes(data[:4]).hex()}; supported: {SUPPORTED})"
            )
        return np.asarray(data, dtype=np.uint8).tobytes(), kind
    enc = str(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    key = enc.lower()
    if key in RAW_ENCODINGS:
        fmt, ch, size = RAW_ENCODINGS[key]
    elif key in BAYER:
        fmt, ch, size = "bayer", 1, 1
    else:
        raise ImageError(f"Image encoding {enc!r} cannot be read (supported: {SUPPORTED})")
    row = w * ch * size
    if h < 1 or w < 1 or step < row or data.size < (h - 1) * step + row:
        raise ImageError(
            f"a malformed {enc} Image: {w}x{h}, step {step}, {data.size} bytes of data (a row "
            f"needs {row} bytes)"
        )
    if data.size < h * step:  # the last row without its padding
        data = np.concatenate([data, np.zeros(h * step - data.size, dtype=np.uint8)])
    rows = data[: h * step].reshape(h, step)[:, :row]
    if size == 2:
        dtype = ">u2" if int(msg.is_bigendian) else "<u2"
        return np.ascontiguousarray(rows).view(dtype).reshape(h, w).astype("<u2"), fmt
    if fmt == "bayer":
        if h < 2 or w < 2:
            raise ImageError(f"a {enc} Image of {w}x{h} is too small for a Bayer mosaic")
        return _bayer_rgb(np, rows, BAYER[key]), "RGB"
    return (rows.reshape(h, w) if ch == 1 else rows.reshape(h, w, ch)), fmt
