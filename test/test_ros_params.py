"""ROS params files and --ros-args for the nodes' params dataclasses: parsing, precedence, coercion, errors."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from t42_transfer.nodes.mock_driver import MockDriverParams
from t42_transfer.nodes.recorder import RecorderParams
from t42_transfer.ros.params import RosArgs, load_params, node_sections, parse_ros_args

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Demo:
    path: Path = Path("a")
    gains: tuple[float, ...] = (1.0,)
    pair: tuple[int, str] = (0, "x")
    rate: float = 1.0
    count: int = 1
    flag: bool = False
    label: str | None = None
    topics: dict[str, str] = field(default_factory=dict)


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_parse_ros_args_splits_blocks_and_parses_values() -> None:
    rest, ros = parse_ros_args([
        "pos", "--ros-args", "--params-file", "a.yaml", "-p", "rate:=2", "--param", "gains:=[1, 2.5]",
        "-r", "__node:=renamed", "-p", "label:=", "--", "tail",
    ])
    assert rest == ["pos", "tail"]
    assert ros == RosArgs((Path("a.yaml"),), (("rate", 2), ("gains", [1, 2.5]), ("label", None)), "renamed")
    assert parse_ros_args(["x"]) == (["x"], RosArgs())


@pytest.mark.parametrize("argv, match", [
    (["--ros-args", "-p", "rate"], "name:=value"),
    (["--ros-args", "-p"], "expects a value"),
    (["--ros-args", "-r", "/a:=/b"], "only __node"),
    (["--ros-args", "-r", "__node:=bad name"], "node name"),
    (["--ros-args", "--log-level", "debug"], "unsupported ROS argument"),
])
def test_parse_ros_args_rejects_what_it_does_not_support(argv: list[str], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        parse_ros_args(argv)


def test_files_then_overrides_with_wildcard_first(tmp_path: Path) -> None:
    first = _write(tmp_path / "a.yaml", """
demo:
  ros__parameters: {count: 3, rate: 2}
/**:
  ros__parameters: {count: 1, label: everyone}
other:
  ros__parameters: {nonsense: 1}
""")
    second = _write(tmp_path / "b.yaml", "/demo:\n  ros__parameters: {rate: 4.5}\n")
    params = load_params(Demo, "demo", [first, second], [("count", 7)])
    assert params.count == 7 and params.rate == 4.5 and params.label == "everyone"
    assert node_sections(first) == ["demo", "other"]


def test_coercion_of_yaml_values() -> None:
    params = load_params(Demo, "demo", [], {
        "path": "out/dir", "gains": [1, 2.5], "pair": [3, "y"], "rate": 2, "topics": {"/a": "std_msgs/msg/String"},
    })
    assert params.path == Path("out/dir") and params.gains == (1.0, 2.5) and params.pair == (3, "y")
    assert isinstance(params.rate, float) and params.topics == {"/a": "std_msgs/msg/String"}


@pytest.mark.parametrize("name, value, match", [
    ("rate", "fast", "'rate' expects float"),
    ("count", 2.5, "'count' expects int"),
    ("count", True, "'count' expects int"),
    ("flag", 1, "'flag' expects bool"),
    ("gains", 1.0, "'gains' expects a list"),
    ("pair", [1], "expects 2 values"),
    ("label", 5, "'label' expects str | None"),
])
def test_wrong_types_name_the_parameter(name: str, value: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        load_params(Demo, "demo", [], [(name, value)])


def test_unknown_parameter_lists_the_valid_ones(tmp_path: Path) -> None:
    f = _write(tmp_path / "p.yaml", "mock_driver:\n  ros__parameters: {hand: source, hnad: target}\n")
    with pytest.raises(ValueError) as err:
        load_params(MockDriverParams, "mock_driver", [f])
    text = str(err.value)
    assert "mock_driver: unknown parameter(s) hnad" in text and "valid: hand, rate_factor" in text


def test_missing_required_and_dataclass_checks_are_value_errors() -> None:
    with pytest.raises(ValueError, match="recorder: missing required parameter.*out_dir"):
        load_params(RecorderParams, "recorder")
    with pytest.raises(ValueError, match="recorder: mode must be one of"):
        load_params(RecorderParams, "recorder", [], {"out_dir": "x", "mode": "sometimes"})


@pytest.mark.parametrize("text, match", [
    ("demo: [1, 2]\n", "'ros__parameters'"),
    ("demo:\n  parameters: {count: 1}\n", "'ros__parameters'"),
    ("- a\n", "mapping of node names"),
    ("demo: {ros__parameters: {count: [1\n", "not valid YAML"),
])
def test_malformed_params_files(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        load_params(Demo, "demo", [_write(tmp_path / "bad.yaml", text)])
    with pytest.raises(ValueError, match="params file .*missing.yaml"):
        load_params(Demo, "demo", [tmp_path / "missing.yaml"])


def test_suite_config_builds_every_nodes_params() -> None:
    from t42_transfer.nodes.registry import NODES
    from t42_transfer.ros.params import node_sections

    suite = REPO / "configs" / "suite.yaml"
    driver = load_params(MockDriverParams, "mock_driver", [suite])
    recorder = load_params(RecorderParams, "recorder", [suite], [("out_dir", "/tmp/elsewhere")])
    assert driver.hand == "target"
    assert recorder.mode == "episode" and recorder.out_dir == "/tmp/elsewhere"
    sections = node_sections(suite)
    assert sections == ["mock_driver", "recorder", "transfer_server", "planner"]
    for name in sections:
        assert load_params(NODES[name].params_class(), name, [suite]) is not None


def test_use_sim_time_is_a_node_option_not_a_params_field(tmp_path: Path) -> None:
    from t42_transfer.ros.params import NodeOptions, node_options

    path = _write(tmp_path / "p.yaml", "mock_driver:\n  ros__parameters:\n    hand: source\n    use_sim_time: true\n")
    assert load_params(MockDriverParams, "mock_driver", [path]).hand == "source"
    assert node_options("mock_driver", [path]) == NodeOptions(use_sim_time=True)
    assert node_options("mock_driver", [path], [("use_sim_time", False)]).use_sim_time is False
    assert node_options("recorder", [path]) == NodeOptions()
    with pytest.raises(ValueError, match="use_sim_time"):
        node_options("mock_driver", [], [("use_sim_time", "sometimes")])
