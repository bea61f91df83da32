"""Evaluation campaigns: many ``vistac run`` calls of one skill, each into its own folder,
reused when the same call already finished there (``vistac eval`` of touch and goal skills)."""

from __future__ import annotations

import contextlib
import io
import json
import logging
from pathlib import Path
from typing import Any

from vistac.errors import ConfigError

log = logging.getLogger(__name__)

_STAMP = "eval_args.json"
"""The arguments and exit code of the finished run in a run folder."""
INTERRUPTED_EXIT_CODE = 130
"""What a run stopped by Ctrl-C exits with (the Scheduler turns the interrupt into it)."""


def run_quietly(args: list[str]) -> tuple[int, str]:
    """``vistac ARGS`` in this process: (its exit code, what it printed).

    KeyboardInterrupt when the run was interrupted (exit 130): Ctrl-C stops the whole
    campaign, not just its current run."""
    from vistac.cli import main

    level = logging.getLogger("vistac").level
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            code = main(args)
    finally:  # the nested CLI call sets the package's log level to -q
        logging.getLogger("vistac").setLevel(level)
    if code == INTERRUPTED_EXIT_CODE:
        raise KeyboardInterrupt
    return code, printed.getvalue()


def run_once(args: list[str], run_dir: Path, who: str) -> tuple[int, dict[str, Any] | None]:
    """``vistac ARGS`` (a ``run`` writing to ``run_dir``) unless a finished run with the same
    arguments is there: (its exit code, its summary or None when it wrote none).

    ConfigError when the skill with these arguments is not valid: every other run of the
    campaign would fail the same way. KeyboardInterrupt when the run was interrupted."""
    stamp, summary_path = run_dir / _STAMP, run_dir / "summary.json"
    if stamp.is_file() and summary_path.is_file():
        finished = json.loads(stamp.read_text(encoding="utf-8"))
        if isinstance(finished, dict) and finished.get("args") == args:
            return int(finished["exit_code"]), json.loads(summary_path.read_text("utf-8"))
    stamp.unlink(missing_ok=True)  # this folder's run is about to be replaced
    code, printed = run_quietly(args)
    log.debug("%s", printed)
    if code == ConfigError.exit_code:
        raise ConfigError(f"{who}: the skill with {' '.join(args[2:])} is not valid (message "
                          "above); fix the skill or the --set options")  # fmt: skip
    if not summary_path.is_file():
        return code, None
    stamp.write_text(json.dumps({"args": args, "exit_code": code}), encoding="utf-8")
    return code, json.loads(summary_path.read_text(encoding="utf-8"))
