"""One URL syntax for both of the companion's MAVLink links.

``--connect`` (the autopilot, through MAVSDK) and ``--gcs`` (the ground station's commands, through pymavlink) take
the same forms, MAVSDK's::

    udpin://HOST:PORT        listen on HOST:PORT (0.0.0.0 for every interface)
    udpout://HOST:PORT       send to HOST:PORT
    tcpin://HOST:PORT        accept a TCP connection on HOST:PORT
    tcpout://HOST:PORT       connect to HOST:PORT
    serial://DEVICE[:BAUD]   a serial port (serial:///dev/ttyAMA0:921600; BAUD defaults to 57600)

pymavlink's spellings of the same (``udpin:HOST:PORT``, ``udp:HOST:PORT`` for udpin, ``tcp:HOST:PORT`` for tcpout,
``tcpin:HOST:PORT``) and MAVSDK's older ``udp://`` (udpin) and ``tcp://`` (tcpout) are read too.
:func:`parse_link_url` checks a URL at once (a :class:`LinkUrlError` names the accepted forms) and gives each
library's spelling: :attr:`LinkUrl.mavsdk` and :attr:`LinkUrl.pymavlink` (a serial port as ``DEVICE,BAUD``, which
:class:`nav.signing.CommandEndpoint` splits).
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass
from typing import Literal

DEFAULT_BAUD = 57_600
PORT_MAX = 65_535
ACCEPTED = ("udpin://HOST:PORT, udpout://HOST:PORT, tcpin://HOST:PORT, tcpout://HOST:PORT, serial://DEVICE[:BAUD] "
            "(e.g. udpin://0.0.0.0:14540, serial:///dev/ttyAMA0:921600)")
Kind = Literal["udpin", "udpout", "tcpin", "tcpout", "serial"]
# scheme as written -> kind (MAVSDK's, then pymavlink's spellings)
_SCHEMES: dict[str, Kind] = {"udpin": "udpin", "udpout": "udpout", "tcpin": "tcpin", "tcpout": "tcpout",
                             "serial": "serial", "udp": "udpin", "tcp": "tcpout"}
_HOST = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}"
                   r"[A-Za-z0-9])?)*$")


class LinkUrlError(ValueError):
    """A link URL that is not one of the accepted forms; the message says why and lists them."""

    def __init__(self, option: str, url: str, why: str) -> None:
        super().__init__(f"{option} {url!r}: {why}; accepted: {ACCEPTED}")


@dataclass(frozen=True)
class LinkUrl:
    """A checked link address: ``kind``, ``host`` and ``port`` (network) or ``device`` and ``baud`` (serial)."""

    kind: Kind
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = DEFAULT_BAUD

    @property
    def mavsdk(self) -> str:
        """The MAVSDK connection URL (``udpin://0.0.0.0:14540``, ``serial:///dev/ttyAMA0:921600``)."""
        if self.kind == "serial":
            return f"serial://{self.device}:{self.baud}"
        return f"{self.kind}://{self.host}:{self.port}"

    @property
    def pymavlink(self) -> str:
        """The ``pymavlink.mavutil.mavlink_connection`` device (``udpin:0.0.0.0:14550``; serial ``DEVICE,BAUD``)."""
        if self.kind == "serial":
            return f"{self.device},{self.baud}"
        scheme = {"udpin": "udpin", "udpout": "udpout", "tcpin": "tcpin", "tcpout": "tcp"}[self.kind]
        return f"{scheme}:{self.host}:{self.port}"


def _host_ok(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return bool(_HOST.match(host)) and not host.replace(".", "").isdigit()


def parse_link_url(url: str, option: str = "link") -> LinkUrl:
    """Check ``url`` (module docstring); ``option`` names the command-line option in the error."""
    text = url.strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, sep, rest = text.partition(":")
    kind = _SCHEMES.get(scheme.lower()) if sep else None
    if kind is None:
        raise LinkUrlError(option, url, f"unknown scheme {scheme!r}" if sep else "no scheme")
    if kind == "serial":
        device, baud_sep, baud_text = rest.rpartition(":")
        if not baud_sep or not baud_text.isdigit():
            device, baud_text = rest, ""
        if not device.startswith("/") and not re.fullmatch(r"COM\d+", device):
            raise LinkUrlError(option, url, "a serial device is an absolute path (/dev/ttyAMA0) or COMn")
        baud = int(baud_text) if baud_text else DEFAULT_BAUD
        if not 1_200 <= baud <= 12_000_000:
            raise LinkUrlError(option, url, f"baud rate {baud} out of range")
        return LinkUrl("serial", device=device, baud=baud)
    host, colon, port_text = rest.rpartition(":")
    host = host.strip("[]")
    if not colon:
        raise LinkUrlError(option, url, "no port")
    if not port_text.isdigit() or not 0 < int(port_text) <= PORT_MAX:
        raise LinkUrlError(option, url, f"port {port_text!r} is not a number in 1-{PORT_MAX}")
    if not host and kind == "udpin":
        host = "0.0.0.0"  # MAVSDK's udp://:14540
    if not _host_ok(host):
        raise LinkUrlError(option, url, f"host {host!r} is not an IP address or host name")
    return LinkUrl(kind, host=host, port=int(port_text))
