"""``robotiq.2f85`` against the Modbus RTU emulator on a pseudo-terminal and the socket one."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from emulators.loopback import next_loopback
from emulators.robotiq import GripperSim, RobotiqPty, RobotiqSocket
from vistac.errors import HardwareError
from vistac.pluginmanager import Plugins
from vistac.plugins.hardware.robotiq import modbus
from vistac.scheduler import Scheduler
from vistac.skill import validate_skill
from vistac.testing import build_components, check_component


@pytest.fixture
def device() -> Iterator[RobotiqPty]:
    with RobotiqPty(GripperSim(object_width_m=0.04)) as pty:
        yield pty


def make_gripper(plugins: Plugins, tmp_path: Path, **options: Any) -> Any:
    components = {"gripper": {"plugin": "robotiq.2f85", "with": options}}
    return build_components(components, tmp_path, plugins=plugins).component("gripper")


def settle(gripper: Any, timeout_s: float = 2.0) -> Any:
    deadline = time.monotonic() + timeout_s
    state = gripper.state()
    while state.moving and time.monotonic() < deadline:
        time.sleep(0.02)
        state = gripper.state()
    return state


def test_crc16_known_answer() -> None:
    # The Robotiq manual's activation request: 09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30
    frame = modbus.write_request(9, bytes(6))
    assert frame.hex() == "091003e8000306000000000000" + "7330"
    assert modbus.read_request(9).hex() == "090407d00003" + "b1ce"


def test_activates_moves_and_detects_an_object(
    device: RobotiqPty, plugins: Plugins, tmp_path: Path
) -> None:
    gripper = make_gripper(plugins, tmp_path, port=device.path)
    assert device.gripper.activation_status == 3
    gripper.open()
    opened = settle(gripper)
    assert opened.width_m == pytest.approx(0.085) and not opened.object_detected
    gripper.close()
    assert gripper.state().moving
    closed = settle(gripper)
    assert closed.object_detected and not closed.moving
    assert closed.width_m == pytest.approx(0.04, abs=0.001)  # stopped on the 4 cm object
    gripper.release()


def test_bad_crc_and_silence_give_clear_errors(
    device: RobotiqPty, plugins: Plugins, tmp_path: Path
) -> None:
    gripper = make_gripper(plugins, tmp_path, port=device.path, timeout_s=0.1)
    device.corrupt_crc = True
    with pytest.raises(HardwareError, match="bad CRC"):
        gripper.state()
    device.corrupt_crc = False
    device.silent = True
    started = time.monotonic()
    with pytest.raises(HardwareError, match="did not answer within 100 ms"):
        gripper.open()
    assert time.monotonic() - started < 1.0
    gripper.release()


def test_faults_are_surfaced(device: RobotiqPty, plugins: Plugins, tmp_path: Path) -> None:
    gripper = make_gripper(plugins, tmp_path, port=device.path)
    device.gripper.fault = 0x0E
    with pytest.raises(HardwareError, match="fault 0xe: overcurrent"):
        gripper.state()
    gripper.release()


def test_missing_port_is_a_clear_error(plugins: Plugins, tmp_path: Path) -> None:
    with pytest.raises(HardwareError, match="cannot open serial port /dev/nonexistent"):
        make_gripper(plugins, tmp_path, port="/dev/nonexistent")


def test_ur_gripper_socket_transport(plugins: Plugins, tmp_path: Path) -> None:
    emulator = RobotiqSocket(next_loopback(), 63352, GripperSim(object_width_m=0.03))
    try:
        gripper = make_gripper(plugins, tmp_path, transport="ur_socket", host=emulator.host)
        gripper.close()
        closed = settle(gripper)
        assert closed.object_detected and closed.width_m == pytest.approx(0.03, abs=0.001)
        gripper.release()
    finally:
        emulator.close()


def test_robotiq_conforms(device: RobotiqPty, plugins: Plugins, tmp_path: Path) -> None:
    gripper = make_gripper(plugins, tmp_path, port=device.path)
    check_component(gripper, advance=time.sleep)
    gripper.release()



def test_a_run_ends_with_the_fingers_left_alone_and_the_port_released(
    device: RobotiqPty, plugins: Plugins, tmp_path: Path
) -> None:
    # Gripper.close() closes the fingers: the run's end must call release() instead
    components = {"gripper": {"plugin": "robotiq.2f85", "with": {"port": device.path}}}
    data = {"version": 1, "name": "t", "components": components, "tree": "stop"}
    skill = validate_skill(data, tmp_path / "s.yaml", plugins.registry)
    scheduler = Scheduler(skill, plugins, tmp_path / "out")
    gripper = scheduler.ctx.component("gripper")  # kept here, so only release() shuts the port
    assert scheduler.run().status == "success"
    assert (device.gripper.requested, device.gripper.going) == (0, False)
    assert not gripper.transport.serial.is_open
