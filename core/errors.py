"""Exceptions with messages meant for users, and the exit code each maps to."""

from __future__ import annotations

from dataclasses import dataclass


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
