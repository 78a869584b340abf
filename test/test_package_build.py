"""`colcon build` of this package, the way a ROS 2 workspace builds it.

colcon-common-extensions from PyPI builds an ament_python package without a
ROS install.  The build goes to a temporary directory outside the repository
and must leave no build/, install/, log/ or *.egg-info behind in it.
(Takes a few seconds, so it is part of the fast suite.)
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import t42_transfer

REPO = Path(__file__).resolve().parents[1]
PKG = "t42_transfer"
SKIP_DIRS = {".venv", ".git", "__pycache__", ".pytest_cache", ".hypothesis", "node_modules"}


def _build_artefacts(root: Path) -> set[str]:
    """Build outputs in the tree: top-level build/ install/ log/, any *.egg-info."""
    found = {name for name in ("build", "install", "log") if (root / name).exists()}
    for dirpath, dirnames, _ in os.walk(root):
        dirnames[:] = [d for d in dirnames if d not in SKIP_DIRS]
        for d in dirnames:
            if d.endswith(".egg-info"):
                found.add(str(Path(dirpath, d).relative_to(root)))
    return found


def _colcon() -> list[str]:
    exe = Path(sys.executable).parent / "colcon"
    if exe.is_file() and os.access(exe, os.X_OK):
        return [str(exe)]
    colcon = shutil.which("colcon")
    if colcon:
        return [colcon]
    return [sys.executable, "-m", "colcon"]


def _clean_env(tmp: Path) -> dict[str, str]:
    env = dict(os.environ)
    # No user colcon defaults, no sourced workspaces leaking into the build.
    for key in ("COLCON_PREFIX_PATH", "AMENT_PREFIX_PATH", "COLCON_LOG_PATH", "PYTHONPATH"):
        env.pop(key, None)
    env["COLCON_HOME"] = str(tmp / "colcon_home")
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def _source_and_run(install: Path, env: dict[str, str], cwd: Path, *cmd: str):
    """Run cmd in a shell that has sourced install/local_setup.bash."""
    script = 'source "$1/local_setup.bash" && shift && exec "$@"'
    return subprocess.run(
        ["bash", "-c", script, "bash", str(install), *cmd],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=120,
    )


@pytest.fixture(scope="module")
def colcon_build(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("colcon_ws")
    assert REPO not in tmp.parents, "the build must happen outside the repository"
    env = _clean_env(tmp)
    before = _build_artefacts(REPO)
    cmd = [
        *_colcon(),
        "--log-base", str(tmp / "log"),
        "build",
        "--paths", str(REPO),
        "--build-base", str(tmp / "build"),
        "--install-base", str(tmp / "install"),
        "--event-handlers", "console_direct+", "desktop_notification-", "status-",
        "terminal_title-",
    ]
    proc = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, timeout=600)
    after = _build_artefacts(REPO)
    return {"tmp": tmp, "env": env, "proc": proc, "before": before, "after": after,
            "install": tmp / "install"}


def test_colcon_build_succeeds(colcon_build):
    proc = colcon_build["proc"]
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout}\n{proc.stderr}"
    assert "Summary: 1 package finished" in proc.stdout + proc.stderr


def test_build_leaves_repository_clean(colcon_build):
    new = colcon_build["after"] - colcon_build["before"]
    assert not new, f"colcon build left artefacts in the repository: {sorted(new)}"


def test_ament_index_and_package_xml_installed(colcon_build):
    share = colcon_build["install"] / PKG / "share"
    marker = share / "ament_index" / "resource_index" / "packages" / PKG
    assert marker.is_file()
    installed_xml = share / PKG / "package.xml"
    assert installed_xml.is_file()
    assert installed_xml.read_bytes() == (REPO / "package.xml").read_bytes()
    for launch_file in sorted((REPO / "launch").glob("*.py")):
        assert (share / PKG / "launch" / launch_file.name).is_file()
    for config_file in sorted((REPO / "config").glob("*.yaml")):
        assert (share / PKG / "config" / config_file.name).is_file()


def _site_packages(install: Path) -> Path:
    lib = install / PKG / "lib"
    candidates = sorted(lib.glob("python3*/site-packages"))
    assert len(candidates) == 1, f"expected one site-packages under {lib}: {candidates}"
    return candidates[0]


def test_python_packages_installed(colcon_build):
    site = _site_packages(colcon_build["install"])
    not_shipped = {"test", "bench", "scripts"}  # setup.py's find_packages excludes
    top_level = [p.parent for p in REPO.glob("*/__init__.py") if p.parent.name not in not_shipped]
    assert REPO / PKG in top_level
    for top in top_level:
        for init in top.rglob("__init__.py"):
            rel = init.relative_to(REPO)
            if "__pycache__" in rel.parts:
                continue
            assert (site / rel).is_file(), f"{rel} was not installed"


def test_executables_in_ros2_run_layout(colcon_build):
    install = colcon_build["install"]
    libexec = install / PKG / "lib" / PKG
    t42 = libexec / "t42"
    assert t42.is_file() and os.access(t42, os.X_OK)
    # Every console script (the node executables too) lands where `ros2 run` looks.
    site = _site_packages(install)
    entry_points_txt = next(site.glob(f"{PKG}-*.egg-info/entry_points.txt"))
    names = _console_script_names(entry_points_txt.read_text())
    assert "t42" in names
    for name in names:
        assert (libexec / name).is_file(), f"console script {name} not in lib/{PKG}"


def _console_script_names(text: str) -> list[str]:
    names, section = [], None
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
        elif section == "console_scripts" and "=" in line:
            names.append(line.split("=", 1)[0].strip())
    return names


def test_installed_t42_runs_from_sourced_workspace(colcon_build):
    install, env, tmp = colcon_build["install"], colcon_build["env"], colcon_build["tmp"]
    t42 = install / PKG / "lib" / PKG / "t42"
    proc = _source_and_run(install, env, tmp, str(t42), "--help")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "usage: t42" in proc.stdout
    proc = _source_and_run(install, env, tmp, str(t42), "--version")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert t42_transfer.__version__ in proc.stdout
    # The sourced workspace (not the repository) provides the package.
    proc = _source_and_run(
        install, env, tmp, sys.executable, "-c",
        "import t42_transfer, os; print(os.path.realpath(t42_transfer.__file__))",
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert Path(proc.stdout.strip()).is_relative_to(install.resolve())


def test_installed_t42_runs_with_plain_pythonpath(colcon_build):
    install, env, tmp = colcon_build["install"], dict(colcon_build["env"]), colcon_build["tmp"]
    env["PYTHONPATH"] = str(_site_packages(install))
    t42 = install / PKG / "lib" / PKG / "t42"
    proc = subprocess.run([str(t42), "--help"], cwd=tmp, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "usage: t42" in proc.stdout
