"""Exceptions with messages meant for users, and the exit code each maps to."""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Any, get_args

from pydantic import BaseModel, ValidationError


class VistacError(Exception):
    """Base class: a problem the user can fix; the CLI prints the message, no traceback."""

    exit_code = 1


@dataclass(frozen=True)
class ConfigIssue:
    """One problem in a skill or object file, located by its dotted YAML path."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message


def suggest(name: str, choices: list[str]) -> str:
    """A ``did you mean`` clause for ``name`` among ``choices`` ('' when nothing is close)."""
    close = difflib.get_close_matches(name, choices, n=3, cutoff=0.6)
    if not close:
        return ""
    return " (did you mean " + " or ".join(repr(c) for c in close) + "?)"


def yaml_path(prefix: str, loc: tuple[int | str, ...]) -> str:
    """A pydantic location joined onto a YAML path: ``a.b[0].c``."""
    text = prefix
    for item in loc:
        if isinstance(item, int):
            text += f"[{item}]"
        else:
            text = f"{text}.{item}" if text else str(item)
    return text


def validation_issues(
    prefix: str, error: ValidationError, model: type[BaseModel]
) -> list[ConfigIssue]:
    """The errors of validating ``model``, located by YAML path under ``prefix``; an unknown
    key also names the known keys close to it."""
    issues = []
    for item in error.errors():
        loc = tuple(item["loc"])
        message = item["msg"]
        if item["type"] == "extra_forbidden" and loc:
            message += suggest(str(loc[-1]), _keys_at(model, loc[:-1]))
        issues.append(ConfigIssue(yaml_path(prefix, loc), message))
    return issues


def _keys_at(model: type[BaseModel], loc: tuple[int | str, ...]) -> list[str]:
    """The keys (field names and aliases) of the model at ``loc`` within ``model``."""
    current: type[BaseModel] | None = model
    for part in (part for part in loc if isinstance(part, str)):
        fields = current.model_fields.items() if current is not None else []
        field = next((f for name, f in fields if part in (name, f.alias)), None)
        current = _model_in(field.annotation) if field is not None else None
    if current is None:
        return []
    return [f.alias or name for name, f in current.model_fields.items()]


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The first pydantic model in a type annotation (``list[X]``, ``X | None``, ...)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


class ConfigError(VistacError):
    """A skill, object or command-line configuration is invalid (exit code 2)."""

    exit_code = 2

    def __init__(self, issues: list[ConfigIssue] | str, source: str = "") -> None:
        """``issues``: the problems found, or one message."""
        if isinstance(issues, str):
            issues = [ConfigIssue("", issues)]
        self.issues = issues
        self.source = source
        prefix = f"{source}: " if source else ""
        super().__init__("\n".join(f"{prefix}{issue}" for issue in issues))


class PluginError(VistacError):
    """A plugin or component could not be found or loaded."""

    exit_code = 2


class DataError(VistacError):
    """Sensor data or a data file is malformed (wrong shape, NaN, empty)."""


class SafetyError(VistacError):
    """A safety check failed: the arm has been stopped."""


class HardwareError(VistacError):
    """A device is disconnected, faulted, or did not answer in time."""
