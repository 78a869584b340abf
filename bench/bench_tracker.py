"""Object tracker per frame beside a bare ArUco + solvePnP loop on the same rendered frames, and the renderer's rate.

    .venv/bin/python bench/bench_tracker.py [--frames 200] [--repeats 3] [--out bench/results/tracker.json]

At each resolution (640x480 and 1280x720; ``--resolutions``) the simulated hand moves under random actions
and :class:`~t42_transfer.tracking.render.HandCamera` renders ``--frames`` frames of it once, beforehand
(``rgb8``, the scene's default camera pose and field of view at that image size); the render calls are timed
(``render``: frames per second, CPU per frame).  Then, on those same frames:

* ``tracker``: :meth:`ObjectTracker.process <t42_transfer.tracking.markers.ObjectTracker.process>`, what the
  ``object_tracker`` node runs per frame: the image checks and grey conversion, detection (AprilTag corner
  refinement), the base frame (IPPE of one base marker refined over all of them), the object on its known
  plane, reprojection errors and the jump check;
* ``bare``: ``cv2.aruco.ArucoDetector.detectMarkers`` on the frame (the same dictionary and corner refinement;
  it converts the colour image itself) and ``cv2.solvePnP`` (``SOLVEPNP_IPPE_SQUARE``) for every marker of the
  scene it finds, and nothing else.

The two run frame by frame in turn (which goes first alternates), ``--repeats`` passes over the frames, so
both see the same load.  Wall time (``time.perf_counter``) and CPU (``time.process_time``: this process, OpenCV's
worker threads included) are summed per method; the ratios are tracker over bare.  Target: the tracker within
1.3x of the bare loop, in wall time and in CPU per frame, at every resolution; ``target_met`` says whether this
run met it.  The tracker's answers are checked against the scene's truth (``tracked``, ``median_error_mm``) so
a fast but wrong tracker does not pass unnoticed.  The machine's load is recorded before and after each
resolution: on a shared machine, repeat on a quiet one before quoting.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.machine import machine_info  # noqa: E402
from t42_transfer.hand import SimulatedHand  # noqa: E402
from t42_transfer.hand.mjcf import MarkerScene, SceneCamera  # noqa: E402
from t42_transfer.tracking.markers import ObjectTracker  # noqa: E402
from t42_transfer.tracking.render import HandCamera  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "tracker.json"
RATIO_MAX = 1.3
ENCODING = "rgb8"


def resolution(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x480, got {text[:40]!r}") from None
    if not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise argparse.ArgumentTypeError(f"resolution {width}x{height} is out of range (16-4096)")
    return width, height


def render_frames(camera: HandCamera, frames: int, seed: int) -> tuple[list[np.ndarray], np.ndarray, dict]:
    """``frames`` images of the hand moving under random actions, the object's true positions (mm), render timing."""
    hand = SimulatedHand(camera.params)
    hand.reset(seed=seed)
    rng = np.random.default_rng(seed)
    camera.set_hand(hand)
    camera.render()  # the GL context is made on the first call: not part of the rate
    images, truths, wall, cpu = [], [], 0.0, 0.0
    for i in range(frames):
        hand.step(rng.uniform(-1.0, 1.0, size=2))
        if hand.done:
            hand.reset(seed=seed + 1 + i)
        camera.set_hand(hand)
        t, c = time.perf_counter(), time.process_time()
        images.append(camera.render())
        wall, cpu = wall + time.perf_counter() - t, cpu + time.process_time() - c
        truths.append(camera.object_xy_mm().copy())
    timing = {"frames": frames, "fps": frames / wall, "ms_per_frame": 1e3 * wall / frames,
              "cpu_ms_per_frame": 1e3 * cpu / frames}
    return images, np.array(truths), timing


def bare_loop(dictionary: str, sizes_m: dict[int, float], k: np.ndarray, d: np.ndarray):  # noqa: ANN201
    """One frame of the bare loop: detectMarkers, then solvePnP (IPPE_SQUARE) per known marker; poses found."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)
    squares = {}
    for marker_id, size in sizes_m.items():
        h = size / 2.0
        squares[marker_id] = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    def frame(image: np.ndarray) -> int:
        corners, ids, _ = detector.detectMarkers(image)
        poses = 0
        for c, i in zip(corners, () if ids is None else ids.reshape(-1), strict=True):
            square = squares.get(int(i))
            if square is not None:
                ok, _, _ = cv2.solvePnP(square, c.reshape(4, 1, 2), k, d, flags=cv2.SOLVEPNP_IPPE_SQUARE)
                poses += bool(ok)
        return poses

    return frame


def compare(camera: HandCamera, images: list[np.ndarray], truths: np.ndarray, repeats: int) -> dict:
    """Tracker and bare loop frame by frame in turn; their totals, the ratios, the tracker's answers."""
    intrinsics = camera.intrinsics()
    config = camera.tracker_config(object_height_m=camera.object_marker_height_m())
    sizes = {config.object_id: config.object_size_m, **{m.marker_id: m.size_m for m in config.base_markers}}
    bare = bare_loop(config.dictionary, sizes, intrinsics.k, intrinsics.d)
    totals = {name: {"wall": 0.0, "cpu": 0.0} for name in ("tracker", "bare")}
    per_repeat = []
    tracks, poses = [], 0
    for r in range(repeats):
        tracker = ObjectTracker(config)
        before = {name: dict(t) for name, t in totals.items()}
        for i, image in enumerate(images):
            for name in (("tracker", "bare") if (i + r) % 2 == 0 else ("bare", "tracker")):
                t, c = time.perf_counter(), time.process_time()
                if name == "tracker":
                    track = tracker.process(image, ENCODING, intrinsics)
                else:
                    found = bare(image)
                wall, cpu = time.perf_counter() - t, time.process_time() - c
                totals[name]["wall"] += wall
                totals[name]["cpu"] += cpu
            if r == 0:
                tracks.append(track)
                poses += found
        spent = {name: {k: totals[name][k] - before[name][k] for k in ("wall", "cpu")} for name in totals}
        per_repeat.append(spent["tracker"]["wall"] / spent["bare"]["wall"])
    n = len(images) * repeats
    result = {name: {"fps": n / t["wall"], "ms_per_frame": 1e3 * t["wall"] / n, "cpu_ms_per_frame": 1e3 * t["cpu"] / n}
              for name, t in totals.items()}
    errors = [float(np.linalg.norm(t.xy_mm - truth)) for t, truth in zip(tracks, truths, strict=True)
              if t.xy_mm is not None]
    statuses: dict[str, int] = {}
    for t in tracks:
        statuses[t.status] = statuses.get(t.status, 0) + 1
    result["tracker"].update(tracked=len(errors), statuses=statuses,
                             median_error_mm=float(np.median(errors)) if errors else None,
                             max_error_mm=max(errors) if errors else None)
    result["bare"]["marker_poses_per_frame"] = poses / len(images)
    result["ratio_tracker_to_bare"] = {
        "ms_per_frame": totals["tracker"]["wall"] / totals["bare"]["wall"],
        "cpu_ms_per_frame": totals["tracker"]["cpu"] / totals["bare"]["cpu"],
        "ms_per_frame_per_repeat": per_repeat,
    }
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="frames rendered per resolution (200)")
    parser.add_argument("--repeats", type=int, default=3, help="passes of both methods over the frames (3)")
    parser.add_argument("--resolutions", type=resolution, nargs="+", default=[(640, 480), (1280, 720)],
                        metavar="WxH", help="image sizes (640x480 1280x720)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.frames < 1 or args.repeats < 1:
        parser.error("--frames and --repeats must be at least 1")
    machine = machine_info()
    results = {}
    for width, height in args.resolutions:
        load_before = os.getloadavg()
        scene = MarkerScene(camera=SceneCamera(width=width, height=height))
        with HandCamera("source", scene) as camera:
            images, truths, render = render_frames(camera, args.frames, args.seed)
            run = compare(camera, images, truths, args.repeats)
        results[f"{width}x{height}"] = {"render": render, **run, "load_before": load_before,
                                        "load_after": os.getloadavg()}
    ratios = [r["ratio_tracker_to_bare"][k] for r in results.values() for k in ("ms_per_frame", "cpu_ms_per_frame")]
    command = ["python", "bench/bench_tracker.py", "--frames", str(args.frames), "--repeats", str(args.repeats),
               "--resolutions", *(f"{w}x{h}" for w, h in args.resolutions)]
    result = {
        "benchmark": "tracker",
        "command": shlex.join(command),
        "machine": machine,
        "load_before": machine["load_average"],
        "load_after": os.getloadavg(),
        "parameters": {"frames": args.frames, "repeats": args.repeats, "seed": args.seed, "encoding": ENCODING,
                       "opencv": cv2.__version__, "opencv_threads": cv2.getNumThreads(),
                       "mujoco_gl": os.environ.get("MUJOCO_GL") or "egl"},
        "resolutions": results,
        "target": {"ratio_tracker_to_bare_max": RATIO_MAX, "on": ["ms_per_frame", "cpu_ms_per_frame"],
                   "at": list(results)},
        "target_met": bool(all(r <= RATIO_MAX for r in ratios)),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
