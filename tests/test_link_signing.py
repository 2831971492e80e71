"""MAVLink 2 signing on the companion's own link: signed commands pass, unsigned and wrongly signed are refused."""

from __future__ import annotations

import hashlib

import pytest

from nav.signing import CommandEndpoint, load_key
from tests.polling import gather
from tests.test_link import free_udp_port


def test_load_key_formats(tmp_path):
    raw = bytes(range(32))
    (tmp_path / "raw.key").write_bytes(raw)
    (tmp_path / "hex.key").write_text(raw.hex() + "\n")
    (tmp_path / "pass.key").write_text("correct horse battery staple\n")
    (tmp_path / "empty.key").write_bytes(b"")
    assert load_key(tmp_path / "raw.key") == raw
    assert load_key(tmp_path / "hex.key") == raw
    assert load_key(tmp_path / "pass.key") == hashlib.sha256(b"correct horse battery staple").digest()
    with pytest.raises(ValueError, match="empty"):
        load_key(tmp_path / "empty.key")


def test_signed_commands_accepted_unsigned_refused():
    key = hashlib.sha256(b"gsoe test key").digest()
    port = free_udp_port()
    companion = CommandEndpoint(f"udpin:127.0.0.1:{port}", key)
    good_gcs = CommandEndpoint(f"udpout:127.0.0.1:{port}", key, source_system=255, source_component=190)
    plain_gcs = CommandEndpoint(f"udpout:127.0.0.1:{port}", None, source_system=254, source_component=190)
    wrong_gcs = CommandEndpoint(f"udpout:127.0.0.1:{port}", hashlib.sha256(b"other").digest(), source_system=253,
                                source_component=190)
    try:
        for ep, marker in ((good_gcs, 1.0), (plain_gcs, 2.0), (wrong_gcs, 3.0)):
            ep.conn.mav.command_long_send(1, 191, 31010, 0, marker, 0, 0, 0, 0, 0, 0)
            ep.conn.mav.heartbeat_send(6, 8, 0, 0, 4)
        msgs = gather(companion.poll)
        cmds = [m for m in msgs if m.get_type() == "COMMAND_LONG"]
        assert [c.param1 for c in cmds] == [1.0]  # only the correctly signed command
        assert companion.stats.refused_unsigned >= 1  # the unsigned command
        assert companion.stats.bad_data >= 1  # the wrongly signed one
        assert sum(m.get_type() == "HEARTBEAT" for m in msgs) >= 2  # unsigned heartbeats allowed
    finally:
        for ep in (companion, good_gcs, plain_gcs, wrong_gcs):
            ep.close()


def test_unsigned_endpoint_accepts_everything():
    port = free_udp_port()
    companion = CommandEndpoint(f"udpin:127.0.0.1:{port}", None)
    gcs = CommandEndpoint(f"udpout:127.0.0.1:{port}", None, source_system=255)
    try:
        gcs.conn.mav.command_long_send(1, 191, 31010, 0, 7.0, 0, 0, 0, 0, 0, 0)
        cmds = [m for m in gather(companion.poll) if m.get_type() == "COMMAND_LONG"]
        assert [c.param1 for c in cmds] == [7.0]
    finally:
        companion.close()
        gcs.close()
