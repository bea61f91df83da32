"""The PapillArray serial stream as vistac reads it: one binary frame per sensor sample.

Contactile's own PTSDK protocol is not public, so vistac defines this framing (a small
firmware bridge or the SDK's host tool produces it); all of it lives in this module.
Little-endian:

==========  ======  =====================================================================
offset      type    field
==========  ======  =====================================================================
0           2 B     sync ``0x55 0xAA``
2           uint8   sensor id (0, 1, ...)
3           uint8   P = number of pillars (9 on a PapillArray)
4           uint32  device time, microseconds (informational)
8           P x 6   float32 per pillar: displacement dx, dy, dz (mm), force fx, fy, fz (N)
8 + 24 P    6       float32 global force Fx, Fy, Fz (N) and torque Tx, Ty, Tz (N mm)
32 + 24 P   uint32  CRC-32 (zlib) of bytes 2 .. 32 + 24 P
==========  ======  =====================================================================

Forces are in the sensor frame (z out of the pad surface) and are the force the touched
object applies to the pad. The host sends ``BIAS_COMMAND`` to zero all pillars.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np
from vistac.types import FloatArray

SYNC = b"\x55\xaa"
BIAS_COMMAND = SYNC + b"B"
HEADER = struct.Struct("<BBI")
MAX_PILLARS = 32


class MalformedFrameError(ValueError):
    """A frame that fails its checks (it is skipped and counted)."""


@dataclass(frozen=True)
class SensorFrame:
    """One decoded sample of one sensor.

    pillars: [P, 6] = (dx, dy, dz mm, fx, fy, fz N); global_wrench: [6] = (Fx, Fy, Fz N,
    Tx, Ty, Tz N mm).
    """

    sensor_id: int
    device_time_us: int
    pillars: FloatArray
    global_wrench: FloatArray


def frame_size(pillars: int) -> int:
    """Total bytes of a frame with ``pillars`` pillars (sync and CRC included)."""
    return len(SYNC) + HEADER.size + 4 * 6 * (pillars + 1) + 4


def encode(frame: SensorFrame) -> bytes:
    pillars = np.asarray(frame.pillars, dtype="<f4")
    body = HEADER.pack(frame.sensor_id, len(pillars), frame.device_time_us)
    body += pillars.tobytes() + np.asarray(frame.global_wrench, dtype="<f4").tobytes()
    return SYNC + body + struct.pack("<I", zlib.crc32(body))


def decode(data: bytes) -> SensorFrame:
    """Decode one complete frame (``data`` starts with SYNC); MalformedFrameError when bad."""
    if data[:2] != SYNC:
        raise MalformedFrameError("missing sync bytes")
    sensor_id, count, device_time_us = HEADER.unpack_from(data, 2)
    if not 0 < count <= MAX_PILLARS or len(data) != frame_size(count):
        raise MalformedFrameError(f"bad pillar count {count} or length {len(data)}")
    body, (crc,) = data[2:-4], struct.unpack("<I", data[-4:])
    if zlib.crc32(body) != crc:
        raise MalformedFrameError("checksum mismatch")
    values = np.frombuffer(data, dtype="<f4", offset=8, count=6 * (count + 1)).astype(np.float64)
    if not np.all(np.isfinite(values)):
        raise MalformedFrameError("non-finite values")
    return SensorFrame(sensor_id, device_time_us, values[:-6].reshape(count, 6), values[-6:])


class FrameSplitter:
    """Cuts a byte stream into frames, resynchronising on the sync bytes after garbage."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.malformed = 0

    def feed(self, data: bytes) -> list[SensorFrame]:
        """Frames completed by ``data``; bad ones are counted in ``malformed`` and skipped."""
        self.buffer += data
        frames: list[SensorFrame] = []
        while True:
            start = self.buffer.find(SYNC)
            if start < 0:
                del self.buffer[: max(0, len(self.buffer) - 1)]
                return frames
            del self.buffer[:start]
            if len(self.buffer) < 4:
                return frames
            count = self.buffer[3]
            if not 0 < count <= MAX_PILLARS:
                self.malformed += 1
                del self.buffer[:2]
                continue
            size = frame_size(count)
            if len(self.buffer) < size:
                return frames
            try:
                frames.append(decode(bytes(self.buffer[:size])))
                del self.buffer[:size]
            except MalformedFrameError:
                self.malformed += 1
                del self.buffer[:2]
