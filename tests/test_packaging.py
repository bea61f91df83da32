"""Packaging: the explicit package list in pyproject.toml covers every package folder, and
constraints.txt pins every dependency within pyproject.toml's ranges."""

from __future__ import annotations

import tomllib
from importlib.metadata import entry_points

from conftest import ROOT
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name


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


def _pins() -> dict[str, str]:
    """constraints.txt as {canonical name: pinned version}."""
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pins[canonicalize_name(name)] = version.strip()
    return pins


def test_constraints_pin_every_dependency_within_its_range() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = [Requirement(text) for text in config["dependencies"]]
    requirements += [Requirement(text) for text in config["optional-dependencies"]["dev"]]
    pins = _pins()
    for requirement in requirements:
        name = canonicalize_name(requirement.name)
        if name == "torch":  # installed first from its own pin (Makefile)
            continue
        assert name in pins, f"constraints.txt pins no {name}: run make lock"
        assert requirement.specifier.contains(pins[name]), (
            f"constraints.txt pins {name}=={pins[name]}, outside pyproject.toml's "
            f"{requirement}: run make lock after installing a version within it"
        )
