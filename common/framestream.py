"""The simulator's camera frame stream: the wire format, defined once for its writer and its reader.

The vehicle (:mod:`sim.mavlink_vehicle`) writes it to a TCP client, the companion's camera (``sim://HOST:PORT``,
:class:`nav.companion.SimFrameClient`) reads it.  Each frame is a 24-byte little-endian header ``<4sqIIi``: magic
``b"GSOF"``, exposure time ``t_us`` (int64, vehicle clock), width, height, channels (1 gray, 3 BGR), followed by
``width * height * channels`` bytes of the image (uint8, row-major).  There is no resynchronisation marker inside
the stream: a reader that meets a corrupt header reconnects.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

FRAME_MAGIC = b"GSOF"
FRAME_HEADER = struct.Struct("<4sqIIi")
FRAME_HEADER_SIZE = FRAME_HEADER.size  # 24 bytes
FRAME_CHANNELS = (1, 3)  # gray, BGR
MAX_FRAME_SIDE_PX = 16384  # a larger width or height is taken for a corrupt header


class CorruptFrameStream(OSError):
    """A header that is not one of this format: the stream must be reconnected to resynchronise."""


class FrameHeader(NamedTuple):
    t_us: int
    width_px: int
    height_px: int
    channels: int

    @property
    def payload_size(self) -> int:
        """Bytes of image data that follow the header."""
        return self.width_px * self.height_px * self.channels


def encode_frame(t_us: int, image: NDArray[np.uint8]) -> bytes:
    """Header and image bytes of one frame (``image``: height x width gray, or height x width x 3 BGR, uint8)."""
    h, w = image.shape[:2]
    ch = 1 if image.ndim == 2 else image.shape[2]
    return FRAME_HEADER.pack(FRAME_MAGIC, t_us, w, h, ch) + np.ascontiguousarray(image, dtype=np.uint8).tobytes()


def decode_header(head: bytes) -> FrameHeader:
    """The header of ``head`` (:data:`FRAME_HEADER_SIZE` bytes); :class:`CorruptFrameStream` when it is not one."""
    if len(head) != FRAME_HEADER_SIZE:
        raise CorruptFrameStream(f"frame stream header of {len(head)} bytes, expected {FRAME_HEADER_SIZE}")
    magic, t_us, w, h, ch = FRAME_HEADER.unpack(head)
    if magic != FRAME_MAGIC or not (0 < w <= MAX_FRAME_SIDE_PX and 0 < h <= MAX_FRAME_SIDE_PX
                                    and ch in FRAME_CHANNELS):
        raise CorruptFrameStream("corrupt frame stream header")
    return FrameHeader(int(t_us), int(w), int(h), int(ch))


def decode_image(header: FrameHeader, data: bytes) -> NDArray[np.uint8]:
    """The image of ``data`` (:attr:`FrameHeader.payload_size` bytes following ``header``)."""
    img = np.frombuffer(data, np.uint8)
    shape = (header.height_px, header.width_px)
    return img.reshape(shape if header.channels == 1 else (*shape, header.channels))
