"""The companion's ground-station commands (issue 23, link hygiene): a designated pixel outside the image is refused
(acknowledged DENIED) and designates nothing; one inside is accepted; the acknowledgement goes to the sender."""

from __future__ import annotations

import time
from typing import Any

import pytest

from nav.signing import CommandEndpoint
from tests.test_link import free_udp_port


def test_the_companion_refuses_a_designated_pixel_outside_the_image(gsoe_config, tmp_path):
    """COMMAND_LONG MAV_CMD_USER_1 with the issue's pixel (1e9, -1e9) is acknowledged DENIED and designates nothing;
    a pixel inside the image is ACCEPTED and becomes the target."""
    from nav.companion import MAV_CMD_USER_1, Companion
    from pipeline.config import load_gsoe_config

    port = free_udp_port()
    app = Companion(f"udpin://127.0.0.1:{free_udp_port()}", str(tmp_path / "no_camera.avi"), gsoe_config,
                    load_gsoe_config()[1], str(tmp_path / "log"), gcs_url=f"udpin:127.0.0.1:{port}")
    gcs = CommandEndpoint(f"udpout:127.0.0.1:{port}", None, source_system=255, source_component=190)
    w, h = app.camera.size_px
    try:
        acks = []
        for xy in [(1e9, -1e9), (float(w), 10.0), (w / 2, h / 3)]:
            gcs.conn.mav.command_long_send(1, 191, MAV_CMD_USER_1, 0, xy[0], xy[1], 0, 0, 0, 0, 0)
            end = time.monotonic() + 2.0
            got: list[Any] = []
            while time.monotonic() < end and not got:
                app._gcs_commands()
                m = gcs.conn.recv_match(type="COMMAND_ACK", blocking=False)
                got = [m] if m is not None else []
                time.sleep(0.01)
            acks.append(got[0].result if got else None)
            if got:
                assert (got[0].target_system, got[0].target_component) == (255, 190)   # to the sender
            if xy[0] > w:
                assert app.target_px is None
        assert acks == [2, 2, 0]                                        # DENIED, DENIED, ACCEPTED
        assert app.target_px == pytest.approx((w / 2, h / 3))
    finally:
        gcs.close()
        app.close()
