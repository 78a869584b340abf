"""ament_python build description of t42_transfer (also usable with plain pip).

Runtime dependencies are NOT listed in install_requires: rosdep resolves the
ROS ones from package.xml and pip installs the rest from the exact pins in
requirements.txt (torch must stay at the local CPU build 2.13.0).
"""

import ast
import os
from glob import glob

from setuptools import find_packages, setup

package_name = "t42_transfer"


def _files(pattern: str) -> list[str]:
    return sorted(glob(pattern))


def _node_names() -> list[str]:
    """Keys of NODES in t42_transfer/nodes/registry.py, parsed (not imported: the build needs no dependencies)."""
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "t42_transfer", "nodes", "registry.py")
    with open(path) as f:
        tree = ast.parse(f.read())
    for stmt in tree.body:
        if isinstance(stmt, ast.AnnAssign) and getattr(stmt.target, "id", None) == "NODES":
            return [key.value for key in stmt.value.keys]
    raise RuntimeError(f"no NODES dict in {path}")


data_files = [
    ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
    ("share/" + package_name, ["package.xml"]),
]
for directory, patterns in (
    ("share/" + package_name + "/launch", ["launch/*.py"]),
    # The node suite's params files (the launch file's params_file) and the Foxglove layout; the experiment
    # configs stay in the repository.
    ("share/" + package_name + "/config", ["configs/suite*.yaml", "configs/hardware_*.yaml",
                                           "configs/foxglove_layout.json"]),
):
    found = [f for pattern in patterns for f in _files(pattern)]
    if found:
        data_files.append((directory, found))

setup(
    name=package_name,
    version="0.1.0",
    description="Transfer of learned dynamics models between Yale Model-T42 hands.",
    license="Apache-2.0",
    maintainer="t42_transfer maintainers",
    maintainer_email="maintainer@example.com",
    python_requires=">=3.10",
    packages=find_packages(exclude=["test", "test.*", "bench", "bench.*", "scripts"]),
    data_files=data_files,
    install_requires=["setuptools"],
    entry_points={
        "console_scripts": [
            "t42 = t42_transfer.cli:main",
            # One executable per node (`ros2 run t42_transfer <node>`), named as the registry names it.
            *(f"{name} = t42_transfer.ros.runner:main" for name in _node_names()),
        ],
    },
)
