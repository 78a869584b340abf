"""t42 view's scene: the hand drawn from its actuator angles, its markers, and the --snapshot picture's pixels."""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.image import imread

from msg_adapters.markers import COLORS, DELETEALL, LINE_STRIP, scene_markers
from t42_transfer.cli import main
from t42_transfer.hand.params import variant
from t42_transfer.view.scene import build_scene, hand_fingers
from t42_transfer.view.snapshot import image_size, pixel_of, render

TARGET = variant("target")


def _lengths(points: np.ndarray) -> list[float]:
    return [float(np.linalg.norm(points[i + 1] - points[i])) for i in range(2)]


def _min_distance(points: np.ndarray, centre: np.ndarray) -> float:
    dists = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        t = np.clip(np.dot(centre - a, b - a) / np.dot(b - a, b - a), 0, 1)
        dists.append(float(np.linalg.norm(centre - (a + t * (b - a)))))
    return min(dists)


def test_fingers_keep_their_links_and_close_with_the_servo():
    left0, right0 = hand_fingers(TARGET, None)
    left1, right1 = hand_fingers(TARGET, [0.8, 0.8])
    for finger, params in ((left0, TARGET.left), (right0, TARGET.right), (left1, TARGET.left)):
        assert _lengths(finger) == pytest.approx([params.proximal_mm, params.distal_mm])
    assert left0[0].tolist() == [-TARGET.base_half_width_mm, 0.0]
    assert right0[0].tolist() == [TARGET.base_half_width_mm, 0.0]
    # Free fingers close towards the centre line as the servos reel in.
    assert left1[2, 0] > left0[2, 0] + 10 and right1[2, 0] < right0[2, 0] - 10


def test_actuator_order_picks_the_finger():
    mirrored = TARGET.with_(actuator_order=(1, 0))
    left, right = hand_fingers(mirrored, [0.0, 0.8])  # component 0 turns the right finger: here at rest
    rest_left, rest_right = hand_fingers(mirrored, None)
    assert np.allclose(right, rest_right) and not np.allclose(left, rest_left)


def test_fingers_stop_at_the_object():
    clearance = TARGET.object_radius_mm + 7.0
    for centre in ([0.0, 90.0], [0.0, 60.0], [-8.0, 50.0]):
        for angles in ([0.3, 0.3], [0.36, 0.36], [0.9, 0.5], [2.0, 2.0]):
            for finger in hand_fingers(TARGET, angles, centre):
                assert _min_distance(finger, np.array(centre)) >= clearance - 0.05
    free = hand_fingers(TARGET, [0.3, 0.3])
    assert all(_min_distance(f, np.array([0.0, 60.0])) < clearance - 10 for f in free)  # they would cross it


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="actuator angles"):
        build_scene(TARGET, actuator_angles=[math.nan, 0.0])
    with pytest.raises(ValueError, match="goal"):
        build_scene(TARGET, goal_xy_mm=[1.0])
    with pytest.raises(ValueError, match="tolerance"):
        build_scene(TARGET, tolerance_mm=0.0)


def _scene(goal=True):
    path = np.column_stack([np.linspace(0, 20, 21), np.linspace(90, 105, 21)])
    return build_scene(TARGET, actuator_angles=[0.36, 0.4], object_xy_mm=[0.0, 90.0],
                       goal_xy_mm=[20.0, 105.0] if goal else None, tolerance_mm=6.0, path_xy_mm=path,
                       candidates=[path + [0, 5]])


def test_markers_draw_every_part_in_metres_and_survive_cdr():
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    array = deserialize_message(serialize_message(scene_markers(_scene(), 1_500_000_000)), MarkerArray)
    first, *markers = array.markers
    assert first.action == DELETEALL
    by_ns = {}
    for m in markers:
        by_ns.setdefault(m.ns, []).append(m)
        assert m.header.frame_id == "t42_base" and m.header.stamp.sec == 1 and m.header.stamp.nanosec == 500_000_000
    assert sorted(by_ns) == ["candidates", "goal", "hand", "object", "path"]
    assert len(by_ns["hand"]) == 3  # two fingers and the palm
    circle = next(m for m in by_ns["goal"] if m.type == LINE_STRIP)
    radii = [math.hypot(p.x - 0.020, p.y - 0.105) for p in circle.points]
    assert radii == pytest.approx([0.006] * len(radii))
    obj = by_ns["object"][0]
    assert (obj.pose.position.x, obj.pose.position.y) == pytest.approx((0.0, 0.090))
    assert obj.scale.x == pytest.approx(2 * TARGET.object_radius_mm / 1000)
    path = by_ns["path"][0]
    assert (path.points[-1].x, path.points[-1].y) == pytest.approx((0.020, 0.105))
    no_goal = scene_markers(_scene(goal=False), 0)
    assert "goal" not in {m.ns for m in no_goal.markers}


def _near(image: np.ndarray, color: tuple[float, ...], col: float, row: float, radius: int = 1) -> bool:
    """Whether a pixel within ``radius`` of (col, row) has ``color`` (RGB, within a few levels)."""
    c, r = round(col), round(row)
    patch = image[max(r - radius, 0):r + radius + 1, max(c - radius, 0):c + radius + 1, :3]
    return bool(np.any(np.all(np.abs(patch - np.array(color[:3])) < 0.03, axis=-1)))


def _count(image: np.ndarray, color: tuple[float, ...]) -> int:
    return int(np.sum(np.all(np.abs(image[..., :3] - np.array(color[:3])) < 0.03, axis=-1)))


def test_snapshot_draws_the_goal_circle_and_the_path_where_they_are(tmp_path):
    scene = _scene()
    image = imread(render(scene, tmp_path / "scene.png"))
    assert image.shape[:2] == image_size(scene)[::-1]
    goal = scene.goal_xy_mm
    for angle in np.linspace(0, 2 * math.pi, 12, endpoint=False):
        on_circle = goal + scene.tolerance_mm * np.array([math.cos(angle), math.sin(angle)])
        assert _near(image, COLORS["goal"], *pixel_of(scene, on_circle)), f"no goal circle at {angle:.2f} rad"
    # Inside the circle, between the dot and the line, the picture shows the path, not the goal.
    assert not _near(image, COLORS["goal"], *pixel_of(scene, goal + [0, -3.5]), radius=0)
    for k in (3, 8, 13):
        assert _near(image, COLORS["path"], *pixel_of(scene, scene.path_xy_mm[k])), f"no path at point {k}"
    assert not _near(image, COLORS["path"], *pixel_of(scene, [-20.0, 60.0]), radius=3)  # nor elsewhere

    bare = imread(render(_scene(goal=False), tmp_path / "no_goal.png"))
    assert _count(image, COLORS["goal"]) > 50
    assert _count(bare, COLORS["goal"]) == 0
    assert _count(bare, COLORS["path"]) > 50


def test_cli_snapshot_from_a_bag_and_from_values(tmp_path, small_set, capsys):
    from t42_transfer.data.bag import write_bag

    bag = write_bag(tmp_path / "bag", small_set)
    out = tmp_path / "bag.png"
    assert main(["view", "--snapshot", str(out), "--bag", str(bag), "--goal", "12", "110", "--tolerance", "4"]) == 0
    assert "object, goal" in capsys.readouterr().out
    image = imread(out)
    scene = build_scene("target", goal_xy_mm=[12, 110], tolerance_mm=4)
    assert _near(image, COLORS["goal"], *pixel_of(scene, [16.0, 110.0]))
    path_file = tmp_path / "path.txt"
    path_file.write_text("0,90\n10,100\n")
    assert main(["view", "--snapshot", str(tmp_path / "v.png"), "--angles", "0.3", "0.3", "--path",
                 str(path_file)]) == 0
    assert main(["view", "--snapshot", str(out), "--bag", str(bag)]) == 2  # never overwrites
    assert main(["view", "--snapshot", str(tmp_path / "x.png"), "--bag", str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_the_foxglove_layout_shows_suite_topics_and_publishes_goals_where_the_view_lets_it():
    import json
    import re
    from pathlib import Path

    from msg_adapters import names
    from t42_transfer.nodes.view import ViewParams

    layout = json.loads((Path(__file__).resolve().parents[1] / "configs" / "foxglove_layout.json").read_text())
    panels = layout["configById"]

    def leaves(node):
        return [node] if isinstance(node, str) else [*leaves(node["first"]), *leaves(node["second"])]

    assert sorted(leaves(layout["layout"])) == sorted(panels)  # every panel placed, none missing
    words = {v for k, v in vars(names).items() if k.isupper() and isinstance(v, str)}
    text = json.dumps(panels)
    unused_tools = {"/rosout", "/move_base_simple/goal", "/initialpose"}  # Foxglove's defaults, left unused
    topics = set(re.findall(r'"(/[a-z_/]+?)(?:\.[a-z_\[\]0-9.]+)?"', text)) - unused_tools
    assert topics and {t.lstrip("/") for t in topics} <= words, sorted(t for t in topics if t.lstrip("/") not in words)
    scene = panels["3D!t42scene"]
    assert scene["topics"]["/" + names.VIEW_MARKERS]["visible"] and scene["followTf"] == "t42_base"
    allowed = {t.lstrip("/") for t in ViewParams().client_topics}
    assert scene["publish"]["pointTopic"].lstrip("/") in allowed
    publish = panels["Publish!t42goal"]
    assert publish["topicName"].lstrip("/") in allowed and publish["datatype"] == "geometry_msgs/msg/PointStamped"
    assert json.loads(publish["value"])["header"]["frame_id"] == "t42_base"


def _decoder(typename: str, definition: str):
    """An independent reader of ``typename`` from its full definition alone (rosbags' CDR, a fresh typestore)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store, types = get_typestore(Stores.EMPTY), {}
    first, *rest = definition.split("\n" + "=" * 80 + "\n")
    package, _, name = typename.split("/")
    types.update(get_types_from_msg(first, f"{package}/msg/{name}"))
    for section in rest:
        head, _, body = section.partition("\n")
        pkg, _, sub = head.removeprefix("MSG: ").partition("/")
        types.update(get_types_from_msg(body, f"{pkg}/msg/{sub}"))
    store.register(types)
    return lambda cdr: store.deserialize_cdr(cdr, f"{package}/msg/{name}")


def test_schemas_are_the_recorders_and_decode_our_own_types(tmp_path, small_set):
    from rclpy.serialization import serialize_message
    from rosbags.highlevel import AnyReader

    from msg_adapters.kit import TYPESTORE
    from msg_adapters.schemas import message_definition
    from t42_transfer.data.bag import write_bag

    with AnyReader([write_bag(tmp_path / "bag", small_set)], default_typestore=TYPESTORE) as reader:
        for conn in reader.connections:
            assert message_definition(conn.msgtype) == conn.msgdef.data  # what the recorder's bags hold
    interfaces = pytest.importorskip("t42_interfaces.action")
    feedback = interfaces.Reach.Impl.FeedbackMessage()
    feedback.feedback.step, feedback.feedback.error_m = 7, 0.0125
    typename = "t42_interfaces/action/Reach_FeedbackMessage"  # as the action's feedback topic names it
    decoded = _decoder(typename, message_definition(typename))(serialize_message(feedback))
    assert (decoded.feedback.step, decoded.feedback.error_m) == (7, 0.0125)
    with pytest.raises(KeyError, match="no definition"):
        message_definition("no_such_msgs/msg/Nothing")


def test_a_refused_goal_is_drawn_red_with_the_planners_word(tmp_path):
    scene = build_scene(TARGET, goal_xy_mm=[20.0, 105.0], tolerance_mm=6.0, goal_refused="unreachable")
    goal = [m for m in scene_markers(scene, 0).markers if m.ns == "goal"]
    assert {(m.color.r, m.color.g, m.color.b) for m in goal} == {COLORS["refused"][:3]}
    assert [m.text for m in goal if m.text] == ["refused: unreachable"]
    image = imread(render(scene, tmp_path / "refused.png"))
    assert _near(image, COLORS["refused"], *pixel_of(scene, [26.0, 105.0]))
    assert _count(image, COLORS["goal"]) == 0


def test_cli_refuses_what_it_would_not_draw(tmp_path, small_set, capsys):
    """Snapshot options given to a server, --at without a bag, or a time after the bag's end: refused, not
    dropped without a word."""
    from t42_transfer.data.bag import write_bag

    bag = write_bag(tmp_path / "bag", small_set)
    for argv, says in ((["--port", "0", "--object", "1", "2"], "--object: for a --snapshot only"),
                       (["--bag", str(bag), "--at", "3"], "--at: for a --snapshot only"),
                       (["--snapshot", str(tmp_path / "a.png"), "--at", "3"], "give --bag too")):
        with pytest.raises(SystemExit) as stop:
            main(["view", *argv])
        assert stop.value.code == 2 and says in capsys.readouterr().err, argv
    out = tmp_path / "late.png"
    assert main(["view", "--snapshot", str(out), "--bag", str(bag), "--at", "1e6"]) == 2
    assert "no scene at 1e+06 s" in capsys.readouterr().err and not out.exists()
