"""Registry, plugin discovery, broken plugins and the autoload switch."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from conftest import run_vistac, write
from vistac.errors import PluginError
from vistac.pluginmanager import load_plugins
from vistac.registry import Registry, suggest


def test_unknown_name_gets_a_suggestion() -> None:
    registry = Registry()
    registry.add("arm", "sim.arm", "vistac.plugins.hardware.sim.arm:SimArm")
    with pytest.raises(PluginError, match=r"did you mean 'sim\.arm'"):
        registry.info("sim.armm")
    assert suggest("zzz", ["sim.arm"]) == ""


def test_bad_registrations_are_refused() -> None:
    registry = Registry()
    with pytest.raises(PluginError, match="unknown component kind 'armm'"):
        registry.add("armm", "x", "a:B")
    with pytest.raises(PluginError, match="module:Class"):
        registry.add("arm", "x", "no_colon")
    registry.add("arm", "x", "a:B")
    with pytest.raises(PluginError, match="registered twice"):
        registry.add("arm", "x", "a:C")


def test_load_is_lazy_and_checks_the_class() -> None:
    registry = Registry()
    registry.add("arm", "missing", "vistac.no_such_module:Arm")
    registry.add("arm", "notcfg", "vistac.registry:Registry")
    assert registry.names("arm") == ["missing", "notcfg"]
    with pytest.raises(PluginError, match=r"cannot import 'vistac\.no_such_module'"):
        registry.load("missing")
    with pytest.raises(PluginError, match="no pydantic 'Config'"):
        registry.load("notcfg")


def test_builtin_plugins_register_every_builtin_component() -> None:
    plugins = load_plugins()
    assert {"core", "sim", "actions", "shape"} <= set(plugins.loaded)
    assert "sim.mujoco" in plugins.registry.names("world")
    assert "look" in plugins.registry.names("behaviour")


def _broken_module(tmp_path: Path, body: str, name: str) -> str:
    write(tmp_path / f"{name}.py", body)
    sys.path.insert(0, str(tmp_path))
    return name


def test_broken_plugin_is_reported_and_skipped(tmp_path: Path) -> None:
    bad_import = _broken_module(tmp_path, "raise ImportError('needs libfoo')\n", "vt_bad_import")
    bad_register = _broken_module(
        tmp_path,
        "from vistac import hookimpl\n@hookimpl\ndef vistac_register(registry):\n"
        "    registry.add('arm', 'vt.arm', 'x:Y')\n"  # added before the failure: withdrawn
        "    registry.add('arm', 'sim.arm', 'x:Y')\n",  # clashes with the built-in name
        "vt_bad_register",
    )
    try:
        plugins = load_plugins([bad_import, bad_register])
    finally:
        sys.path.remove(str(tmp_path))
    failed = {f.name: f.error for f in plugins.failures}
    assert "needs libfoo" in failed[bad_import]
    assert "registered twice" in failed[bad_register]
    assert plugins.registry.info("sim.arm").plugin == "sim"  # the good ones still work
    assert "vt.arm" not in plugins.registry.names()


def _fake_distribution(site: Path, entry: str) -> None:
    dist = site / "vt_thirdparty-1.0.dist-info"
    write(dist / "METADATA", "Metadata-Version: 2.1\nName: vt-thirdparty\nVersion: 1.0\n")
    write(dist / "entry_points.txt", f"[vistac]\nthirdparty = {entry}\n")
    write(
        site / "vt_thirdparty.py",
        "from vistac import hookimpl\n@hookimpl\ndef vistac_register(registry):\n"
        "    registry.add('action_selector', 'third.pick',\n"
        "                 'vistac.plugins.actions.selectors:RandomSelector')\n",
    )


def test_entry_point_autoload_and_disable_switch(tmp_path: Path) -> None:
    _fake_distribution(tmp_path, "vt_thirdparty")
    env = {"PYTHONPATH": str(tmp_path), "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"}
    assert "third.pick" in run_vistac("plugins", env=env).stdout
    sealed = {**env, "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "1"}
    assert "third.pick" not in run_vistac("plugins", env=sealed).stdout
    assert "third.pick" in run_vistac("-p", "thirdparty", "plugins", env=sealed).stdout


def test_broken_entry_point_does_not_break_the_cli(tmp_path: Path) -> None:
    _fake_distribution(tmp_path, "vt_missing_module")
    result = run_vistac(
        "plugins", env={"PYTHONPATH": str(tmp_path), "VISTAC_DISABLE_PLUGIN_AUTOLOAD": "0"}
    )
    assert result.returncode == 0
    assert "failed:  thirdparty" in result.stdout
    assert "sim.mujoco" in result.stdout


def test_listing_plugins_imports_no_heavy_library() -> None:
    result = run_vistac("plugins", "--json")
    import json

    listed = json.loads(result.stdout)
    assert any(c["name"] == "sim.mujoco" for c in listed["components"])
    heavy = ("torch", "open3d", "mujoco", "rtde_control", "rtde_receive", "cv2")
    probe = run_vistac_importtime()
    imported = {
        line.split("|")[-1].strip().split(".")[0] for line in probe.splitlines() if "|" in line
    }
    assert not imported & set(heavy), f"vistac plugins imported {imported & set(heavy)}"


def run_vistac_importtime() -> str:
    import subprocess

    from conftest import ROOT

    result = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "vistac.cli", "plugins"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stderr
