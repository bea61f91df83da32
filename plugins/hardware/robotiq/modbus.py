"""Robotiq 2F-85 over Modbus RTU: frames, CRC16 and the gripper registers.

Requests (slave id 9 by default):

- write the action request, function 0x10 at register 0x03E8, 3 registers = 6 bytes:
  ``rACT|rGTO<<3|rATR<<4``, 0, 0, ``rPR`` (position 0 open..255 closed), ``rSP`` (speed),
  ``rFR`` (force);
- read the status, function 0x04 at register 0x07D0, 3 registers = 6 bytes: ``gSTA``,
  0, ``gFLT`` (fault), ``gPR`` (echo), ``gPO`` (position), ``gCU`` (current), where
  byte 0 = ``gACT | gGTO<<3 | gSTA<<4 | gOBJ<<6``.

Every frame ends with the Modbus CRC16 (polynomial 0xA001 reflected, init 0xFFFF, low byte
first).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from vistac.errors import HardwareError

WRITE_REGISTERS = 0x10
READ_INPUT_REGISTERS = 0x04
ACTION_REGISTER = 0x03E8
STATUS_REGISTER = 0x07D0

OBJECT_MOVING, OBJECT_OPENING, OBJECT_CLOSING, OBJECT_AT_POSITION = 0, 1, 2, 3
FAULTS = {
    0x05: "action delayed: activation must complete first",
    0x07: "the activation bit must be set before an action",
    0x08: "maximum operating temperature exceeded",
    0x09: "no communication during at least 1 second",
    0x0A: "under minimum operating voltage",
    0x0B: "automatic release in progress",
    0x0C: "internal fault; contact support",
    0x0D: "activation fault: check that nothing obstructs the fingers",
    0x0E: "overcurrent triggered",
    0x0F: "automatic release completed",
}


def crc16(data: bytes) -> int:
    """Modbus CRC16 of ``data``."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(frame: bytes) -> bytes:
    return frame + struct.pack("<H", crc16(frame))


def check_crc(frame: bytes) -> bytes:
    """The frame without its CRC; HardwareError when the CRC does not match."""
    if len(frame) < 4:
        raise HardwareError(f"Robotiq: short Modbus frame ({len(frame)} bytes)")
    body, (received,) = frame[:-2], struct.unpack("<H", frame[-2:])
    if crc16(body) != received:
        raise HardwareError(
            f"Robotiq: bad CRC in reply ({received:#06x}, expected {crc16(body):#06x}); "
            "check the baud rate and the cable"
        )
    return body


def write_request(slave: int, payload: bytes) -> bytes:
    """Function 0x10 frame writing ``payload`` (6 bytes) at the action register."""
    count = len(payload) // 2
    header = struct.pack(">BBHHB", slave, WRITE_REGISTERS, ACTION_REGISTER, count, len(payload))
    return with_crc(header + payload)


def read_request(slave: int) -> bytes:
    """Function 0x04 frame reading the 3 status registers."""
    return with_crc(struct.pack(">BBHH", slave, READ_INPUT_REGISTERS, STATUS_REGISTER, 3))


def action_payload(activate: bool, go: bool, position: int, speed: int, force: int) -> bytes:
    """The 6 bytes of an action request (0..255 each for position, speed and force)."""
    flags = (1 if activate else 0) | (8 if go else 0)
    return bytes([flags, 0, 0, position & 0xFF, speed & 0xFF, force & 0xFF])


@dataclass(frozen=True)
class Status:
    """Decoded status registers."""

    activated: bool
    going: bool
    activation_status: int
    """gSTA: 0 reset, 1 activating, 3 activation complete."""
    object_status: int
    """gOBJ: 0 moving, 1 stopped opening (object), 2 stopped closing (object), 3 at target."""
    fault: int
    requested: int
    position: int
    current: int

    @classmethod
    def decode(cls, data: bytes) -> Status:
        if len(data) != 6:
            raise HardwareError(f"Robotiq: status must be 6 bytes, got {len(data)}")
        head = data[0]
        return cls(
            activated=bool(head & 1),
            going=bool(head & 8),
            activation_status=(head >> 4) & 3,
            object_status=(head >> 6) & 3,
            fault=data[2] & 0x0F,
            requested=data[3],
            position=data[4],
            current=data[5],
        )

    def encode(self) -> bytes:
        head = (
            int(self.activated)
            | int(self.going) << 3
            | self.activation_status << 4
            | self.object_status << 6
        )
        return bytes([head, 0, self.fault, self.requested, self.position, self.current])
