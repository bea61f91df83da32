"""``contactile.papillarray`` on a pseudo-terminal stream and ``can.force_sensor`` on
python-can's virtual bus: decoding, frames, malformed data and staleness."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from conftest import wait_for
from emulators.papillarray import PapillArrayPty
from vistac.errors import HardwareError, SafetyError
from vistac.pluginmanager import Plugins
from vistac.plugins.hardware.contactile import protocol
from vistac.plugins.hardware.frames import gripper_to_world_xy
from vistac.testing import build_components, check_component
from vistac.types import ArmState


@pytest.fixture
def stream() -> Iterator[PapillArrayPty]:
    with PapillArrayPty(rate_hz=100.0) as pty:
        yield pty


def build(plugins: Plugins, tmp_path: Path, components: dict[str, Any]) -> Any:
    return build_components(components, tmp_path, plugins=plugins)


def test_frame_round_trip_and_resynchronisation() -> None:
    pillars = np.arange(54, dtype=np.float64).reshape(9, 6) / 8
    frame = protocol.SensorFrame(1, 1234, pillars, np.array([1.0, -2.0, 3.0, 0.5, 0.0, 0.25]))
    data = protocol.encode(frame)
    assert len(data) == protocol.frame_size(9) == 252
    splitter = protocol.FrameSplitter()
    broken = data[:-1] + bytes([data[-1] ^ 1])
    frames = splitter.feed(b"\x01\x02" + broken + data[:100]) + splitter.feed(data[100:])
    assert splitter.malformed == 1
    assert len(frames) == 1 and frames[0].sensor_id == 1 and frames[0].device_time_us == 1234
    assert np.allclose(frames[0].pillars, pillars) and np.allclose(
        frames[0].global_wrench[:3], [1, -2, 3]
    )


def test_gripper_to_world_known_answer() -> None:
    world = gripper_to_world_xy(np.array([[1.0, 0.0, 5.0], [0.0, 2.0, 0.0]]), math.pi / 2)
    assert np.allclose(world, [[0.0, 1.0], [-2.0, 0.0]])


def test_papillarray_decodes_rotates_and_biases(
    stream: PapillArrayPty, plugins: Plugins, tmp_path: Path
) -> None:
    ctx = build(
        plugins,
        tmp_path,
        {"tactile": {"plugin": "contactile.papillarray", "with": {"port": stream.path}}},
    )
    tactile = ctx.component("tactile")
    try:
        stream.set_force(0, [1.0, 0.0, 2.0])  # sensor frame: tangential x, normal z
        stream.set_force(1, [0.5, 0.0, 3.0])
        # pad 0 faces +y: normal -> gripper +y; pad 1 faces -y (x flipped too)
        assert wait_for(
            lambda: np.allclose(tactile.read().force_n, [[1.0, 2.0], [-0.5, -3.0]], atol=1e-5)
        )
        tactile.bias()
        assert wait_for(lambda: np.allclose(tactile.read().force_n, 0.0, atol=1e-6))
        assert stream.bias_commands == 1
    finally:
        tactile.close()


def test_papillarray_uses_the_arm_yaw(
    stream: PapillArrayPty, plugins: Plugins, tmp_path: Path
) -> None:
    components = {
        "arm": {"plugin": "test.arm"},
        "tactile": {"plugin": "contactile.papillarray", "with": {"port": stream.path}},
    }
    ctx = build(plugins, tmp_path, components)
    tactile, arm = ctx.component("tactile"), ctx.component("arm")
    try:
        stream.set_force(0, [1.0, 0.0, 0.0])
        assert wait_for(lambda: np.allclose(tactile.read().force_n[0], [1.0, 0.0], atol=1e-5))
        arm.state = lambda: ArmState(np.array([0, 0, 0, math.pi / 2]), np.zeros(4), 0.0)
        assert np.allclose(tactile.read().force_n[0], [0.0, 1.0], atol=1e-5)
    finally:
        tactile.close()


def test_papillarray_skips_malformed_frames_and_goes_stale(
    stream: PapillArrayPty, plugins: Plugins, tmp_path: Path
) -> None:
    ctx = build(
        plugins,
        tmp_path,
        {"tactile": {"plugin": "contactile.papillarray", "with": {"port": stream.path}}},
    )
    tactile = ctx.component("tactile")
    try:
        stream.corrupt_every = 3
        stream.set_force(0, [0.0, 0.0, 1.0])
        assert wait_for(lambda: tactile.malformed >= 5)
        assert np.allclose(tactile.read().force_n[0], [0.0, 1.0], atol=1e-5)  # good frames pass
        stream.corrupt_every = 0
        ctx.check_fresh("tactile", tactile.read().timestamp_s, 0.1)  # fresh now
        stream.silent = True
        time.sleep(0.3)
        with pytest.raises(SafetyError, match="stale tactile data"):
            ctx.check_fresh("tactile", tactile.read().timestamp_s, 0.1)
    finally:
        tactile.close()


def test_papillarray_without_data_is_a_clear_error(plugins: Plugins, tmp_path: Path) -> None:
    with PapillArrayPty() as silent_stream:  # never started streaming: no frames
        silent_stream.silent = True
        components = {
            "tactile": {
                "plugin": "contactile.papillarray",
                "with": {"port": silent_stream.path, "first_data_timeout_s": 0.3},
            }
        }
        with pytest.raises(HardwareError, match=r"no data from pads \[0, 1\] within 0.3 s"):
            build(plugins, tmp_path, components)


def test_papillarray_conforms(stream: PapillArrayPty, plugins: Plugins, tmp_path: Path) -> None:
    ctx = build(
        plugins,
        tmp_path,
        {"tactile": {"plugin": "contactile.papillarray", "with": {"port": stream.path}}},
    )
    try:
        check_component(ctx.component("tactile"), advance=time.sleep)
    finally:
        ctx.component("tactile").close()


CAN_CONFIG = {
    "interface": "virtual",
    "pads": [
        {"arbitration_id": 0x101, "scale_n_per_count": 0.01},
        {"arbitration_id": 0x102, "scale_n_per_count": 0.01, "axes": 3, "offset_n": [0.5, 0, 0]},
    ],
}


class CanPublisher:
    """Publishes the two pads' counts on the virtual bus at 100 Hz."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.counts = {0x101: [100, -200], 0x102: [0, 300, 7]}
        self.extra: list[can.Message] = []
        self.running = True
        self.sent = 0

    def step(self) -> None:
        for arbitration_id, counts in self.counts.items():
            data = np.asarray(counts, dtype="<i2").tobytes()
            self.bus.send(
                can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
            )
        for message in self.extra:
            self.bus.send(message)
        self.sent += 1


@pytest.fixture
def can_bus(request: pytest.FixtureRequest) -> Iterator[tuple[CanPublisher, str]]:
    import threading

    channel = f"vistac-{request.node.name}"
    publisher = CanPublisher(channel)

    def loop() -> None:
        while publisher.running:
            publisher.step()
            time.sleep(0.01)

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    yield publisher, channel
    publisher.running = False
    thread.join(1.0)
    publisher.bus.shutdown()


def test_can_sensor_decodes_scales_and_counts_malformed(
    can_bus: tuple[CanPublisher, str], plugins: Plugins, tmp_path: Path
) -> None:
    publisher, channel = can_bus
    config = {**CAN_CONFIG, "channel": channel}
    ctx = build(plugins, tmp_path, {"tactile": {"plugin": "can.force_sensor", "with": config}})
    tactile = ctx.component("tactile")
    try:
        assert np.allclose(tactile.read().force_n, [[1.0, -2.0], [0.5, 3.0]])
        publisher.extra = [
            can.Message(arbitration_id=0x101, data=b"\x01", is_extended_id=False),  # too short
            can.Message(arbitration_id=0x555, data=b"\x01\x02", is_extended_id=False),  # other
        ]
        assert wait_for(lambda: tactile.malformed >= 3)
        assert np.allclose(tactile.read().force_n, [[1.0, -2.0], [0.5, 3.0]])
        tactile.bias()
        assert np.allclose(tactile.read().force_n, 0.0)
        publisher.running = False
        time.sleep(0.3)
        with pytest.raises(SafetyError, match="stale tactile"):
            ctx.check_fresh("tactile", tactile.read().timestamp_s, 0.1)
    finally:
        tactile.close()


def test_can_sensor_conforms(
    can_bus: tuple[CanPublisher, str], plugins: Plugins, tmp_path: Path
) -> None:
    config = {**CAN_CONFIG, "channel": can_bus[1]}
    ctx = build(plugins, tmp_path, {"tactile": {"plugin": "can.force_sensor", "with": config}})
    try:
        check_component(ctx.component("tactile"), advance=time.sleep)
    finally:
        ctx.component("tactile").close()


def test_can_sensor_rejects_duplicate_ids(plugins: Plugins, tmp_path: Path) -> None:
    pads = [{"arbitration_id": 1}, {"arbitration_id": 1}]
    components = {
        "tactile": {"plugin": "can.force_sensor", "with": {"interface": "virtual", "pads": pads}}
    }
    with pytest.raises(HardwareError, match="must be distinct"):
        build(plugins, tmp_path, components)
