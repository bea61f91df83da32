"""A fake UR controller that the real ``ur_rtde`` client connects to.

It speaks the three interfaces ``RTDEControlInterface`` / ``RTDEReceiveInterface`` use:

- RTDE (port 30004), protocol version 2: version negotiation (``V``), controller version
  (``v``), output and input recipe setup (``O``, ``I``), start/pause (``S``, ``P``) and data
  packages (``U``), big-endian. Outputs are streamed at the frequency each client asks for.
- the dashboard server (29999): one ASCII command per line (``PolyscopeVersion``,
  ``robotmode``, ``safetystatus``, ``unlock protective stop``, ``stop``, ...).
- the script ports (30002/30003): the control script the client uploads is accepted; from then
  on the "program is running" and the emulator plays the script's part of the register
  handshake (``output_int_register_0``: 1 = ready for a command, 2 = done with it).

Commands are read from ``input_int_register_0`` with their arguments in the input double
registers, as the uploaded script reads them: 3 moveL, 10 speedL, 15 speedStop (ends speed
mode only), 33 stopL (ends a moveL too), 35 setWatchdog, 255 stop script (other codes are
acknowledged and ignored). The TCP pose is
integrated from the commanded velocity (with the commanded acceleration) at 125 Hz.

The controller reports PolyScope 3.15 (a CB3: 125 Hz, no remote-control check). It runs in
its own process (``URControllerProcess``, multiprocessing spawn) bound to its own loopback
address 127.0.0.N, because the client's constructors block without releasing the GIL. Tests
steer it through a pipe: inject a protective stop, drop every connection (and refuse new
ones), go silent (connections stay open, nothing is sent), set the TCP force, override the
safety status bits, read the state.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import re
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from vistac.plugins.hardware.ur_rtde.frames import matrix_to_rotvec, rotvec_to_matrix

log = logging.getLogger(__name__)

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30002, 30003)
CONTROLLER_VERSION = (3, 15, 7, 106331)
POLYSCOPE_VERSION = "URSoftware 3.15.7.106331 (Mar 04 2022)"
PHYSICS_RATE_HZ = 125.0
MOVE_TURN_RATE_RAD_S = 1.0
"""How fast a moveL turns the tool (it moves at the commanded speed)."""

CMD_NONE, CMD_MOVEL, CMD_SPEEDL, CMD_SPEED_STOP = 0, 3, 10, 15
CMD_WATCHDOG_KICK, CMD_STOPL, CMD_SET_WATCHDOG, CMD_STOP_SCRIPT = 24, 33, 35, 255
REALTIME_COMMANDS = {6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
READY, DONE = 1, 2

_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_TYPES = {
    "timestamp": "DOUBLE",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "target_q": "VECTOR6D",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "runtime_state": "UINT32",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
    "external_force_torque": "VECTOR6D",
}
_REGISTER = re.compile(r"(input|output)_(int|double)_register_(\d+)$")


def variable_type(name: str) -> str:
    """RTDE type name of ``name``, or ``NOT_FOUND`` as a real controller answers."""
    match = _REGISTER.match(name)
    if match:
        return "INT32" if match.group(2) == "int" else "DOUBLE"
    return _TYPES.get(name, "NOT_FOUND")


def _names(payload: bytes) -> list[str]:
    """Variable names of a recipe request (the client ends the list with a comma)."""
    return [name for name in payload.decode().split(",") if name]


def pack_package(kind: str, payload: bytes) -> bytes:
    """One RTDE package: uint16 size (header included), uint8 type, payload."""
    return struct.pack(">HB", len(payload) + 3, ord(kind)) + payload


@dataclass
class ArmSim:
    """The controller's robot: TCP pose, speed and force, program and safety state."""

    pose: np.ndarray
    speed: np.ndarray = field(default_factory=lambda: np.zeros(6))
    force: np.ndarray = field(default_factory=lambda: np.zeros(6))
    speed_target: np.ndarray = field(default_factory=lambda: np.zeros(6))
    acceleration: float = 1.0
    move_target: np.ndarray | None = None
    move_start: np.ndarray | None = None
    move_speed_mps: float = 0.0
    move_progress: float = 0.0
    move_sync: bool = False
    program_running: bool = False
    script_state: int = 0
    protective_stop: bool = False
    safety_bits: int | None = None
    """Reported ``safety_status_bits`` instead of those of ``protective_stop``."""
    watchdog_hz: float = 0.0
    last_input_s: float = 0.0
    watchdog_trips: int = 0
    commands: list[int] = field(default_factory=list)

    def halt(self) -> None:
        self.speed_target = np.zeros(6)
        self.move_target = None

    def step(self, dt_s: float, now_s: float) -> None:
        """Advance the robot by ``dt_s``."""
        if self.watchdog_hz > 0 and now_s - self.last_input_s > 1.0 / self.watchdog_hz:
            if np.any(self.speed_target) or self.move_target is not None:
                self.watchdog_trips += 1
            self.halt()
        if self.protective_stop:
            self.halt()
            self.speed[:] = 0.0
            return
        if self.move_target is not None:
            self._step_move(dt_s)
            return
        for part, acceleration in ((slice(0, 3), self.acceleration), (slice(3, 6), 10.0)):
            change = self.speed_target[part] - self.speed[part]
            max_change = acceleration * dt_s
            norm = float(np.linalg.norm(change))
            if norm > max_change:
                change *= max_change / norm
            self.speed[part] += change
        self._integrate(dt_s)

    def _integrate(self, dt_s: float) -> None:
        self.pose[:3] += self.speed[:3] * dt_s
        rotation = rotvec_to_matrix(self.speed[3:] * dt_s) @ rotvec_to_matrix(self.pose[3:])
        self.pose[3:] = matrix_to_rotvec(rotation)

    def _step_move(self, dt_s: float) -> None:
        """Along the straight line and the shortest turn, both ending together."""
        assert self.move_target is not None and self.move_start is not None
        start = rotvec_to_matrix(self.move_start[3:])
        turn = matrix_to_rotvec(rotvec_to_matrix(self.move_target[3:]) @ start.T)
        shift = self.move_target[:3] - self.move_start[:3]
        duration_s = max(
            float(np.linalg.norm(shift)) / self.move_speed_mps,
            float(np.linalg.norm(turn)) / MOVE_TURN_RATE_RAD_S,
            dt_s,
        )
        self.move_progress = min(self.move_progress + dt_s / duration_s, 1.0)
        if self.move_progress >= 1.0:
            self.pose[:] = self.move_target
            self.speed[:] = 0.0
            self.move_target = None
            if self.move_sync:
                self.script_state = DONE
            return
        self.speed[:3] = shift / duration_s
        self.speed[3:] = turn / duration_s
        self.pose[:3] = self.move_start[:3] + self.move_progress * shift
        self.pose[3:] = matrix_to_rotvec(rotvec_to_matrix(self.move_progress * turn) @ start)

    def execute(self, values: dict[str, Any], now_s: float) -> None:
        """Play the control script's part for one input package."""
        self.last_input_s = now_s
        cmd = int(values.get("input_int_register_0", CMD_NONE))
        if cmd == CMD_NONE:
            if self.script_state == DONE:
                self.script_state = READY
            return
        self.commands.append(cmd)
        if not self.program_running or self.script_state != READY:
            return
        doubles = [values.get(f"input_double_register_{i}", 0.0) for i in range(8)]
        if cmd in REALTIME_COMMANDS:
            if cmd == CMD_SPEEDL and not self.protective_stop:
                self.move_target = None
                self.speed_target = np.array(doubles[:6])
                self.acceleration = max(float(doubles[6]), 1e-3)
            return
        if self.protective_stop:
            return  # the script is paused: the command is never done
        self._execute_blocking(cmd, doubles, int(values.get("input_int_register_1", 0)))

    def _execute_blocking(self, cmd: int, doubles: list[float], async_flag: int) -> None:
        self.script_state = DONE
        if cmd == CMD_MOVEL:
            self.speed_target = np.zeros(6)
            self.move_start = self.pose.copy()
            self.move_target = np.array(doubles[:6])
            self.move_progress = 0.0
            self.move_speed_mps = max(float(doubles[6]), 1e-4)
            self.move_sync = async_flag == 0
            if self.move_sync:
                self.script_state = 0  # busy until the move ends
        elif cmd in (CMD_SPEED_STOP, CMD_STOPL):
            if cmd == CMD_STOPL:
                self.halt()
            self.speed_target = np.zeros(6)
            self.acceleration = max(float(doubles[0]), 1e-3)
        elif cmd == CMD_SET_WATCHDOG:
            self.watchdog_hz = float(doubles[0])
        elif cmd == CMD_STOP_SCRIPT:
            self.halt()
            self.program_running = False
            self.script_state = 0

    def outputs(self, now_s: float) -> dict[str, Any]:
        """Every output variable the emulator serves."""
        values: dict[str, Any] = {
            "timestamp": now_s,
            "actual_TCP_pose": self.pose.copy(),
            "target_TCP_pose": self.pose.copy(),
            "actual_TCP_speed": self.speed.copy(),
            "target_TCP_speed": self.speed.copy(),
            "actual_TCP_force": self.force.copy(),
            "robot_mode": 7,
            "safety_mode": 3 if self.protective_stop else 1,
            "safety_status": 3 if self.protective_stop else 1,
            "runtime_state": 2 if self.program_running else 1,
            "robot_status_bits": 1 | (2 if self.program_running else 0),
            "safety_status_bits": self._safety_status_bits(),
            "output_int_register_0": self.script_state,
            "speed_scaling": 1.0,
            "target_speed_fraction": 1.0,
        }
        return values

    def _safety_status_bits(self) -> int:
        if self.safety_bits is not None:
            return self.safety_bits
        return 4 if self.protective_stop else 1


class RTDESession:
    """One client connection to the RTDE port."""

    def __init__(self, emulator: URControllerEmulator, sock: socket.socket) -> None:
        self.emulator = emulator
        self.sock = sock
        self.output_names: list[str] = []
        self.output_types: list[str] = []
        self.period_s = 1.0 / PHYSICS_RATE_HZ
        self.inputs: dict[int, tuple[list[str], list[str]]] = {}
        self.started = threading.Event()
        self.closed = threading.Event()

    def serve(self) -> None:
        threading.Thread(target=self._stream, daemon=True).start()
        try:
            while not self.closed.is_set():
                header = self._read(3)
                size, kind = struct.unpack(">HB", header)
                self._handle(chr(kind), self._read(size - 3))
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            self.close()

    def close(self) -> None:
        self.closed.set()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()

    def _read(self, count: int) -> bytes:
        data = b""
        while len(data) < count:
            chunk = self.sock.recv(count - len(data))
            if not chunk:
                raise ConnectionError("client closed")
            data += chunk
        return data

    def _send(self, kind: str, payload: bytes) -> None:
        with self.emulator.send_lock:
            self.sock.sendall(pack_package(kind, payload))

    def _handle(self, kind: str, payload: bytes) -> None:
        if kind == "V":
            self._send("V", struct.pack(">B", 1))
        elif kind == "v":
            self._send("v", struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == "O":
            (frequency_hz,) = struct.unpack(">d", payload[:8])
            self.period_s = 1.0 / max(min(frequency_hz, 500.0), 1.0)
            self.output_names = _names(payload[8:])
            self.output_types = [variable_type(n) for n in self.output_names]
            self._send("O", struct.pack(">B", 1) + ",".join(self.output_types).encode())
        elif kind == "I":
            names = _names(payload)
            types = [variable_type(n) for n in names]
            recipe_id = len(self.inputs) + 1
            self.inputs[recipe_id] = (names, types)
            self._send("I", struct.pack(">B", recipe_id) + ",".join(types).encode())
        elif kind == "S":
            self._send("S", struct.pack(">B", 1))
            self.started.set()
        elif kind == "P":
            self.started.clear()
            self._send("P", struct.pack(">B", 1))
        elif kind == "U":
            self._input(payload)

    def _input(self, payload: bytes) -> None:
        recipe_id = payload[0]
        if recipe_id not in self.inputs:
            return
        names, types = self.inputs[recipe_id]
        fmt = ">" + "".join(_FORMATS[t] for t in types)
        values = struct.unpack(fmt, payload[1 : 1 + struct.calcsize(fmt)])
        self.emulator.on_input(dict(zip(names, values, strict=True)))

    def _stream(self) -> None:
        next_s = time.monotonic()
        while not self.closed.is_set():
            next_s += self.period_s
            time.sleep(max(0.0, next_s - time.monotonic()))
            if not self.started.is_set() or self.emulator.silent.is_set():
                continue
            try:
                self._send("U", self._output_payload())
            except OSError:
                self.close()

    def _output_payload(self) -> bytes:
        values = self.emulator.outputs()
        parts = [struct.pack(">B", 1)]
        for name, kind in zip(self.output_names, self.output_types, strict=True):
            value = values.get(name, 0)
            fmt = ">" + _FORMATS.get(kind, "d")
            flat = np.atleast_1d(np.asarray(value)).tolist()
            parts.append(struct.pack(fmt, *flat))
        return b"".join(parts)


class URControllerEmulator:
    """The controller: listeners on ``host`` and the simulated robot."""

    def __init__(self, host: str, start_pose: list[float]) -> None:
        self.host = host
        self.arm = ArmSim(np.array(start_pose, dtype=np.float64))
        self.lock = threading.Lock()
        self.send_lock = threading.Lock()
        self.silent = threading.Event()
        self.refusing = threading.Event()
        self.stopped = threading.Event()
        self.start_s = time.monotonic()
        self.sockets: list[socket.socket] = []
        self.sessions: list[RTDESession] = []
        self.listeners: list[socket.socket] = []
        self.script_uploads = 0
        self.dashboard_log: list[str] = []

    def now_s(self) -> float:
        return time.monotonic() - self.start_s

    # --- robot -------------------------------------------------------------------------
    def on_input(self, values: dict[str, Any]) -> None:
        if self.silent.is_set():
            return
        with self.lock:
            self.arm.execute(values, self.now_s())

    def outputs(self) -> dict[str, Any]:
        with self.lock:
            return self.arm.outputs(self.now_s())

    def _physics(self) -> None:
        period_s = 1.0 / PHYSICS_RATE_HZ
        next_s = time.monotonic()
        while not self.stopped.is_set():
            next_s += period_s
            time.sleep(max(0.0, next_s - time.monotonic()))
            with self.lock:
                self.arm.step(period_s, self.now_s())

    # --- network ------------------------------------------------------------------------
    def start(self) -> None:
        self.listen()
        threading.Thread(target=self._physics, daemon=True).start()

    def listen(self) -> None:
        self.refusing.clear()
        handlers = [(RTDE_PORT, self._rtde), (DASHBOARD_PORT, self._dashboard)]
        handlers += [(port, self._script) for port in SCRIPT_PORTS]
        for port, handler in handlers:
            server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            server.bind((self.host, port))
            server.listen(8)
            self.listeners.append(server)
            threading.Thread(target=self._accept, args=(server, handler), daemon=True).start()

    def _accept(self, server: socket.socket, handler: Any) -> None:
        while True:
            try:
                client, _ = server.accept()
            except OSError:
                return
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.sockets.append(client)
            threading.Thread(target=handler, args=(client,), daemon=True).start()

    def _rtde(self, client: socket.socket) -> None:
        session = RTDESession(self, client)
        self.sessions.append(session)
        session.serve()

    def _dashboard(self, client: socket.socket) -> None:
        with contextlib.suppress(OSError), client.makefile("rwb", buffering=0) as stream:
            stream.write(b"Connected: Universal Robots Dashboard Server\n")
            for raw in stream:
                command = raw.decode(errors="replace").strip()
                self.dashboard_log.append(command)
                stream.write((self._dashboard_answer(command) + "\n").encode())

    def _dashboard_answer(self, command: str) -> str:
        with self.lock:
            arm = self.arm
            if command == "PolyscopeVersion":
                return POLYSCOPE_VERSION
            if command == "robotmode":
                return "Robotmode: RUNNING"
            if command in ("safetystatus", "safetymode"):
                state = "PROTECTIVE_STOP" if arm.protective_stop else "NORMAL"
                return f"{command.capitalize()}: {state}"
            if command == "unlock protective stop":
                if not arm.protective_stop:
                    return "Protective stop releasing failed: not in protective stop"
                arm.protective_stop = False
                return "Protective stop releasing"
            if command == "stop":
                arm.halt()
                arm.program_running = False
                arm.script_state = 0
                return "Stopped"
            if command == "running":
                return f"Program running: {str(arm.program_running).lower()}"
            if command == "is in remote control":
                return "true"
        return f"could not understand: '{command}'"

    def _script(self, client: socket.socket) -> None:
        client.settimeout(0.3)
        data = b""
        with contextlib.suppress(OSError):
            while True:
                try:
                    chunk = client.recv(65536)
                except TimeoutError:
                    if data:
                        self._load_script(data)
                        data = b""
                    continue
                if not chunk:
                    break
                data += chunk
        if data:
            self._load_script(data)

    def _load_script(self, script: bytes) -> None:
        if b"def " not in script:
            return
        with self.lock:
            self.script_uploads += 1
            self.arm.program_running = True
            self.arm.script_state = READY
            self.arm.halt()

    # --- test hooks ---------------------------------------------------------------------
    def drop(self) -> None:
        """Close every connection and refuse new ones (a pulled cable / controller crash)."""
        self.refusing.set()
        for server in self.listeners:
            with contextlib.suppress(OSError):
                server.shutdown(socket.SHUT_RDWR)  # wakes the thread blocked in accept()
            with contextlib.suppress(OSError):
                server.close()
        self.listeners.clear()
        for sock in self.sockets:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                sock.close()
        self.sockets.clear()
        with self.lock:
            self.arm.halt()

    def control(self, request: tuple[Any, ...]) -> Any:
        """Handle one test request; returns its answer."""
        name, *args = request
        if name == "protective_stop":
            with self.lock:
                self.arm.protective_stop = True
        elif name == "drop":
            self.drop()
        elif name == "restore":
            self.listen()
        elif name == "silent":
            (self.silent.set if args[0] else self.silent.clear)()
        elif name == "safety_bits":
            with self.lock:
                self.arm.safety_bits = args[0]
        elif name == "set_force":
            with self.lock:
                self.arm.force = np.array(args[0], dtype=np.float64)
        elif name == "state":
            with self.lock:
                return {
                    "pose": self.arm.pose.tolist(),
                    "speed": self.arm.speed.tolist(),
                    "protective_stop": self.arm.protective_stop,
                    "program_running": self.arm.program_running,
                    "commands": list(self.arm.commands),
                    "watchdog_hz": self.arm.watchdog_hz,
                    "watchdog_trips": self.arm.watchdog_trips,
                    "script_uploads": self.script_uploads,
                    "dashboard": list(self.dashboard_log),
                }
        return None


def serve(host: str, start_pose: list[float], pipe: Connection) -> None:
    """Entry point of the emulator process: serve until the pipe says ``shutdown``."""
    emulator = URControllerEmulator(host, start_pose)
    emulator.start()
    pipe.send("ready")
    while True:
        try:
            request = pipe.recv()
        except EOFError:
            break
        if request[0] == "shutdown":
            break
        pipe.send(emulator.control(request))
    emulator.stopped.set()
    emulator.drop()


class URControllerProcess:
    """The emulator in a separate (spawned) process; use as a context manager."""

    def __init__(self, host: str, start_pose: list[float] | None = None) -> None:
        self.host = host
        pose = start_pose or [0.0, 0.45, 0.15, np.pi, 0.0, 0.0]
        spawn = multiprocessing.get_context("spawn")
        self._pipe, child = spawn.Pipe()
        self._process = spawn.Process(target=serve, args=(host, pose, child), daemon=True)
        self._lock = threading.Lock()

    def __enter__(self) -> URControllerProcess:
        self._process.start()
        if not self._pipe.poll(30.0):
            self.close()
            raise RuntimeError("the UR emulator did not start within 30 s")
        self._pipe.recv()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        """For a spawned process that drives the emulator (its host and request pipe; the
        emulator's own process stays with the parent, which closes it)."""
        return {"host": self.host, "_pipe": self._pipe}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state, _lock=threading.Lock())

    def request(self, *request: Any, timeout_s: float = 5.0) -> Any:
        with self._lock:
            self._pipe.send(request)
            if not self._pipe.poll(timeout_s):
                raise TimeoutError(f"the UR emulator did not answer {request[0]!r}")
            return self._pipe.recv()

    def protective_stop(self) -> None:
        self.request("protective_stop")

    def drop(self) -> None:
        self.request("drop")

    def restore(self) -> None:
        self.request("restore")

    def silent(self, on: bool) -> None:
        self.request("silent", on)

    def set_safety_bits(self, bits: int | None) -> None:
        """Report ``bits`` as ``safety_status_bits`` (None: those of the protective stop)."""
        self.request("safety_bits", bits)

    def set_force(self, wrench: list[float]) -> None:
        self.request("set_force", wrench)

    def state(self) -> dict[str, Any]:
        answer: dict[str, Any] = self.request("state")
        return answer

    def dashboard(self, command: str, timeout_s: float = 2.0) -> str:
        """Send one dashboard command as a person at the pendant would (e.g. to unlock)."""
        with socket.create_connection((self.host, DASHBOARD_PORT), timeout=timeout_s) as sock:
            stream = sock.makefile("rwb", buffering=0)
            stream.readline()
            stream.write(command.encode() + b"\n")
            return stream.readline().decode().strip()

    def close(self) -> None:
        if self._process.is_alive():
            with contextlib.suppress(OSError, BrokenPipeError):
                self._pipe.send(("shutdown",))
            self._process.join(3.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(3.0)
