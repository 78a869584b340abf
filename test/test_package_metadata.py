"""package.xml, setup.py and the package agree; entry points resolve; pins hold."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import EntryPoint, PackageNotFoundError, version
from pathlib import Path

import pytest

import t42_transfer

REPO = Path(__file__).resolve().parents[1]

LAUNCH_DEPS = {"launch", "launch_ros", "ament_index_python"}
ROS_MESSAGE_PACKAGES = {
    "rcl_interfaces", "builtin_interfaces", "std_msgs", "std_srvs", "geometry_msgs", "sensor_msgs",
    "trajectory_msgs", "nav_msgs", "diagnostic_msgs", "rosgraph_msgs", "action_msgs", "lifecycle_msgs",
    "visualization_msgs", "shape_msgs", "stereo_msgs", "actionlib_msgs", "unique_identifier_msgs", "t42_interfaces",
}
"""ROS interface packages the code could name (an import or a ``pkg/msg/Name`` type string)."""
ROSDEP_PYTHON_DEPS = {"python3-numpy", "python3-yaml", "python3-matplotlib", "python3-tqdm"}

# What setup() was called with, read without installing anything.
_SETUP_PROBE = r"""
import json, sys
import setuptools  # makes `distutils` the setuptools copy that setup() uses
from distutils.core import run_setup
dist = run_setup("setup.py", stop_after="init")
eps = dist.entry_points or {}
json.dump({
    "name": dist.get_name(),
    "version": dist.get_version(),
    "console_scripts": list(eps.get("console_scripts", [])),
    "packages": list(dist.packages or []),
    "data_files": [[d, list(f)] for d, f in (dist.data_files or [])],
}, sys.stdout)
"""


@pytest.fixture(scope="module")
def package_xml() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


@pytest.fixture(scope="module")
def setup_info() -> dict:
    proc = subprocess.run([sys.executable, "-c", _SETUP_PROBE], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_package_xml_is_format3_ament_python(package_xml):
    assert package_xml.tag == "package"
    assert package_xml.get("format") == "3"
    assert package_xml.findtext("name") == "t42_transfer"
    assert package_xml.findtext("license") == "Apache-2.0"
    assert package_xml.findtext("description").strip()
    assert package_xml.find("maintainer").get("email")
    assert package_xml.findtext("export/build_type") == "ament_python"


def _ros_packages_used() -> set[str]:
    """ROS packages the package's code and launch file import or name by type string."""
    used: set[str] = set()
    files = [*REPO.glob("t42_transfer/**/*.py"), *REPO.glob("msg_adapters/*.py"), *REPO.glob("launch/*.py")]
    for path in files:
        text = path.read_text()
        if re.search(r"^\s*(from|import) rclpy\b", text, re.M):
            used.add("rclpy")
        for pkg in re.findall(r"^\s*(?:from|import) ([a-z][a-z0-9_]*)(?:\.(?:msg|srv|action)|\b)", text, re.M):
            if pkg in ROS_MESSAGE_PACKAGES | LAUNCH_DEPS:
                used.add(pkg)
        for pkg in re.findall(r"[\"']([a-z][a-z0-9_]*)/(?:msg|srv|action)/[A-Z]\w*[\"']", text):
            used.add(pkg)
    return used


def test_package_xml_names_the_ros_packages_the_code_uses_and_no_others(package_xml):
    exec_deps = {e.text.strip() for e in package_xml.iter("exec_depend")}
    exec_deps |= {e.text.strip() for e in package_xml.iter("depend")}
    ros_deps = {d for d in exec_deps if not d.startswith("python3-")}
    used = _ros_packages_used()
    assert {"rclpy", "sensor_msgs", "std_srvs", "launch_ros"} <= used  # the scan finds things
    assert ros_deps == used, f"package.xml lacks {sorted(used - ros_deps)}, names unused {sorted(ros_deps - used)}"
    assert ROSDEP_PYTHON_DEPS <= exec_deps
    assert "python3-pytest" in {e.text.strip() for e in package_xml.iter("test_depend")}


def test_no_home_made_transport_left():
    sources = [*REPO.glob("t42_transfer/**/*.py"), *REPO.glob("msg_adapters/*.py"), *REPO.glob("test/*.py"),
               *REPO.glob("bench/*.py"), REPO / "requirements.txt", REPO / "package.xml"]
    offenders = [str(p.relative_to(REPO)) for p in sources
                 if p != Path(__file__) and re.search(r"cyclonedds|CycloneTransport|InProcessBus", p.read_text())]
    assert not offenders


def test_versions_agree(package_xml, setup_info):
    xml_version = package_xml.findtext("version")
    assert re.fullmatch(r"\d+\.\d+\.\d+", xml_version)
    assert setup_info["name"] == package_xml.findtext("name")
    assert setup_info["version"] == xml_version
    assert t42_transfer.__version__ == xml_version


def test_setup_ships_packages_and_ament_files(setup_info):
    packages = setup_info["packages"]
    assert "t42_transfer" in packages
    assert not any(p == "test" or p.startswith("test.") for p in packages)
    if (REPO / "msg_adapters" / "__init__.py").is_file():
        assert "msg_adapters" in packages
    data = {d: set(f) for d, f in setup_info["data_files"]}
    assert "resource/t42_transfer" in data["share/ament_index/resource_index/packages"]
    assert (REPO / "resource" / "t42_transfer").is_file()
    assert "package.xml" in data["share/t42_transfer"]


def test_setup_cfg_gives_ros2_run_layout():
    text = (REPO / "setup.cfg").read_text()
    assert re.search(r"^\[develop\]\s*\nscript_dir\s*=\s*\$base/lib/t42_transfer\s*$", text, re.M)
    assert re.search(r"^\[install\]\s*\ninstall_scripts\s*=\s*\$base/lib/t42_transfer\s*$",
                     text, re.M)


def test_console_scripts_resolve_to_callables(setup_info):
    scripts = setup_info["console_scripts"]
    assert any(s.split("=", 1)[0].strip() == "t42" for s in scripts)
    names = set()
    for spec in scripts:
        name, value = (part.strip() for part in spec.split("=", 1))
        assert name not in names, f"duplicate console script {name}"
        names.add(name)
        target = EntryPoint(name=name, value=value, group="console_scripts").load()
        assert callable(target), f"{spec} does not resolve to a callable"


def test_t42_main_help_and_version(capsys):
    from t42_transfer.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert t42_transfer.__version__ in capsys.readouterr().out


def _pins(path: Path) -> dict[str, str]:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        m = re.fullmatch(r"([A-Za-z0-9_.\-]+)(?:\[[a-z0-9_,\-]+\])?==([A-Za-z0-9_.+\-]+)", line)
        assert m, f"{path.name}: not an exact pin: {line!r}"
        pins[m.group(1)] = m.group(2)
    return pins


def test_requirements_are_exact_pins_matching_the_environment():
    pins = _pins(REPO / "requirements.txt")
    assert pins.get("torch") == "2.13.0"
    for name in ("numpy", "mujoco", "rosbags", "mcap", "tqdm", "PyYAML", "matplotlib", "ros-jazzy-rclpy",
                 "ros-jazzy-common-interfaces", "ros-jazzy-rosgraph-msgs", "opencv-python-headless"):
        assert name in pins, f"requirements.txt lacks a pin for {name}"
    pins_test = _pins(REPO / "requirements-test.txt")
    for name in ("pytest", "hypothesis", "colcon-common-extensions"):
        assert name in pins_test, f"requirements-test.txt lacks a pin for {name}"
    for name, pinned in {**pins, **pins_test}.items():
        try:
            installed = version(name)
        except PackageNotFoundError:
            pytest.fail(f"{name} is pinned but not installed (run scripts/bootstrap.sh)")
        # A local build label (torch 2.13.0+cpu) satisfies the plain pin.
        assert installed.split("+", 1)[0] == pinned, f"{name}: {installed} != pin {pinned}"
