"""A health check of the UR controller, with timeouts, before ``ur_rtde`` connects.

``ur_rtde``'s constructors hold the GIL while they wait for the controller (forever when it
accepts connections but sends no data), so no deadline can interrupt them. Before building
them, this probe checks in plain Python, with socket timeouts, that the dashboard server
answers and that the RTDE server negotiates, sets up a one-variable output recipe and actually
streams a data package; then it disconnects. It uses the RTDE protocol v2 wire format: uint16
size, uint8 type, payload (big-endian).
"""

from __future__ import annotations

import socket
import struct
import time

from vistac.errors import HardwareError

RTDE_PORT = 30004
DASHBOARD_PORT = 29999


def _receive(sock: socket.socket, kind: str, deadline_s: float) -> bytes:
    """The payload of the next package of type ``kind`` (others are skipped)."""
    while True:
        sock.settimeout(max(deadline_s - time.monotonic(), 0.001))
        header = _read(sock, 3)
        size, got = struct.unpack(">HB", header)
        payload = _read(sock, size - 3)
        if chr(got) == kind:
            return payload


def _read(sock: socket.socket, count: int) -> bytes:
    data = b""
    while len(data) < count:
        chunk = sock.recv(count - len(data))
        if not chunk:
            raise ConnectionError("the controller closed the connection")
        data += chunk
    return data


def _send(sock: socket.socket, kind: str, payload: bytes = b"") -> None:
    sock.sendall(struct.pack(">HB", len(payload) + 3, ord(kind)) + payload)


def _check_rtde(host: str, deadline_s: float) -> None:
    with socket.create_connection((host, RTDE_PORT), timeout=deadline_s - time.monotonic()) as s:
        _send(s, "V", struct.pack(">H", 2))
        if _receive(s, "V", deadline_s)[:1] != b"\x01":
            raise HardwareError(f"UR controller at {host} refused RTDE protocol version 2")
        _send(s, "O", struct.pack(">d", 10.0) + b"timestamp")
        if b"NOT_FOUND" in _receive(s, "O", deadline_s):
            raise HardwareError(f"UR controller at {host} has no RTDE 'timestamp' output")
        _send(s, "S")
        _receive(s, "S", deadline_s)
        _receive(s, "U", deadline_s)
        _send(s, "P")


def _check_dashboard(host: str, deadline_s: float) -> None:
    timeout_s = deadline_s - time.monotonic()
    with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
        if not sock.makefile("rb").readline():
            raise ConnectionError("the dashboard server sent no greeting")


def probe_controller(host: str, timeout_s: float) -> None:
    """Raise HardwareError unless the controller at ``host`` streams RTDE data and its
    dashboard answers, all within ``timeout_s``."""
    deadline_s = time.monotonic() + timeout_s
    try:
        _check_dashboard(host, deadline_s)
        _check_rtde(host, deadline_s)
    except (OSError, ConnectionError, struct.error) as exc:
        raise HardwareError(
            f"UR controller at {host} does not answer or stream RTDE data within {timeout_s} s "
            f"({exc or type(exc).__name__}); check the address, the cable and that the robot "
            "is powered on"
        ) from exc
