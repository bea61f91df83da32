"""The explicit package list in pyproject.toml must cover every package folder."""

from __future__ import annotations

import tomllib
from importlib.metadata import entry_points

from conftest import ROOT


def _package_folders() -> set[str]:
    found = set()
    for top, name in (("core", "vistac"), ("plugins", "vistac.plugins")):
        for init in (ROOT / top).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / top)
            found.add(".".join([name, *rel.parts]))
    return found


def test_every_package_folder_is_listed() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    listed = set(config["tool"]["setuptools"]["packages"])
    missing = _package_folders() - listed
    assert not missing, (
        f"add these to [tool.setuptools] packages in pyproject.toml: {sorted(missing)}"
    )


def test_builtin_plugins_use_the_public_entry_point_group() -> None:
    names = {ep.name for ep in entry_points(group="vistac") if ep.dist and ep.dist.name == "vistac"}
    assert {"core", "sim", "actions", "shape"} <= names
