"""MAVLink 2 message signing on the companion's own link (the ground station <-> companion channel).

MAVSDK 4's native binding has no signing API, so the companion's own link (where a ground station sends it
commands, e.g. designating a target) is a pymavlink endpoint, signed with pymavlink's implementation of the
MAVLink 2 signing protocol (HMAC-SHA-256 truncated to 48 bits, timestamps against replay).

Key file: 32 raw bytes, or 64 hexadecimal characters, or a passphrase whose SHA-256 is the key (as MAVProxy's
``signing setup PASSPHRASE`` does).  When signing is enabled, unsigned or badly signed *commands* (COMMAND_LONG,
COMMAND_INT, SET_MODE, ...) are refused and counted; unsigned telemetry-like messages listed in
:data:`UNSIGNED_OK` (HEARTBEAT, RADIO_STATUS) are accepted, as ArduPilot does for a radio's own messages.  Without a
key the endpoint warns at start that anyone who can reach it can command the companion.  Signed or not, a message
with target fields comes out of :meth:`CommandEndpoint.poll` only when it is addressed to the companion's own
system and component (:func:`nav.hygiene.addressed_to`); the others are counted (``not_for_us``) and dropped.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLINK20 must be set before import)

from nav.hygiene import addressed_to  # noqa: E402

log = logging.getLogger(__name__)

KEY_BYTES = 32
UNSIGNED_OK = frozenset({"HEARTBEAT", "RADIO_STATUS"})


def load_key(path: str | Path) -> bytes:
    """The 32-byte signing key from a key file (raw, hex or passphrase); a clear error when unusable."""
    p = Path(path)
    data = p.read_bytes()
    if len(data) == KEY_BYTES:
        return data
    text = data.decode("utf-8", errors="strict").strip() if data else ""
    if not text:
        raise ValueError(f"{p}: empty signing key file")
    try:
        raw = bytes.fromhex(text)
        if len(raw) == KEY_BYTES:
            return raw
    except ValueError:
        pass
    return hashlib.sha256(text.encode("utf-8")).digest()


@dataclass
class SignedLinkStats:
    accepted: dict[str, int] = field(default_factory=dict)
    refused_unsigned: int = 0
    bad_data: int = 0
    not_for_us: int = 0


class CommandEndpoint:
    """A pymavlink endpoint for ground-station commands, optionally signed.

    ``poll()`` returns the accepted messages waiting on the socket that are addressed to ``source_system`` /
    ``source_component`` (the companion's own ids); with a key, unsigned or badly signed messages other than
    :data:`UNSIGNED_OK` never come out of it (pymavlink raises "Invalid signature"; we count them).
    """

    def __init__(self, url: str, key: bytes | None, source_system: int = 1, source_component: int = 191) -> None:
        # ``url``: a pymavlink device; a serial port as ``DEVICE,BAUD`` (nav.urls.LinkUrl.pymavlink)
        device, comma, baud = url.partition(",")
        extra = {"baud": int(baud)} if comma and baud.isdigit() else {}
        self.conn = mavutil.mavlink_connection(device if extra else url, source_system=source_system,
                                               source_component=source_component, dialect="ardupilotmega", **extra)
        self.stats = SignedLinkStats()
        self.signed = key is not None
        self.system_id, self.component_id = int(source_system), int(source_component)
        if key is None:
            log.warning("ground-station link %s is NOT signed: anyone who can reach it can command the companion "
                        "(give a signing key to refuse unsigned commands)", url)
        if key is not None:
            if len(key) != KEY_BYTES:
                raise ValueError(f"signing key must be {KEY_BYTES} bytes, got {len(key)}")
            names = {mid: cls.msgname for mid, cls in mavutil.mavlink.mavlink_map.items()}

            def allow_unsigned(_mav: Any, msg_id: int) -> bool:
                ok = names.get(msg_id, "") in UNSIGNED_OK
                if not ok:
                    self.stats.refused_unsigned += 1
                    log.warning("refused unsigned %s on the signed companion link", names.get(msg_id, msg_id))
                return ok

            self.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=allow_unsigned)

    def poll(self) -> list[Any]:
        out: list[Any] = []
        while True:
            try:
                msg = self.conn.recv_match(blocking=False)
            except Exception as e:  # invalid signature, malformed bytes: refuse, count, go on
                self.stats.bad_data += 1
                log.debug("refused message: %s", e)
                continue
            if msg is None:
                return out
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.stats.bad_data += 1
                continue
            if not addressed_to(msg, self.system_id, self.component_id):
                self.stats.not_for_us += 1
                log.debug("dropped %s addressed to %s/%s, not to us (%d/%d)", kind, getattr(msg, "target_system", "-"),
                          getattr(msg, "target_component", "-"), self.system_id, self.component_id)
                continue
            self.stats.accepted[kind] = self.stats.accepted.get(kind, 0) + 1
            out.append(msg)

    def close(self) -> None:
        self.conn.close()
