"""Run a possibly blocking device call with a deadline.

Device libraries can block for minutes (``moveL`` on a dropped connection, a read on a silent
serial port). The call runs in a daemon thread; when it has not returned by the deadline the
caller gets ``HardwareError`` at once and the thread is abandoned (the device is then treated
as disconnected by the caller). ``ur_rtde`` releases the GIL inside its calls, so the waiting
thread keeps running.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, TypeVar

from vistac.errors import HardwareError, VistacError

T = TypeVar("T")


class DeadlineExceededError(HardwareError):
    """A device call did not return in time (the device is presumed lost)."""


def call_with_deadline(call: Callable[[], T], timeout_s: float, what: str) -> T:
    """Return ``call()`` or raise ``DeadlineExceededError`` after ``timeout_s``.

    An exception raised by ``call`` is re-raised as ``HardwareError`` naming ``what`` (a
    ``VistacError`` is re-raised unchanged).
    """
    outcome: dict[str, Any] = {}
    finished = threading.Event()

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as exc:  # handed to the caller
            outcome["error"] = exc
        finally:
            finished.set()

    threading.Thread(target=run, name=f"deadline:{what}", daemon=True).start()
    if not finished.wait(timeout_s):
        raise DeadlineExceededError(f"{what} did not return within {timeout_s * 1e3:.0f} ms")
    error = outcome.get("error")
    if isinstance(error, VistacError):
        raise error
    if error is not None:
        raise HardwareError(f"{what} failed: {error}") from error
    value: T = outcome["value"]
    return value
