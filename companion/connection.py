"""Connection strings: the one parser, shared by the config, the CLI and the service's links.

Pure text in, a `LinkSpec` out (or a ValueError saying what is wrong); it opens nothing, so
`companion.config` can validate `link.connection` without importing the service.
"""

from __future__ import annotations

import termios
from dataclasses import dataclass
from typing import Literal

LinkKind = Literal["udpin", "udpout", "tcp", "serial"]


@dataclass(frozen=True, slots=True)
class LinkSpec:
    """A parsed connection string."""

    kind: LinkKind
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind}:{self.host}:{self.port}"


def _host_port(rest: str, text: str) -> tuple[str, int]:
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT in {text!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"port must be an integer in {text!r}, found {port_text!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"port must be 0..65535 in {text!r}, found {port}")
    return host.strip("[]"), port


_URL_SCHEMES: dict[str, LinkKind] = {
    "udp": "udpin",
    "udpin": "udpin",
    "udpout": "udpout",
    "tcp": "tcp",
    "tcpout": "tcp",
}


def _parse_url(text: str, scheme: str, rest: str) -> LinkSpec:
    """MAVSDK URL forms (`udp://:14540`, `udpin://0.0.0.0:14540`, `udpout://HOST:PORT`,
    `tcp://HOST:PORT`, `serial:///dev/ttyACM0:57600`) as the equivalent pymavlink form."""
    if scheme in ("serial", "serial_flowcontrol"):
        if scheme == "serial_flowcontrol":
            raise ValueError(
                f"{text!r}: hardware flow control is not supported; "
                "use serial:DEVICE:BAUD (e.g. serial:/dev/ttyACM0:57600)"
            )
        return _parse_serial(rest, text)
    kind = _URL_SCHEMES.get(scheme)
    if kind is None:
        hint = (
            "the companion connects to the autopilot; use tcp:HOST:PORT"
            if scheme == "tcpin"
            else "use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or serial:DEVICE:BAUD"
        )
        raise ValueError(f"unsupported connection URL {text!r}: {hint}")
    host, sep, port_text = rest.rpartition(":")
    if not sep:
        raise ValueError(f"expected {scheme}://HOST:PORT in {text!r}")
    if not host:
        if kind != "udpin":
            raise ValueError(f"{scheme}:// needs a host in {text!r}")
        host = "0.0.0.0"  # MAVSDK's udp://:PORT listens on every interface
    return _validated(kind, *_host_port(f"{host}:{port_text}", text), text)


def _validated(kind: LinkKind, host: str, port: int, text: str) -> LinkSpec:
    if kind != "udpin" and port == 0:
        raise ValueError(f"{kind} needs a destination port in {text!r}")
    return LinkSpec(kind, host=host, port=port)


def _parse_serial(device: str, text: str) -> LinkSpec:
    dev, sep, baud_text = device.replace(",", ":").rpartition(":")
    if not sep or not dev:
        raise ValueError(f"expected DEVICE:BAUD in {text!r}")
    try:
        baud = int(baud_text)
    except ValueError:
        raise ValueError(f"baud rate must be an integer in {text!r}") from None
    if not hasattr(termios, f"B{baud}"):
        raise ValueError(f"unsupported baud rate {baud} in {text!r}")
    return LinkSpec("serial", device=dev, baud=baud)


def parse_connection(text: str) -> LinkSpec:
    """Parse a connection string; ValueError says what is wrong.

    pymavlink forms: udpin:HOST:PORT (listen), udp:HOST:PORT (the same), udpout:HOST:PORT
    (send to), tcp:HOST:PORT (connect), serial:DEVICE:BAUD, DEVICE:BAUD or DEVICE,BAUD.
    MAVSDK URL forms are read as the same: udp://:PORT and udp://HOST:PORT (listen),
    udpin://HOST:PORT, udpout://HOST:PORT, tcp://HOST:PORT, tcpout://HOST:PORT and
    serial://DEVICE:BAUD (serial:///dev/ttyACM0:57600). `str()` of the result is the
    pymavlink form. The only parser of connection strings: the config, `check-config`,
    `run` and `--connection` all use it.
    """
    s = text.strip()
    scheme, sep, rest = s.partition(":")
    if sep and rest.startswith("//"):
        return _parse_url(text, scheme.lower(), rest[2:])
    if sep and scheme in ("udpin", "udp"):
        return _validated("udpin", *_host_port(rest, text), text)
    if sep and scheme in ("udpout", "tcp"):
        kind: LinkKind = "udpout" if scheme == "udpout" else "tcp"
        return _validated(kind, *_host_port(rest, text), text)
    if sep and scheme == "serial":
        return _parse_serial(rest, text)
    if s.startswith("/dev/"):
        return _parse_serial(s, text)
    raise ValueError(
        f"unknown connection string {text!r}; use udpin:HOST:PORT, udpout:HOST:PORT, "
        "tcp:HOST:PORT or serial:DEVICE:BAUD"
    )


__all__ = ["LinkKind", "LinkSpec", "parse_connection"]
