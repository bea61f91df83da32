"""A Robotiq 2F-85 on a pseudo-terminal (Modbus RTU) and on a TCP gripper socket.

``GripperSim`` moves the fingers towards the requested position at a speed proportional to
``rSP`` and stops on an object of ``object_width_m`` (object detection gOBJ = 2 when closing).
``RobotiqPty`` answers Modbus frames on the master side of ``os.openpty()``; the plugin opens
the slave path with pyserial. Test modes: ``corrupt_crc`` (every reply's CRC is wrong),
``silent`` (no replies) and ``fault`` (a gFLT code).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
import threading
import time

from vistac.plugins.hardware.robotiq import modbus
from vistac.plugins.hardware.robotiq.modbus import Status

from emulators.pty import PtyDevice

STROKE_M = 0.085
CLOSED_POSITION = 230
FULL_SPEED_COUNTS_S = 1500.0


class GripperSim:
    """Finger motion, activation, object detection and faults."""

    def __init__(self, object_width_m: float | None = None) -> None:
        self.object_width_m = object_width_m
        self.lock = threading.Lock()
        self.position = 0.0
        self.requested = 0
        self.speed = 255
        self.activated = False
        self.going = False
        self.activation_status = 0
        self.object_status = modbus.OBJECT_AT_POSITION
        self.fault = 0
        self.last_s = time.monotonic()

    def object_position(self) -> float | None:
        if self.object_width_m is None:
            return None
        return CLOSED_POSITION * (1.0 - self.object_width_m / STROKE_M)

    def write(self, payload: bytes) -> None:
        with self.lock:
            self._advance()
            activate, go = bool(payload[0] & 1), bool(payload[0] & 8)
            if not activate:
                self.activated, self.activation_status, self.going = False, 0, False
                return
            if not self.activated:
                self.activated, self.activation_status = True, 3
            self.requested, self.speed, self.going = payload[3], max(payload[4], 1), go
            if go:
                self.object_status = modbus.OBJECT_MOVING

    def _advance(self) -> None:
        now = time.monotonic()
        dt_s, self.last_s = now - self.last_s, now
        if not (self.going and self.object_status == modbus.OBJECT_MOVING):
            return
        step = FULL_SPEED_COUNTS_S * self.speed / 255.0 * dt_s
        target = float(self.requested)
        blocker = self.object_position()
        closing = target > self.position
        if closing and blocker is not None and target > blocker >= self.position:
            target = blocker
        if abs(target - self.position) <= step:
            self.position = target
            if target == self.requested:
                self.object_status = modbus.OBJECT_AT_POSITION
            else:
                self.object_status = modbus.OBJECT_CLOSING
        else:
            self.position += step if target > self.position else -step

    def status(self) -> Status:
        with self.lock:
            self._advance()
            return Status(
                activated=self.activated,
                going=self.going,
                activation_status=self.activation_status,
                object_status=self.object_status,
                fault=self.fault,
                requested=self.requested,
                position=round(self.position),
                current=10 if self.object_status == modbus.OBJECT_CLOSING else 0,
            )


class RobotiqPty(PtyDevice):
    """Modbus RTU slave on a pseudo-terminal; ``path`` is the device the plugin opens."""

    def __init__(self, gripper: GripperSim | None = None, slave: int = 9) -> None:
        self.gripper = gripper or GripperSim()
        self.slave = slave
        self.corrupt_crc = False
        super().__init__()

    def _read(self, count: int) -> bytes:
        data = b""
        while len(data) < count and not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if ready:
                data += os.read(self.master, count - len(data))
        return data

    def _run(self) -> None:
        while not self._stop.is_set():
            head = self._read(2)
            if len(head) < 2:
                continue
            if head[1] == modbus.WRITE_REGISTERS:
                header = self._read(5)
                frame = head + header + self._read(header[-1] + 2)
            else:
                frame = head + self._read(6)
            self._answer(frame)

    def _answer(self, frame: bytes) -> None:
        try:
            body = modbus.check_crc(frame)
        except Exception:
            return  # a real slave ignores frames with a bad CRC
        if body[0] != self.slave or self.silent:
            return
        if body[1] == modbus.WRITE_REGISTERS:
            self.gripper.write(body[7:13])
            reply = body[:6]
        else:
            data = self.gripper.status().encode()
            reply = struct.pack(">BBB", self.slave, modbus.READ_INPUT_REGISTERS, 6) + data
        framed = modbus.with_crc(reply)
        if self.corrupt_crc:
            framed = framed[:-1] + bytes([framed[-1] ^ 0xFF])
        os.write(self.master, framed)


class RobotiqSocket:
    """The URCap gripper socket (ASCII SET/GET) on ``host``:63352-style port."""

    def __init__(self, host: str, port: int, gripper: GripperSim | None = None) -> None:
        self.gripper = gripper or GripperSim()
        self.server = socket.create_server((host, port))
        self.host, self.port = host, port
        self._payload = bytearray(6)
        threading.Thread(target=self._accept, daemon=True).start()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.server.shutdown(socket.SHUT_RDWR)
        self.server.close()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        with contextlib.suppress(OSError), client, client.makefile("rwb", buffering=0) as stream:
            for raw in stream:
                stream.write((self._answer(raw.decode().split()) + "\n").encode())

    def _answer(self, words: list[str]) -> str:
        if len(words) == 3 and words[0] == "SET":
            slot = {"ACT": 0, "GTO": 0, "POS": 3, "SPE": 4, "FOR": 5}[words[1]]
            value = int(words[2])
            if words[1] == "ACT":
                self._payload[0] = (self._payload[0] & ~1) | value
            elif words[1] == "GTO":
                self._payload[0] = (self._payload[0] & ~8) | (value << 3)
            else:
                self._payload[slot] = value
            if words[1] in ("ACT", "GTO"):
                self.gripper.write(bytes(self._payload))
            return "ack"
        status = self.gripper.status()
        values = {
            "ACT": int(status.activated),
            "GTO": int(status.going),
            "STA": status.activation_status,
            "OBJ": status.object_status,
            "FLT": status.fault,
            "PRE": status.requested,
            "POS": status.position,
        }
        return f"{words[1]} {values[words[1]]}"
