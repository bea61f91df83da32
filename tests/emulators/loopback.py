"""Loopback addresses for emulators: each gets its own 127.0.0.N so fixed ports never collide."""

from __future__ import annotations

import itertools
import os

_COUNTER = itertools.count(20 + (os.getpid() % 100))


def next_loopback() -> str:
    """A fresh address in 127.0.0.20-254 (Linux routes all of 127/8 to the loopback device)."""
    return f"127.0.0.{20 + (next(_COUNTER) - 20) % 230}"
