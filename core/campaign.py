"""Evaluation campaigns: many ``vistac run`` calls of one skill, each into its own folder,
reused when the same call already finished there (``vistac eval`` of touch and goal skills)."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from vistac.errors import ConfigError
from vistac.skill import apply_overrides, read_yaml

log = logging.getLogger(__name__)

STAMP = "eval_args.json"
"""What a finished run in a run folder was asked for (its arguments) and the code that ran it,
written when it ends."""
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


@functools.cache
def code_fingerprint() -> str:
    """SHA-256 of vistac's Python sources (the core and the built-in plugins): a run made by
    other code is not reused."""
    import vistac
    import vistac.plugins

    digest = hashlib.sha256()
    for package in (vistac, vistac.plugins):
        root = Path(package.__file__).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def named_files_digest(skill: Path, overrides: Sequence[str]) -> str:
    """SHA-256 of the skill file and of every file a value of the skill, with ``overrides``
    applied, names (checkpoints, objects, priors; a relative path from the skill's folder, as
    the skill takes it), and of the ``NAME.json`` beside each (where a checkpoint keeps its
    architecture): a run whose checkpoint was retrained in place is not reused. A skill that
    cannot be read counts as its bytes alone (its run fails anyway)."""
    try:
        data = apply_overrides(read_yaml(skill) or {}, list(overrides))
    except ConfigError:
        data = {}
    named = {path.resolve() for path in _named_files(data, skill.parent)}
    beside = {path.with_name(path.name + ".json") for path in named}
    files = {skill.resolve()} | named | {path for path in beside if path.is_file()}
    digest = hashlib.sha256()
    for path in sorted(files):
        digest.update(str(path).encode())
        with contextlib.suppress(OSError):
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _named_files(value: Any, base: Path) -> Iterator[Path]:
    """Every existing file a string in ``value`` (nested mappings and lists) names."""
    if isinstance(value, dict):
        for item in value.values():
            yield from _named_files(item, base)
    elif isinstance(value, list):
        for item in value:
            yield from _named_files(item, base)
    elif isinstance(value, str) and 0 < len(value) < 4096:
        with contextlib.suppress(OSError, ValueError):  # not a path the system takes
            if (base / value).is_file():
                yield base / value


def args_digest(args: Sequence[str]) -> str:
    """:func:`named_files_digest` of the skill and ``--set`` overrides of ``vistac ARGS``
    (a ``run``)."""
    skill = Path(args[list(args).index("run") + 1])
    overrides = [args[i + 1] for i, arg in enumerate(args[:-1]) if arg == "--set"]
    return named_files_digest(skill, overrides)


def stamp_of(run_dir: Path) -> Any:
    """The stamp of the finished run in ``run_dir`` (what it was asked for), or None when
    there is none (never run, running, failed where failures are not stamped, or run by
    other code than this)."""
    stamp = run_dir / STAMP
    if not (stamp.is_file() and (run_dir / "summary.json").is_file()):
        return None
    try:
        stamped = json.loads(stamp.read_text(encoding="utf-8"))
    except json.JSONDecodeError:
        log.warning("%s is not a stamp this code wrote: running %s again", stamp, run_dir)
        return None
    if not isinstance(stamped, dict) or stamped.get("code") != code_fingerprint():
        return None
    return stamped.get("value")


def set_stamp(run_dir: Path, value: Any) -> None:
    """Stamp ``run_dir``'s run as finished with ``value`` by this code, or, with None, remove
    the stamp before the folder's run is replaced (so that a run failing there is never reused
    as the one stamped before)."""
    stamp = run_dir / STAMP
    if value is None:
        stamp.unlink(missing_ok=True)
    else:
        stamp.write_text(json.dumps({"value": value, "code": code_fingerprint()}), "utf-8")


def run_once(args: list[str], run_dir: Path, who: str) -> tuple[int, dict[str, Any] | None]:
    """``vistac ARGS`` (a ``run`` writing to ``run_dir``) unless a finished run with the same
    arguments is there: (its exit code, its summary or None when it wrote none).

    ConfigError when the skill with these arguments is not valid: every other run of the
    campaign would fail the same way. KeyboardInterrupt when the run was interrupted."""
    summary_path = run_dir / "summary.json"
    asked = {"args": args, "inputs": args_digest(args)}
    finished = stamp_of(run_dir)
    if isinstance(finished, dict) and {key: finished.get(key) for key in asked} == asked:
        return int(finished["exit_code"]), json.loads(summary_path.read_text("utf-8"))
    set_stamp(run_dir, None)
    summary_path.unlink(missing_ok=True)  # a run that fails before it starts writes none
    code, printed = run_quietly(args)
    log.debug("%s", printed)
    if code == ConfigError.exit_code:
        raise ConfigError(f"{who}: the skill with {' '.join(args[2:])} is not valid (message "
                          "above); fix the skill or the --set options")  # fmt: skip
    if not summary_path.is_file():
        return code, None
    set_stamp(run_dir, asked | {"exit_code": code})
    return code, json.loads(summary_path.read_text(encoding="utf-8"))
