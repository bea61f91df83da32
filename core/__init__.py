"""vistac: a plugin-based robot skill framework for interactive visuo-tactile perception.

Third-party plugins use ``from vistac import hookimpl`` and the types and protocols below.
"""

from __future__ import annotations

import pluggy

__version__ = "0.1.0"

hookimpl = pluggy.HookimplMarker("vistac")
"""Marker for hook implementations in plugin modules."""

__all__ = ["__version__", "hookimpl"]
