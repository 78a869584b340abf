"""``t42 up configs/hardware_emulated.yaml`` (emulator and Dynamixel driver) used by a plain rclpy script."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from ros_rig import REPO, stop

USER = Path(__file__).with_name("hardware_user.py")
T42 = [sys.executable, "-u", "-m", "t42_transfer.cli"]


def test_a_plain_rclpy_script_drives_the_emulated_hand(ros_domain: int, tmp_path: Path) -> None:
    config = yaml.safe_load((REPO / "configs" / "hardware_emulated.yaml").read_text())
    link = str(tmp_path / "ttyT42")  # the test's own port: parallel runs do not share /tmp/t42_servos
    config["/**/hw_emulator"]["ros__parameters"]["link"] = link
    config["/**/dynamixel_driver"]["ros__parameters"]["port"] = link
    config["/**/dynamixel_driver"]["ros__parameters"]["autostart"] = False  # the script drives the lifecycle
    params = tmp_path / "hardware.yaml"
    params.write_text(yaml.safe_dump(config))
    suite = subprocess.Popen([*T42, "up", str(params), "--only", "hw_emulator,dynamixel_driver"], cwd=tmp_path,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        user = subprocess.run([sys.executable, str(USER)], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    finally:
        codes = stop([suite], timeout_s=15.0)
    out = suite.stdout.read() if suite.stdout else ""
    if suite.stdout:
        suite.stdout.close()
    if user.returncode != 0:  # pytest.fail prints all of it (an assertion's message is cut short)
        pytest.fail(f"the user script failed:\n{user.stdout}\n{user.stderr}\nthe suite said:\n{out[-6000:]}")
    seen = json.loads(user.stdout.strip().splitlines()[-1])
    lifecycle = seen["lifecycle"]  # through the stock services, from unconfigured: each transition did its part
    assert (lifecycle["initial"], lifecycle["configured"], lifecycle["activate"], lifecycle["activated"]) == \
        ("unconfigured", "inactive", True, "active"), lifecycle
    assert seen["state"] == "active"
    assert {"port", "servo_ids", "load_limit", "grasp_load", "max_pose_age_s", "drop_jump_m"} <= set(seen["parameters"])
    (ok, _), (refused, reason) = seen["set"]
    assert ok and not refused and "grasp_load must be below load_limit" in reason
    assert seen["reset"][0], seen["reset"]
    assert seen["grasp_statuses"][-2:] == ["grasping", "reset"], seen["grasp_statuses"]  # begun, then closed
    assert all(8.0 <= r <= 12.0 for r in seen["rates_hz"]), seen["rates_hz"]  # on arrival
    assert all(9.0 <= r <= 11.0 for r in seen["stamp_rates_hz"]), seen  # the stamps: 10 Hz of the graph's clock
    assert all(95.0 <= g <= 105.0 for g in seen["stamp_median_gap_ms"]), seen["stamp_median_gap_ms"]
    assert seen["trajectory_done"]
    final, target = seen["followed"]
    assert abs(final[1] - target[1]) < 0.03 and abs(final[0] - target[0]) < 0.03, seen["followed"]
    past = seen["past_limit"]  # targets to -0.5 rad on actuator 2, its limit at 0 (open)
    assert past["max_angle_rad"] == [3.0, 3.0] and past["target"][1] == -0.5 and past["trajectory_done"], past
    assert any("position limit on actuator(s) [1]" in s for s in past["refused"]), past["refused"]
    assert all(p[1] >= -0.005 for p in past["positions"]), past["positions"]  # never past the limit ...
    assert abs(past["positions"][-1][1]) < 0.02, past["positions"][-5:]  # ... and stopped at it
    assert seen["rejections"] >= 3
    assert len(seen["refused_statuses"]) >= 3, seen["refused_statuses"]  # the bad commands, on hand/status too
    assert all(0.0 <= a <= 3.0 + 1e-3 for pos in seen["positions_after"] for a in pos)
    assert codes == [0], out[-3000:]
