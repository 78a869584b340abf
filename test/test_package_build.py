"""`colcon build` of this package, the way a ROS 2 workspace builds it.

colcon-common-extensions from PyPI builds an ament_python package without a
ROS install.  The build goes to a temporary directory outside the repository
and must leave no build/, install/, log/ or *.egg-info behind in it.
(Takes a few seconds, so it is part of the fast suite.)

The interface package t42_interfaces (interfaces/t42_interfaces) is built by interfaces/build.sh into the venv
(scripts/bootstrap.sh runs it): its tests reuse that install when it is up to date (a no-op of a fraction of a
second) and build it otherwise (about 30 s), once per session; without cmake or a C++ compiler they fail,
as the bootstrap does (the suite's nodes import the package). On a machine with ROS 2 Jazzy in /opt/ros/jazzy the
slow suite also builds both packages there.
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
    params_files = sorted([*REPO.glob("configs/suite*.yaml"), *REPO.glob("configs/hardware_*.yaml")])
    assert len(params_files) >= 4, "the suite's params files moved"
    for config_file in [*params_files, REPO / "configs" / "foxglove_layout.json"]:
        installed = share / PKG / "config" / config_file.name
        assert installed.read_bytes() == config_file.read_bytes(), config_file.name


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


# --------------------------------------------------------------------------- t42_interfaces
INTERFACES = REPO / "interfaces" / "t42_interfaces"
VENV = Path(sys.prefix)
MESSAGES = ("PlanResult", "ModelUpdated", "BagClosed")
ACTIONS = ("Reach", "Transfer")
TYPESUPPORTS = ("rosidl_generator_c", "rosidl_generator_py", "rosidl_typesupport_c", "rosidl_typesupport_cpp",
                "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp",
                "rosidl_typesupport_introspection_c", "rosidl_typesupport_introspection_cpp")
# What a plain `python` of the venv starts with: nothing that names the package or its libraries.
_NOT_INHERITED = ("PYTHONPATH", "LD_LIBRARY_PATH", "AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH", "COLCON_PREFIX_PATH",
                  "_ROS_WHEELS_BOOTSTRAP_COMPLETE")


@pytest.fixture(scope="session")
def interfaces_installed() -> Path:
    """interfaces/build.sh for this venv (a no-op when the bootstrap's install is up to date); the venv.

    The suite's nodes import the package, so a build tool missing here fails (build.sh's exit 3, its line naming
    the Debian packages), as the bootstrap does."""
    env = {k: v for k, v in os.environ.items() if k not in _NOT_INHERITED}
    proc = subprocess.run(["bash", str(REPO / "interfaces" / "build.sh"), str(VENV)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"interfaces/build.sh failed:\n{proc.stdout}\n{proc.stderr}"
    return VENV


def test_a_machine_without_build_tools_gets_one_line_naming_the_debian_packages(tmp_path):
    """A build asked for (T42_BOOTSTRAP_FORCE) on a PATH without cmake, a C++ compiler or make: exit 3 and one
    line, before anything installed is touched (scripts/bootstrap.sh stops on it)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for folder in (Path("/usr/bin"), Path("/bin")):
        for tool in folder.iterdir():
            if tool.name not in {"cmake", "c++", "g++", "make", "ninja"} and not (bin_dir / tool.name).exists():
                (bin_dir / tool.name).symlink_to(tool)
    stamp = VENV / ".t42-interfaces-installed"
    before = stamp.read_bytes() if stamp.exists() else None
    env = {**{k: v for k, v in os.environ.items() if k not in _NOT_INHERITED}, "PATH": str(bin_dir),
           "T42_BOOTSTRAP_FORCE": "1"}
    proc = subprocess.run(["bash", str(REPO / "interfaces" / "build.sh"), str(VENV)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3, proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("interfaces: error: no cmake g++ make") and "sudo apt-get install cmake g++ make" in line
    assert (stamp.read_bytes() if stamp.exists() else None) == before  # the installed package is untouched


def test_interfaces_package_builds_into_the_venv(interfaces_installed):
    venv = interfaces_installed
    manifest = (venv / ".t42-interfaces-manifest.txt").read_text().split()
    assert manifest and all(Path(f).is_file() and Path(f).is_relative_to(venv) for f in manifest)
    for ts in TYPESUPPORTS:
        assert str(venv / "lib" / f"libt42_interfaces__{ts}.so") in manifest, ts
    site = _venv_site_packages(venv)
    for name in MESSAGES:
        assert str(site / "t42_interfaces" / "msg" / f"_{_snake(name)}.py") in manifest
    for name in ACTIONS:
        assert str(site / "t42_interfaces" / "action" / f"_{_snake(name)}.py") in manifest
        assert str(venv / "share" / "t42_interfaces" / "action" / f"{name}.action") in manifest
    assert str(venv / "share" / "ament_index" / "resource_index" / "packages" / "t42_interfaces") in manifest
    assert (venv / "share" / "t42_interfaces" / "package.xml").read_bytes() == (INTERFACES / "package.xml").read_bytes()


def _venv_site_packages(venv: Path) -> Path:
    return venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"


def _snake(name: str) -> str:
    return "".join("_" + c.lower() if c.isupper() and i else c.lower() for i, c in enumerate(name))


def test_interfaces_import_in_a_plain_venv_python(interfaces_installed, tmp_path):
    """A fresh interpreter of the venv, none of the variables a sourced ROS workspace sets, outside the repo."""
    env = {k: v for k, v in os.environ.items() if k not in _NOT_INHERITED}
    code = (
        "import t42_interfaces\n"
        "from t42_interfaces.action import Reach, Transfer\n"
        "from t42_interfaces.msg import BagClosed, ModelUpdated, PlanResult\n"
        "from rclpy.serialization import deserialize_message, serialize_message\n"
        "goal = Reach.Goal(tolerance_m=0.002, steps=40)\n"
        "assert deserialize_message(serialize_message(goal), Reach.Goal) == goal\n"
        "print(t42_interfaces.__file__)\n"
    )
    proc = subprocess.run([str(interfaces_installed / "bin" / "python"), "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert Path(proc.stdout.strip()).is_relative_to(_venv_site_packages(interfaces_installed))


def _filled_messages() -> list:
    """One message of each type, every field set to something other than its default."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import Point, PointStamped, PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from std_msgs.msg import Header
    from t42_interfaces.action import Reach, Transfer
    from t42_interfaces.msg import BagClosed, ModelUpdated, PlanResult

    stamp = Time(sec=12, nanosec=345)
    base = Header(stamp=stamp, frame_id="t42_base")
    path = PathMsg(header=base, poses=[PoseStamped(header=base), PoseStamped(header=base)])
    path.poses[1].pose.position.x = 0.01
    return [
        PlanResult(header=base, accepted=True, status="ok", reason="", has_goal=True,
                   goal=Point(x=0.01, y=0.11), goal_stamp=stamp, has_start=True, start=Point(x=0.0, y=0.1),
                   predicted_error_m=0.0012, horizon=40, samples_evaluated=800, planning_time_s=0.25,
                   model="/m/model.safetensors", method="fine_tune", replan_every=5),
        ModelUpdated(stamp=stamp, path="/m/model.safetensors", method="residual", episodes=12),
        BagClosed(path="/b/bag_0", episodes=1, messages=4321, start=stamp, end=Time(sec=20), reason="episode"),
        Reach.Goal(target=PointStamped(header=base, point=Point(x=0.01, y=0.11)), tolerance_m=0.002, steps=40,
                   replan_every=5),
        Reach.Feedback(step=10, error_m=0.004, predicted_final_error_m=0.001),
        Reach.Result(success=True, final_error_m=0.0015, verdict=Reach.Result.VERDICT_HIT, reason="",
                     executed=path, predicted=path),
        Transfer.Goal(method="auto", bags=["/b/bag_0", "/b/bag_1"]),
        Transfer.Feedback(phase="training", epoch=3, epochs=200, train_loss=0.5, val_loss=float("inf")),
        Transfer.Result(success=True, message="done", model_path="/m/new.safetensors",
                        model_divergence_steps=31.5, model_mse_mm2=2.5, source_divergence_steps=12.0,
                        source_mse_mm2=9.0, hold_still_divergence_steps=3.0, hold_still_mse_mm2=40.0,
                        candidates=["fine_tune", "residual"], candidate_scores=[2.5, 3.1],
                        skipped_bags=["/b/empty"], skipped_reasons=["no episode"]),
    ]


def test_interfaces_serialise_and_deserialise(interfaces_installed):
    from rclpy.serialization import deserialize_message, serialize_message

    for msg in _filled_messages():
        data = serialize_message(msg)
        assert deserialize_message(data, type(msg)) == msg, type(msg).__name__
    from t42_interfaces.action import Reach
    assert [Reach.Result.VERDICT_HIT, Reach.Result.VERDICT_MISS, Reach.Result.VERDICT_NO_PROGRESS,
            Reach.Result.VERDICT_INCOMPLETE, Reach.Result.VERDICT_REFUSED] == \
        ["hit", "miss", "no_progress", "incomplete", "refused"]


def test_reach_action_goal_feedback_result(interfaces_installed, ros):
    """rclpy's ActionServer and ActionClient with Reach: a goal, two feedbacks, a result, in one process."""
    from geometry_msgs.msg import Point, PointStamped, PoseStamped
    from rclpy.action import ActionClient, ActionServer
    from t42_interfaces.action import Reach

    server_node, client_node = ros.node("reach_server"), ros.node("reach_client")

    def execute(handle):
        goal = handle.request
        for step in (1, 2):
            handle.publish_feedback(Reach.Feedback(step=step, error_m=0.01 / step, predicted_final_error_m=0.001))
        handle.succeed()
        result = Reach.Result(success=True, final_error_m=0.0015, verdict=Reach.Result.VERDICT_HIT)
        result.executed.header.frame_id = goal.target.header.frame_id
        result.executed.poses = [PoseStamped(header=goal.target.header)]
        result.executed.poses[0].pose.position = goal.target.point
        return result

    server = ActionServer(server_node, Reach, "t42/reach", execute)
    client = ActionClient(client_node, Reach, "t42/reach")
    try:
        assert ros.spin_until(lambda: client.server_is_ready(), 10.0), "the Reach server did not show up"
        feedback: list = []
        target = PointStamped(point=Point(x=0.012, y=0.105))
        target.header.frame_id = "t42_base"
        sent = client.send_goal_async(Reach.Goal(target=target, tolerance_m=0.002, steps=40),
                                      feedback_callback=lambda m: feedback.append(m.feedback))
        assert ros.spin_until(sent.done, 10.0) and sent.result().accepted
        result_future = sent.result().get_result_async()
        assert ros.spin_until(result_future.done, 10.0)
        ros.spin_until(lambda: len(feedback) >= 2, 2.0)
        assert [(f.step, f.error_m) for f in feedback] == [(1, 0.01), (2, 0.005)]
        got = result_future.result()
        assert got.status == 4  # action_msgs/GoalStatus STATUS_SUCCEEDED
        assert got.result.success and got.result.verdict == "hit"
        assert got.result.executed.header.frame_id == "t42_base"
        assert got.result.executed.poses[0].pose.position.x == pytest.approx(0.012)
    finally:
        client.destroy()
        server.destroy()


@pytest.mark.slow
def test_colcon_builds_both_packages_with_the_venv_as_underlay(interfaces_installed, tmp_path):
    """A workspace build of t42_transfer and t42_interfaces with the wheels' venv in place of /opt/ros (about a minute):
    the interface package needs a base path of its own (colcon does not look inside the t42_transfer package)."""
    venv = interfaces_installed
    env = _clean_env(tmp_path)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    env.update(CMAKE_PREFIX_PATH=str(venv), AMENT_PREFIX_PATH=str(venv), PATH=f"{venv / 'bin'}:{env['PATH']}")
    before = _build_artefacts(REPO)
    proc = subprocess.run(
        [*_colcon(), "--log-base", str(tmp_path / "log"), "build",
         "--base-paths", str(REPO), str(REPO / "interfaces"),
         "--build-base", str(tmp_path / "build"), "--install-base", str(tmp_path / "install"),
         "--event-handlers", "console_direct-", "desktop_notification-", "status-", "terminal_title-",
         "--cmake-args", f"-DPython3_EXECUTABLE={venv / 'bin' / 'python'}", "-DBUILD_TESTING=OFF"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900,
    )
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout}\n{proc.stderr}"
    assert "Summary: 2 packages finished" in proc.stdout + proc.stderr
    assert _build_artefacts(REPO) - before == set()
    install = tmp_path / "install"
    proc = _source_and_run(
        install, env, tmp_path, str(venv / "bin" / "python"), "-c",
        "import os, t42_interfaces; from t42_interfaces.action import Reach; "
        "print(os.path.realpath(t42_interfaces.__file__))",
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert Path(proc.stdout.strip()).is_relative_to((install / "t42_interfaces").resolve())


ROS_SETUP = Path("/opt/ros/jazzy/setup.bash")


@pytest.mark.slow
@pytest.mark.skipif(not ROS_SETUP.is_file(), reason=f"no ROS 2 Jazzy install here ({ROS_SETUP} is absent); the "
                                                    "build with the wheels' venv as the underlay stands in for it")
def test_colcon_builds_both_packages_on_a_ros_install(tmp_path):
    """The workspace build as a ROS user runs it: /opt/ros/jazzy sourced, its colcon and its Python, no venv."""
    script = (f'source "{ROS_SETUP}" && colcon --log-base "$1/log" build --base-paths "{REPO}" "{REPO / "interfaces"}" '
              '--build-base "$1/build" --install-base "$1/install" --event-handlers console_direct- '
              '&& source "$1/install/local_setup.bash" '
              '&& python3 -c "from t42_interfaces.action import Reach, Transfer; import t42_transfer"')
    env = {k: v for k, v in _clean_env(tmp_path).items() if k not in _NOT_INHERITED and k != "VIRTUAL_ENV"}
    env["PATH"] = "/usr/local/bin:/usr/bin:/bin"
    before = _build_artefacts(REPO)
    proc = subprocess.run(["bash", "-c", script, "bash", str(tmp_path)], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, f"the build on the ROS install failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert _build_artefacts(REPO) - before == set()
