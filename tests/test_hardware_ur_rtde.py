"""``ur_rtde.arm`` with the real ``ur_rtde`` client against the emulated UR controller."""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from conftest import wait_for
from emulators.loopback import next_loopback
from emulators.ur_controller import URControllerProcess
from vistac.errors import HardwareError, SafetyError
from vistac.pluginmanager import Plugins
from vistac.plugins.hardware.deadline import DeadlineExceededError, call_with_deadline
from vistac.plugins.hardware.ur_rtde import arm as ur_arm
from vistac.plugins.hardware.ur_rtde.frames import arm_pose, tcp_pose
from vistac.testing import build_components, check_component

START = [0.0, 0.45, 0.15, np.pi, 0.0, 0.0]


@pytest.fixture
def emulator() -> Iterator[URControllerProcess]:
    with URControllerProcess(next_loopback(), START) as process:
        yield process


@contextlib.contextmanager
def open_arm(plugins: Plugins | None, tmp_path: Path, host: str, **options: Any) -> Iterator[Any]:
    """A ``ur_rtde.arm`` on ``host`` with ``options``, closed on the way out."""
    components = {"arm": {"plugin": "ur_rtde.arm", "with": {"host": host, **options}}}
    arm = build_components(components, tmp_path, plugins=plugins).component("arm")
    try:
        yield arm
    finally:
        arm.close()


def test_frames_round_trip() -> None:
    for yaw in (0.0, 0.4, -2.5, 3.0):
        pose = np.array([0.1, 0.5, 0.2, yaw])
        assert np.allclose(arm_pose(tcp_pose(pose)), pose)
    assert np.allclose(tcp_pose([0, 0, 0, 0])[3:], [np.pi, 0, 0])  # tool down


def test_deadline_returns_value_or_times_out() -> None:
    assert call_with_deadline(lambda: 42, 1.0, "answer") == 42
    started = time.monotonic()
    with pytest.raises(DeadlineExceededError, match="did not return within 100 ms"):
        call_with_deadline(lambda: time.sleep(5), 0.1, "sleeper")
    assert time.monotonic() - started < 0.5
    with pytest.raises(HardwareError, match="boom failed: bad"):
        call_with_deadline(lambda: (_ for _ in ()).throw(ValueError("bad")), 1.0, "boom")


def test_streams_velocity_reads_pose_and_force(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    with open_arm(plugins, tmp_path, emulator.host) as arm:
        start = arm.state()
        assert np.allclose(start.pose, [0.0, 0.45, 0.15, 0.0], atol=1e-6)
        assert emulator.state()["script_uploads"] == 1
        assert emulator.state()["watchdog_hz"] == 2.0
        emulator.set_force([1.0, -2.0, 3.0, 0.0, 0.0, 0.1])
        assert wait_for(lambda: np.allclose(arm.wrench(), [1.0, -2.0, 3.0, 0.0, 0.0, 0.1]))
        for _ in range(10):  # 0.5 s at 0.02 m/s along +x
            arm.command_velocity(np.array([0.02, 0.0, 0.0, 0.0]))
            time.sleep(0.05)
        moving = arm.state()
        assert moving.twist[0] == pytest.approx(0.02, abs=1e-6)
        arm.stop()
        time.sleep(0.1)
        stopped = arm.state()
        assert np.linalg.norm(stopped.twist) < 1e-6
        assert stopped.pose[0] == pytest.approx(0.01, abs=0.003)  # 0.02 m/s for ~0.5 s
        assert stopped.timestamp_s > start.timestamp_s
        assert 10 in emulator.state()["commands"] and 15 in emulator.state()["commands"]


def test_speed_is_capped_and_moves_stay_in_the_workspace(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    with open_arm(plugins, tmp_path, emulator.host, workspace_max_m=[0.02, 0.85, 0.5]) as arm:
        arm.command_velocity(np.array([1.0, 1.0, 0.0, 5.0]))  # far above the caps
        time.sleep(0.15)
        twist = arm.state().twist
        assert np.linalg.norm(twist[:3]) == pytest.approx(0.025, rel=1e-6)
        assert twist[3] == pytest.approx(0.5)
        arm.stop()
        with pytest.raises(SafetyError, match="outside the workspace on x"):
            arm.move_to(np.array([0.1, 0.45, 0.15, 0.0]))
        arm.move_to(np.array([0.02, 0.45, 0.15, 0.0]), speed_mps=1.0)  # capped to 25 mm/s
        assert arm.state().pose[0] == pytest.approx(0.02, abs=3e-4)
        time.sleep(0.1)  # the last 0.2 mm
        with pytest.raises(SafetyError, match=r"leave the workspace \(x max = 0\.020 m\)"):
            arm.command_velocity(np.array([0.01, 0.0, 0.0, 0.0]))
        arm.command_velocity(np.array([-0.01, 0.0, 0.0, 0.0]))  # back inside is allowed
        arm.stop()


def test_dropped_connection_is_detected_fast_and_nothing_blocks(
    emulator: URControllerProcess, tmp_path: Path
) -> None:
    """In a process of its own, as on a robot. ur_rtde's RTDEControlInterface constructor
    sometimes crashes (SIGSEGV) on the reconnect after the drop: 2 of 32 runs of this module
    in one process, once in a full suite with the arm in a process of its own. That crash is
    ur_rtde's, not the arm's logic, so one such crash is retried with a warning; any other
    failure, or a second crash, fails the test."""
    spawn = multiprocessing.get_context("spawn")
    for attempt in range(2):
        results = spawn.Queue()
        child = spawn.Process(target=_drop_and_reconnect, args=(emulator, str(tmp_path), results))
        child.start()
        child.join(60)
        if child.exitcode == -signal.SIGSEGV and attempt == 0:
            warnings.warn("ur_rtde crashed on the reconnect (SIGSEGV); tried again", stacklevel=1)
            continue  # the crash came after the emulator was restored
        assert child.exitcode == 0, f"the arm's process ended with {child.exitcode}"
        break
    outcome = results.get(timeout=5)
    assert isinstance(outcome, float), outcome
    assert outcome < 0.5, f"disconnect detected after {outcome:.3f} s"


def _drop_and_reconnect(emulator: URControllerProcess, tmp_dir: str, results: Any) -> None:
    """Command, drop the connection, check the arm notices fast and never blocks, restore
    and reconnect. Puts the seconds from the drop to the HardwareError in ``results``, or
    what went wrong."""
    try:
        results.put(_drop_and_reconnect_s(emulator, Path(tmp_dir)))
    except BaseException as error:  # reported to the test in the parent process
        results.put(f"{type(error).__name__}: {error}")


def _drop_and_reconnect_s(emulator: URControllerProcess, tmp_dir: Path) -> float:
    with open_arm(None, tmp_dir, emulator.host) as arm:
        arm.command_velocity(np.array([0.01, 0.0, 0.0, 0.0]))
        dropped_at = time.monotonic()
        emulator.drop()
        with pytest.raises(HardwareError):
            while time.monotonic() - dropped_at < 2.0:  # a 15 Hz control loop
                arm.command_velocity(np.array([0.01, 0.0, 0.0, 0.0]))
                time.sleep(1 / 15)
        latency_s = time.monotonic() - dropped_at
        assert not arm.connected
        with pytest.raises(HardwareError, match="not connected"):
            arm.state()
        arm.stop()  # never raises, never blocks
        emulator.restore()
        arm.reconnect()
        assert arm.connected and arm.state().pose.shape == (4,)
        return latency_s


class FakeInterface:
    """An RTDE interface that records disconnects."""

    def __init__(self, connected: bool) -> None:
        self.connected, self.disconnects = connected, 0

    def isConnected(self) -> bool:  # noqa: N802 (ur_rtde's name)
        return self.connected

    def disconnect(self) -> None:
        self.disconnects += 1


def test_a_connection_closed_already_is_not_disconnected_again() -> None:
    # ur_rtde's own thread closes a dropped connection; a second disconnect crashed it
    open_interface, closed_interface = FakeInterface(True), FakeInterface(False)
    for interface in (open_interface, closed_interface):
        ur_arm._disconnect(interface)
    assert (open_interface.disconnects, closed_interface.disconnects) == (1, 0)


def test_closing_under_a_blocked_command_disconnects_nothing(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # disconnecting either interface under a blocked moveL crashed ur_rtde
    monkeypatch.setattr(ur_arm, "_DISCONNECT_TIMEOUT_S", 0.05)
    interfaces = [FakeInterface(True), FakeInterface(True)]
    arm = SimpleNamespace(_lock=threading.Lock(), config=SimpleNamespace(host="127.0.0.9"))
    for blocked, disconnects in ((True, 0), (False, 1)):
        arm._control, arm._receive = interfaces
        if blocked:
            arm._lock.acquire()  # a command still running
        ur_arm.URArm._abandon(arm)  # type: ignore[arg-type]
        assert [i.disconnects for i in interfaces] == [disconnects] * 2
        assert arm._control is None and arm._receive is None
        assert ("still blocked" in caplog.text) == blocked
        if blocked:
            arm._lock.release()
            caplog.clear()


def test_silent_controller_times_out_a_blocking_move(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    options = {"max_data_age_s": 1.0, "move_timeout_margin_s": 0.3}
    with open_arm(plugins, tmp_path, emulator.host, **options) as arm:
        emulator.silent(True)  # moveL waits for an answer (ur_rtde gives up after about 4 s)
        started = time.monotonic()
        with pytest.raises(HardwareError):
            arm.move_to(np.array([0.005, 0.45, 0.15, 0.0]))
        assert time.monotonic() - started < 1.5
        with pytest.raises(HardwareError, match="not connected"):
            arm.command_velocity(np.zeros(4))
        # ur_rtde's own timeout of a moveL on a silent controller (about 4 s) sometimes
        # crashes the process: let the data flow again, and the blocked call return
        emulator.silent(False)
        wait_for(
            lambda: not any(t.name.startswith("deadline:moveL") for t in threading.enumerate()),
            timeout_s=6.0,
        )


def test_protective_stop_refuses_motion_until_a_person_clears_it(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    with open_arm(plugins, tmp_path, emulator.host) as arm:
        arm.command_velocity(np.array([0.02, 0.0, 0.0, 0.0]))
        emulator.protective_stop()
        assert wait_for(lambda: arm.state().protective_stop)
        with pytest.raises(SafetyError, match="protective stop: motion refused"):
            arm.command_velocity(np.array([0.02, 0.0, 0.0, 0.0]))
        with pytest.raises(SafetyError, match="protective stop"):
            arm.move_to(np.array([0.0, 0.5, 0.15, 0.0]))
        held = emulator.state()["pose"]
        time.sleep(0.2)
        assert emulator.state()["pose"] == held  # nothing moves
        assert "unlock protective stop" not in emulator.state()["dashboard"]  # never self-cleared
        assert emulator.dashboard("unlock protective stop") == "Protective stop releasing"
        assert wait_for(lambda: not arm.state().protective_stop)
        arm.command_velocity(np.array([0.0, 0.01, 0.0, 0.0]))
        assert wait_for(lambda: arm.state().twist[1] > 0.005)
        arm.stop()


def test_ur_arm_conforms(emulator: URControllerProcess, plugins: Plugins, tmp_path: Path) -> None:
    with open_arm(plugins, tmp_path, emulator.host) as arm:
        check_component(arm, advance=time.sleep)


def test_unreachable_controller_gives_a_clear_error(plugins: Plugins, tmp_path: Path) -> None:
    with (
        pytest.raises(HardwareError, match=r"UR controller at 127\.0\.0\.3 does not answer"),
        open_arm(plugins, tmp_path, "127.0.0.3", connect_timeout_s=3.0),
    ):
        pass


def test_silent_controller_does_not_hang_the_connection(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    emulator.silent(True)  # accepts connections, streams nothing: ur_rtde would wait forever
    started = time.monotonic()
    with (
        pytest.raises(HardwareError, match=r"does not answer or stream RTDE data within 0\.5 s"),
        open_arm(plugins, tmp_path, emulator.host, connect_timeout_s=0.5),
    ):
        pass
    assert time.monotonic() - started < 1.5


def test_watchdog_cannot_be_turned_off() -> None:
    with pytest.raises(ValueError, match="greater than 0"):
        ur_arm.URArm.Config(watchdog_min_hz=0.0)


def test_stop_after_a_stale_read_still_stops_the_arm(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    # one stale read marks the arm disconnected while the link still works
    with open_arm(plugins, tmp_path, emulator.host, watchdog_min_hz=0.2) as arm:
        arm.command_velocity(np.array([0.02, 0.0, 0.0, 0.0]))
        assert wait_for(lambda: emulator.state()["speed"][0] > 0.015)
        emulator.silent(True)
        with pytest.raises(HardwareError, match="no new RTDE data"):
            assert wait_for(lambda: arm.state() is None)
        emulator.silent(False)
        assert not arm.connected
        arm.stop()  # before the controller's watchdog (5 s) would stop the arm
        assert wait_for(lambda: emulator.state()["speed"][0] == 0.0, timeout_s=0.5)


@pytest.mark.parametrize(
    ("bits", "condition"),
    [
        (1 | 1 << 4, "a safeguard stop"),
        (1 | 1 << 6, "a robot emergency stop"),
        (1 | 1 << 8, "a safety violation"),
        (1 | 1 << 9, "a safety fault"),
        (1 | 1 << 10, "a stop due to safety"),
        (1 << 3, "neither normal nor reduced safety mode"),  # recovery mode
        (0, "neither normal nor reduced safety mode"),
    ],
)
def test_safety_conditions_are_named(bits: int, condition: str) -> None:
    assert ur_arm.safety_condition(bits) == condition
    assert ur_arm.safety_condition(1) is None and ur_arm.safety_condition(2) is None


def test_safety_stops_refuse_motion(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    with open_arm(plugins, tmp_path, emulator.host) as arm:
        for bits, condition in ((1 | 1 << 4, "safeguard stop"), (1 | 1 << 10, "due to safety")):
            emulator.set_safety_bits(bits)
            wait_for(lambda: arm._safety_bits() == bits)  # noqa: B023 (waited for here)
            assert arm.state().protective_stop  # any stop that refuses motion
            with pytest.raises(SafetyError, match=f"{condition}: motion refused"):
                arm.command_velocity(np.array([0.02, 0.0, 0.0, 0.0]))
            with pytest.raises(SafetyError, match=condition):
                arm.move_to(np.array([0.0, 0.46, 0.15, 0.0]))
        assert 10 not in emulator.state()["commands"] and 3 not in emulator.state()["commands"]


def test_stop_halts_a_move(emulator: URControllerProcess, plugins: Plugins, tmp_path: Path) -> None:
    errors: list[Exception] = []
    with open_arm(plugins, tmp_path, emulator.host, move_timeout_margin_s=0.2) as arm:

        def move() -> None:
            try:
                arm.move_to(np.array([0.02, 0.45, 0.15, 0.0]))  # 0.8 s at 25 mm/s
            except HardwareError as exc:
                errors.append(exc)

        mover = threading.Thread(target=move)
        try:
            mover.start()
            assert wait_for(lambda: emulator.state()["pose"][0] > 0.003)
            arm.stop()
            assert wait_for(lambda: emulator.state()["speed"][0] == 0.0, timeout_s=0.3)
            stopped_x = emulator.state()["pose"][0]
            time.sleep(0.2)
            assert emulator.state()["pose"][0] == stopped_x < 0.015
            mover.join(3.0)
            assert errors and "did not reach" in str(errors[0])
        finally:
            mover.join(3.0)


def test_the_arm_brakes_before_the_workspace_wall(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    x_max_m = 0.10
    peak_x_m = -1.0
    # The clip assumes the next command within lookahead_s; under the whole suite's load this
    # loop's 67 ms ticks came up to 0.1 s late (1.6 mm past the wall with the default 0.1 s),
    # so the reaction time allowed here is 0.3 s.
    with open_arm(
        plugins, tmp_path, emulator.host, max_speed_mps=0.25,
        workspace_max_m=[x_max_m, 0.85, 0.5], lookahead_s=0.3,
    ) as arm:  # fmt: skip
        try:
            started = time.monotonic()
            while time.monotonic() - started < 1.5:  # a 15 Hz control loop at full speed to +x
                with contextlib.suppress(SafetyError):  # at the wall
                    arm.command_velocity(np.array([0.25, 0.0, 0.0, 0.0]))
                next_s = time.monotonic() + 1 / 15
                while time.monotonic() < next_s:
                    peak_x_m = max(peak_x_m, emulator.state()["pose"][0])
                    time.sleep(0.005)
            # Without the braking clip the TCP ran 8.9 mm past the wall; with it, 0.1 mm on
            # an idle machine and 0.34 mm once under the whole suite's load (late loop ticks).
            assert x_max_m - 0.01 < peak_x_m < x_max_m + 1e-3
        finally:
            arm.stop()


def test_data_that_stopped_during_an_idle_gap_is_stale(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    with open_arm(plugins, tmp_path, emulator.host) as arm:
        arm.state()
        time.sleep(0.5)  # idle: nobody polls while the data still flows
        emulator.silent(True)
        time.sleep(0.5)
        with pytest.raises(HardwareError, match=r"no new RTDE data for [45]\d\d ms"):
            arm.state()
        emulator.silent(False)
        arm.reconnect()
        assert time.monotonic() - arm.state().timestamp_s < 0.05


def test_move_to_returns_once_the_yaw_is_reached(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    with open_arm(plugins, tmp_path, emulator.host) as arm:
        arm.move_to(np.array([0.0, 0.45, 0.15, 0.5]))  # a turn in place, 0.5 s
        assert arm.state().pose[3] == pytest.approx(0.5, abs=2e-3)


def test_a_turn_longer_than_the_margin_is_not_stopped(
    emulator: URControllerProcess, plugins: Plugins, tmp_path: Path
) -> None:
    """The controller chooses how fast moveL turns; a move is stopped only when it stalls."""
    with open_arm(plugins, tmp_path, emulator.host, move_timeout_margin_s=0.4) as arm:
        arm.move_to(np.array([0.0, 0.45, 0.15, 1.2]))  # a turn in place, 1.2 s
        assert arm.state().pose[3] == pytest.approx(1.2, abs=2e-3)
