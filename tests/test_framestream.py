"""The simulator's camera frame stream format (common.framestream): round trips and corrupt headers."""

from __future__ import annotations

import numpy as np
import pytest

from common.framestream import (
    FRAME_HEADER_SIZE,
    MAX_FRAME_SIDE_PX,
    CorruptFrameStream,
    decode_header,
    decode_image,
    encode_frame,
)


@pytest.mark.parametrize("shape", [(48, 64), (48, 64, 3)])
def test_a_frame_round_trips(shape: tuple[int, ...]) -> None:
    img = np.random.default_rng(7).integers(0, 256, shape, dtype=np.uint8)
    data = encode_frame(-1_234_567_890_123, img)
    assert FRAME_HEADER_SIZE == 24 and data[:4] == b"GSOF"
    header = decode_header(data[:FRAME_HEADER_SIZE])
    assert header.t_us == -1_234_567_890_123 and (header.height_px, header.width_px) == (48, 64)
    assert len(data) == FRAME_HEADER_SIZE + header.payload_size
    np.testing.assert_array_equal(decode_image(header, data[FRAME_HEADER_SIZE:]), img)


def test_a_corrupt_header_is_an_os_error_that_asks_for_a_reconnect() -> None:
    good = encode_frame(0, np.zeros((4, 4), np.uint8))[:FRAME_HEADER_SIZE]
    for bad in (b"XXXX" + good[4:], good[:-1], encode_frame(0, np.zeros((4, 4, 2), np.uint8))[:FRAME_HEADER_SIZE],
                encode_frame(0, np.zeros((1, MAX_FRAME_SIDE_PX + 1), np.uint8))[:FRAME_HEADER_SIZE]):
        with pytest.raises(CorruptFrameStream):
            decode_header(bad)
    assert issubclass(CorruptFrameStream, OSError)
