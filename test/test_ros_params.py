"""Params dataclasses as declared ROS parameters: descriptors, params files, overrides, refusals at run time."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter

from t42_transfer.ros.node_lifetime import DestroyableLifecycleNode
from t42_transfer.ros.params import LiveParams, declare_params, param


@dataclass(frozen=True)
class Demo:
    out: Path = param(description="where results go", read_only=True)
    rate: float = param(1.0, "steps per tick", min=0.01, max=100.0)
    count: int = param(3, "how many", min=1)
    flag: bool = param(False, "a switch")
    gains: tuple[float, ...] = param((1.0, 2.0), "per-joint gains")
    ids: tuple[int, ...] = param((1, 2), "per-joint ids")
    names: tuple[str, ...] = param(("a",), "names")
    seed: int | None = param(None, "seed (unset: random)")
    extra: tuple[str, ...] = param((), "empty by default")
    reach_m: float = param(0.5, "how far (m)", renamed_from="reach_mm")

    def __post_init__(self) -> None:
        if self.count > 2 * len(self.gains) + 10:
            raise ValueError(f"count {self.count} is more than the gains allow")


class DemoNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("demo", **kwargs)
        self.changes: list[tuple[Demo, Demo]] = []
        self.live = LiveParams(self, Demo, lambda old, new: self.changes.append((old, new)))


def test_declares_every_field_with_its_descriptor(ros) -> None:
    node = ros.add(DemoNode, {"out": "/tmp/x"})
    assert node.live.value == Demo(out=Path("/tmp/x"))
    types = {n: node.describe_parameter(n).type for n in ("out", "rate", "count", "flag", "gains", "names", "extra")}
    assert types == {"out": ParameterType.PARAMETER_STRING, "rate": ParameterType.PARAMETER_DOUBLE,
                     "count": ParameterType.PARAMETER_INTEGER, "flag": ParameterType.PARAMETER_BOOL,
                     "gains": ParameterType.PARAMETER_DOUBLE_ARRAY, "names": ParameterType.PARAMETER_STRING_ARRAY,
                     "extra": ParameterType.PARAMETER_STRING_ARRAY}
    assert node.get_parameter("extra").type_ == Parameter.Type.STRING_ARRAY
    rate = node.describe_parameter("rate")
    assert rate.description == "steps per tick" and not rate.read_only
    assert (rate.floating_point_range[0].from_value, rate.floating_point_range[0].to_value) == (0.01, 100.0)
    assert node.describe_parameter("count").integer_range[0].from_value == 1
    assert node.describe_parameter("out").read_only and node.describe_parameter("seed").dynamic_typing


def test_params_file_then_overrides(ros, tmp_path: Path) -> None:
    params_file = tmp_path / "p.yaml"
    params_file.write_text("/**:\n  ros__parameters:\n    rate: 2.0\n    count: 5\n"
                           "demo:\n  ros__parameters:\n    out: results\n    rate: 3.0\n"
                           "    names: [left, right]\n    seed: 7\n")
    node = ros.add(DemoNode, {"count": 6, "extra": ["z"]},
                   cli_args=["--ros-args", "--params-file", str(params_file)])
    assert node.live.value == Demo(out=Path("results"), rate=3.0, count=6, names=("left", "right"), seed=7,
                                   extra=("z",))


@pytest.mark.parametrize("params,match", [
    ({}, "missing required parameter 'out'"),
    ({"out": "x", "rate": 1000.0}, "rate"),
    ({"out": "x", "count": "many"}, "count"),
    ({"out": "x", "count": 99}, "more than the gains allow"),
    ({"out": "x", "seed": "~"}, r"^/demo: parameter 'seed' expects int, got '~'"),  # dynamically typed: no ROS check
    ({"out": "x", "reach_mm": 500.0}, r"'reach_mm' is now 'reach_m': how far \(m\)"),
])
def test_bad_start_values_are_value_errors_naming_the_parameter(ros, params, match) -> None:
    with pytest.raises(ValueError, match=match):
        ros.add(DemoNode, params)


def test_run_time_changes_validated_refused_with_reason_and_applied(ros) -> None:
    node = ros.add(DemoNode, {"out": "x"})
    client = ros.node("setter").create_client(SetParameters, "demo/set_parameters")

    def set_(**values):
        request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                    for k, v in values.items()])
        return [(r.successful, r.reason) for r in ros.call(client, request).results]

    assert set_(count=40) == [(False, "count 40 is more than the gains allow")]
    assert set_(rate=0.0)[0][0] is False and set_(count=2.5)[0][0] is False and set_(out="y")[0][0] is False
    assert node.live.value == Demo(out=Path("x")) and node.changes == []
    assert set_(rate=4.0, seed=3) == [(True, ""), (True, "")]
    assert set_(extra=["a", "b"]) == [(True, "")]  # an empty default still has its type
    # numeric arrays come out of a set_parameters request as array.array, as `ros2 param set` sends them
    assert set_(gains=[3.0, 4.5], ids=[7, 8]) == [(True, ""), (True, "")]
    assert node.live.value == Demo(out=Path("x"), rate=4.0, seed=3, extra=("a", "b"), gains=(3.0, 4.5), ids=(7, 8))
    assert type(node.live.value.ids[0]) is int and type(node.live.value.gains[0]) is float
    assert set_(ids=[1.5, 2.5])[0][0] is False  # the wrong element type is still refused
    assert node.live.value.ids == (7, 8)
    assert [new.rate for _, new in node.changes] == [4.0] * 5  # (one change per parameter set)
    assert node.changes[-1][1].seed == 3
    assert set_(rate=4.0) == [(True, "")] and len(node.changes) == 5  # set again to its value: no change to act on
    assert set_(use_sim_time=True) == [(True, "")]  # rclpy's own parameters pass through
    (unset,) = set_(seed=None)  # PARAMETER_NOT_SET: rclpy would undeclare the parameter
    assert unset[0] is False and "cannot be unset at run time" in unset[1]
    assert node.has_parameter("seed") and set_(seed=4) == [(True, "")] and node.live.value.seed == 4


@dataclass(frozen=True)
class Bus:
    port: str = param("/dev/ttyUSB0", "the bus", configure=True)
    rate: float = param(1.0, "steps per tick", min=0.01)


class BusNode(DestroyableLifecycleNode):
    def __init__(self, **kwargs) -> None:
        super().__init__("bus", **kwargs)
        self.live = LiveParams(self, Bus)


def test_a_configure_parameter_is_set_while_unconfigured_only(ros) -> None:
    """What configure reads: a wrong port is fixed by cleanup, a set and configure, without a restart."""
    node = ros.add(BusNode)
    assert "set while unconfigured" in node.describe_parameter("port").additional_constraints
    assert not node.describe_parameter("port").read_only

    def set_(name, value):
        (result,) = node.set_parameters([Parameter(name, value=value)])
        return result.successful, result.reason

    assert set_("port", "/dev/ttyUSB1") == (True, "") and node.live.value.port == "/dev/ttyUSB1"
    node.trigger_configure()
    ok, reason = set_("port", "/dev/ttyUSB2")
    assert not ok and reason == "port is read at configure: set it while the node is unconfigured (it is inactive: " \
        "cleanup first)", reason
    assert node.live.value.port == "/dev/ttyUSB1"
    assert set_("port", "/dev/ttyUSB1") == (True, "") and set_("rate", 2.0) == (True, "")  # no change; live
    node.trigger_cleanup()
    assert node.state == "unconfigured" and set_("port", "/dev/ttyUSB2") == (True, "")
    assert node.live.value == Bus(port="/dev/ttyUSB2", rate=2.0)


def test_a_configure_parameter_needs_a_lifecycle_node_and_is_not_also_read_only(ros) -> None:
    class PlainBus(Node):
        def __init__(self, **kwargs) -> None:
            super().__init__("plain_bus", **kwargs)
            self.live = LiveParams(self, Bus)

    with pytest.raises(TypeError, match="need a lifecycle node"):
        ros.add(PlainBus)
    with pytest.raises(TypeError, match="not both"):
        param("x", "both", read_only=True, configure=True)


def test_declare_params_rejects_types_ros_cannot_carry(ros) -> None:
    @dataclass(frozen=True)
    class Bad:
        table: dict = param(default_factory=dict, description="a mapping")

    node = ros.node("plain")
    with pytest.raises(TypeError, match="cannot be a ROS parameter"):
        declare_params(node, Bad)


def test_params_from_file_gives_what_the_named_node_would_declare(tmp_path: Path) -> None:
    """rcl's matching (a wildcard for every node, then the node's own section, by its full name), the node's
    checks (the range, ``__post_init__``), and the names the node has no parameter for."""
    from t42_transfer.ros.launcher import params_from_file

    path = tmp_path / "params.yaml"
    path.write_text("""
/**:
  ros__parameters: {rate: 2.0, count: 4}
/**/demo:
  ros__parameters: {out: /tmp/a, count: 5, gians: [1.0]}
left:
  demo:
    ros__parameters: {out: /tmp/left, rate: 3.0}
""")
    demo, unknown = params_from_file(Demo, path, "demo")
    assert (demo.out, demo.rate, demo.count, unknown) == (Path("/tmp/a"), 2.0, 5, ["gians"])
    left, unknown = params_from_file(Demo, path, "/left/demo")
    assert (left.out, left.rate, left.count) == (Path("/tmp/left"), 3.0, 5)
    with pytest.raises(ValueError, match="no parameters for /other"):
        params_from_file(Demo, _only_for(tmp_path, "demo"), "other")  # a section for another node only
    path.write_text("/**/demo:\n  ros__parameters: {out: /tmp/a, rate: 500.0}\n")
    with pytest.raises(ValueError, match="/demo: parameter 'rate'"):
        params_from_file(Demo, path, "demo")


def _only_for(tmp_path: Path, node: str) -> Path:
    path = tmp_path / f"only_{node}.yaml"
    path.write_text(f"/**/{node}:\n  ros__parameters: {{out: /tmp/x}}\n")
    return path
