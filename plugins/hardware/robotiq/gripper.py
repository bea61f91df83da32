"""Robotiq 2F-85 gripper: Modbus RTU on a serial port, or the UR's gripper socket (63352).

``open``/``close`` send a go-to request and return at once; ``state`` polls the status. The
gripper is activated when the component is built (``activation_timeout_s``). A fault code in
the status raises ``HardwareError`` naming the fault; a bad CRC or a silent device raises
``HardwareError`` with what to check.
"""

from __future__ import annotations

import logging
import socket
import time
from typing import Literal, Protocol

from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.errors import HardwareError
from vistac.plugins.hardware.robotiq import modbus
from vistac.plugins.hardware.robotiq.modbus import Status
from vistac.types import GripperState

log = logging.getLogger(__name__)

_WRITE_REPLY_BYTES = 8
_READ_REPLY_BYTES = 11
_POLL_S = 0.02


class Transport(Protocol):
    def write_action(self, payload: bytes) -> None: ...

    def read_status(self) -> Status: ...

    def close(self) -> None: ...


class ModbusTransport:
    """Modbus RTU over pyserial."""

    def __init__(self, port: str, baudrate: int, slave: int, timeout_s: float) -> None:
        import serial

        try:
            self.serial = serial.Serial(port, baudrate, timeout=timeout_s, write_timeout=timeout_s)
        except (serial.SerialException, OSError) as exc:
            raise HardwareError(f"Robotiq: cannot open serial port {port}: {exc}") from exc
        self.port, self.slave, self.timeout_s = port, slave, timeout_s

    def _exchange(self, request: bytes, reply_bytes: int) -> bytes:
        self.serial.reset_input_buffer()
        self.serial.write(request)
        head = self.serial.read(2)
        if len(head) < 2:
            raise HardwareError(
                f"Robotiq on {self.port} did not answer within {self.timeout_s * 1e3:.0f} ms; "
                "check its power, the port, the baud rate and the slave id"
            )
        if head[1] & 0x80:  # Modbus exception: code + CRC
            body = modbus.check_crc(head + self.serial.read(3))
            raise HardwareError(f"Robotiq: Modbus exception code {body[2]} for {request[1]:#x}")
        frame = head + self.serial.read(reply_bytes - 2)
        if len(frame) < reply_bytes:
            raise HardwareError(f"Robotiq on {self.port}: truncated reply ({len(frame)} bytes)")
        return modbus.check_crc(frame)

    def write_action(self, payload: bytes) -> None:
        self._exchange(modbus.write_request(self.slave, payload), _WRITE_REPLY_BYTES)

    def read_status(self) -> Status:
        body = self._exchange(modbus.read_request(self.slave), _READ_REPLY_BYTES)
        return Status.decode(body[3:9])

    def close(self) -> None:
        self.serial.close()


class SocketTransport:
    """The URCap gripper socket: ASCII ``SET VAR value`` / ``GET VAR`` lines."""

    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        try:
            self.sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise HardwareError(f"Robotiq: cannot connect to {host}:{port}: {exc}") from exc
        self.stream = self.sock.makefile("rwb", buffering=0)
        self.where = f"{host}:{port}"

    def _ask(self, line: str) -> str:
        try:
            self.stream.write(line.encode() + b"\n")
            answer = self.stream.readline().decode().strip()
        except OSError as exc:
            raise HardwareError(f"Robotiq socket {self.where} did not answer: {exc}") from exc
        if not answer:
            raise HardwareError(f"Robotiq socket {self.where} closed the connection")
        return answer

    def _get(self, name: str) -> int:
        answer = self._ask(f"GET {name}").split()
        if len(answer) != 2 or answer[0] != name or not answer[1].isdigit():
            raise HardwareError(f"Robotiq socket: unexpected answer {answer!r} to GET {name}")
        return int(answer[1])

    def write_action(self, payload: bytes) -> None:
        values = {
            "ACT": payload[0] & 1,
            "GTO": (payload[0] >> 3) & 1,
            "POS": payload[3],
            "SPE": payload[4],
            "FOR": payload[5],
        }
        for name in ("SPE", "FOR", "POS", "ACT", "GTO"):
            if self._ask(f"SET {name} {values[name]}") != "ack":
                raise HardwareError(f"Robotiq socket refused SET {name}")

    def read_status(self) -> Status:
        return Status(
            activated=self._get("ACT") == 1,
            going=self._get("GTO") == 1,
            activation_status=self._get("STA"),
            object_status=self._get("OBJ"),
            fault=self._get("FLT"),
            requested=self._get("PRE"),
            position=self._get("POS"),
            current=0,
        )

    def close(self) -> None:
        self.sock.close()


class Robotiq2F85(Component):
    """Implements the ``Gripper`` protocol on a Robotiq 2F-85."""

    kind = "gripper"

    class Config(ComponentConfig):
        transport: Literal["serial", "ur_socket"] = "serial"
        port: str = "/dev/ttyUSB0"
        baudrate: int = Field(default=115200, gt=0)
        slave_id: int = Field(default=9, ge=1, le=247)
        host: str = "192.168.1.10"
        """The UR controller running the gripper URCap (``ur_socket`` transport)."""
        socket_port: int = Field(default=63352, gt=0, lt=65536)
        timeout_s: float = Field(default=0.2, gt=0.0)
        activation_timeout_s: float = Field(default=5.0, gt=0.0)
        speed: int = Field(default=255, ge=0, le=255)
        force: int = Field(default=150, ge=0, le=255)
        stroke_m: float = Field(default=0.085, gt=0.0)
        closed_position: int = Field(default=230, gt=0, le=255)
        """Position count at which the fingers touch (width 0)."""

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.transport: Transport
        if config.transport == "serial":
            self.transport = ModbusTransport(
                config.port, config.baudrate, config.slave_id, config.timeout_s
            )
        else:
            self.transport = SocketTransport(config.host, config.socket_port, config.timeout_s)
        self._target = 0
        self.activate()

    def activate(self) -> None:
        """Reset, then activate and wait until activation completes."""
        config = self.config
        self.transport.write_action(modbus.action_payload(False, False, 0, 0, 0))
        self.transport.write_action(
            modbus.action_payload(True, False, 0, config.speed, config.force)
        )
        deadline = time.monotonic() + config.activation_timeout_s
        while True:
            status = self._status()
            if status.activation_status == 3:
                log.info("Robotiq 2F-85 activated")
                return
            if time.monotonic() > deadline:
                raise HardwareError(
                    f"Robotiq did not finish activating within {config.activation_timeout_s} s"
                )
            time.sleep(_POLL_S)

    def _status(self) -> Status:
        status = self.transport.read_status()
        if status.fault:
            text = modbus.FAULTS.get(status.fault, "unknown fault")
            raise HardwareError(f"Robotiq fault {status.fault:#x}: {text}")
        return status

    def _go_to(self, position: int) -> None:
        self._target = position
        payload = modbus.action_payload(True, True, position, self.config.speed, self.config.force)
        self.transport.write_action(payload)

    def open(self) -> None:
        self._go_to(0)

    def close(self) -> None:
        """Close the fingers. This is the Gripper protocol's ``close``, which shadows
        ``Component.close``; the run never calls it at its end, it calls ``release``."""
        self._go_to(255)

    def stop(self) -> None:
        """Clear the go bit: the fingers stop where they are."""
        self.transport.write_action(
            modbus.action_payload(True, False, self._target, self.config.speed, self.config.force)
        )

    def width_m(self, position: int) -> float:
        return self.config.stroke_m * max(0.0, 1.0 - position / self.config.closed_position)

    def state(self) -> GripperState:
        status = self._status()
        return GripperState(
            width_m=self.width_m(status.position),
            object_detected=status.object_status in (modbus.OBJECT_OPENING, modbus.OBJECT_CLOSING),
            moving=status.going and status.object_status == modbus.OBJECT_MOVING,
            timestamp_s=time.monotonic(),
        )

    def release(self) -> None:
        """Release the serial port or socket; the fingers stay where they are."""
        self.transport.close()
