"""A serial device on a pseudo-terminal: ``path`` is what the plugin opens; a daemon thread
runs the subclass's ``_run`` between ``__enter__`` and ``__exit__``."""

from __future__ import annotations

import contextlib
import os
import threading
import tty
from typing import Self


class PtyDevice:
    def __init__(self) -> None:
        self.silent = False
        self.master, self._slave_fd = os.openpty()
        self.path = os.ttyname(self._slave_fd)
        tty.setraw(self._slave_fd)  # no echo or line editing before the plugin opens it
        os.set_blocking(self.master, False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
        for fd in (self.master, self._slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
