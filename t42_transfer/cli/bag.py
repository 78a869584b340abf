"""``t42 bag``: inspect, import, repair and play rosbag2 bags."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from t42_transfer.cli.args import bags_in, existing_dir, existing_file, float_arg, new_output


def _cmd_bag_info(args: argparse.Namespace) -> int:
    import warnings

    from t42_transfer.data.bag import bag_info, is_bag, read_bag, verify_bag
    from t42_transfer.data.quality import scan, summarise, summary_lines
    from t42_transfer.data.trajectory import TrajectorySet

    if args.bag.is_dir() and not is_bag(args.bag):  # a recorder's out_dir
        return _folder_info(args.bag, args.json, args.verify)
    info = bag_info(args.bag)
    if info["no_hand_episodes"] is None:
        with warnings.catch_warnings():  # bag_info has already warned about whatever it salvaged
            warnings.simplefilter("ignore")
            data = read_bag(args.bag)
    else:  # an empty bag, or one of other topics (ros2 bag record /rosout): listed, no episodes to read
        data = TrajectorySet([])
    findings = scan(data)
    mismatches = verify_bag(args.bag) if args.verify else []
    if args.json:
        info["quality"] = summarise(data, findings)
        print(json.dumps({**info, "verify": mismatches} if args.verify else info, indent=2, default=str))
        return 1 if mismatches else 0
    for key, value in info.items():
        if key == "no_hand_episodes":
            if value:  # why episodes is 0
                print(f"no hand episodes: {value}")
        elif isinstance(value, dict):
            print(f"{key}:")
            for k, v in value.items():
                print(f"  {k}: {v}")
        else:
            print(f"{key}: {value}")
    print(f"quality: {len(findings)} of {len(data)} episodes with frozen tracking, jumps or late steps")
    for line in summary_lines(findings) if findings else ():
        print(f"  {line}")
    if args.verify:
        print(f"verify: {len(mismatches)} mismatches between metadata.yaml and the data" if mismatches
              else "verify: metadata.yaml agrees with the data")
        for mismatch in mismatches:
            print(f"  {mismatch}")
    return 1 if mismatches else 0


def _folder_info(folder: Path, as_json: bool, verify: bool) -> int:
    """One line per finished bag in ``folder`` (its episodes, transitions, end reasons; with ``verify``, its
    mismatches), then the sums; or a JSON list of each bag's info (``error`` for an unreadable one).  Exit 1 when a
    bag is unreadable or disagrees with its metadata."""
    from t42_transfer.data.bag import BagError, bag_info, verify_bag

    bags = bags_in([folder])
    infos, totals, failed = [], [0, 0], False
    for bag in bags:
        try:
            info = bag_info(bag)
            if verify:
                info["verify"] = verify_bag(bag)
        except BagError as err:  # one bad bag is named, the others still summed up
            info = {"path": str(bag), "error": str(err)}
        infos.append(info)
        failed = failed or "error" in info or bool(info.get("verify"))
        if as_json:
            continue
        if "error" in info:
            print(f"{bag.name}: unreadable: {info['error']}")
            continue
        totals[0] += info["episodes"]
        totals[1] += info["transitions"]
        ends = ", ".join(f"{k} {v}" for k, v in info["end_reasons"].items()) or "-"
        checked = f", verify: {len(info['verify'])} mismatches" if verify else ""
        print(f"{bag.name}: {info['episodes']} episodes, {info['transitions']} transitions, "
              f"{info['duration_s']:.1f} s, ends: {ends}{checked}")
    if as_json:
        print(json.dumps(infos, indent=2, default=str))
    else:
        print(f"{len(bags)} bags: {totals[0]} episodes, {totals[1]} transitions (t42 bag info BAG for one)")
    return 1 if failed else 0


def _cmd_bag_import_t42(args: argparse.Namespace) -> int:
    from t42_transfer.data.bag import read_bag
    from t42_transfer.data.t42_real import import_t42_to_bag, quality_lines

    bag = import_t42_to_bag(existing_file(args.pickle), new_output(args.out))
    data = read_bag(bag)
    print(f"{args.pickle} -> {bag}: {len(data)} paths, {data.num_transitions} transitions, hand {data.hand!r}")
    print("flagged stretches: " + "; ".join(quality_lines(data)))
    return 0


def _cmd_bag_repair(args: argparse.Namespace) -> int:
    from t42_transfer.data.bag.repair import repair_bag

    report = repair_bag(existing_dir(args.bag))
    if not report.repaired:
        print(f"{report.path}: sound, left as it is ({report.message_count} messages)")
        return 0
    print(f"{report.path}: repaired ({'; '.join(report.problems)})")
    if not report.counts and not report.left_out:
        print("  it held nothing readable (its recorder stopped right after opening it): now an empty bag")
    if report.stopped:
        print(f"  salvaged up to where {report.stopped}")
    for topic, count in sorted(report.counts.items()):
        print(f"  {topic}: {count} messages")
    for line in report.left_out:
        print(f"  left out {line}")
    print(f"  originals kept as {', '.join(str(p) for p in report.originals)}")
    if report.left_out_messages:  # repaired, but not whole: a script must not take it for a full salvage
        print(f"t42: {report.left_out_messages} messages read could not be carried over; they are in the originals",
              file=sys.stderr)
        return 1
    return 0


def _remap_rule(text: str) -> str:
    """``OLD:=NEW``, both sides non-empty: a ROS remapping rule (passed to rclpy as ``--ros-args -r``)."""
    old, sep, new = text.partition(":=")
    if not sep or not old.strip() or not new.strip() or ":=" in new:
        raise argparse.ArgumentTypeError(f"a remapping is OLD:=NEW, got {text!r}")
    return text


def _cmd_bag_play(args: argparse.Namespace) -> int:
    from t42_transfer.nodes.player import PlayerParams
    from t42_transfer.ros.runner import keep_discovery_local, non_ros_args

    topics = tuple(args.topics) if args.topics else None
    # bad input: exit 2, before rclpy starts
    PlayerParams(existing_dir(args.bag), rate=args.rate, loop=args.loop, topics=topics, clock_hz=args.clock)
    ros_args = ["--ros-args", *(arg for rule in args.remap for arg in ("-r", rule))] if args.remap else []
    non_ros_args(ros_args, "--remap")  # a rule rcl cannot parse, named here (rclpy.init would raise an RCLError)
    keep_discovery_local()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from t42_transfer.nodes.player import BagPlayer

    overrides = [Parameter("bag", value=str(args.bag)), Parameter("rate", value=float(args.rate)),
                 Parameter("loop", value=args.loop), Parameter("clock_hz", value=float(args.clock)),
                 Parameter("start_paused", value=True)]
    if topics:
        overrides.append(Parameter("topics", value=list(topics)))
    context = rclpy.Context()
    rclpy.init(args=ros_args, context=context,
               signal_handler_options=SignalHandlerOptions.NO)
    # SIGTERM (a launch file, a supervisor) ends the play as Ctrl-C does: closed cleanly, DDS's shared memory freed
    main_thread = threading.current_thread() is threading.main_thread()  # (signals are the main thread's only)
    on_term = signal.signal(signal.SIGTERM, signal.default_int_handler) if main_thread else None
    try:
        player = BagPlayer(context=context, parameter_overrides=overrides)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(player)
        try:
            if not player.wait_for_subscribers(args.wait_subscribers, settle_s=0.5):
                unheard = sorted(pub.topic_name for pub in player.topic_publishers.values()
                                 if not pub.get_subscription_count())
                none_on = f" (none on {', '.join(unheard)})" if unheard else ""
                print(f"not every topic had a subscriber within {args.wait_subscribers} s{none_on}; playing anyway",
                      file=sys.stderr)
            player.resume()
            while not player.finished:
                executor.spin_once(timeout_sec=0.1)
            player.wait_for_acks(5.0)
        except KeyboardInterrupt:
            pass
        finally:
            player.close()
            executor.shutdown(timeout_sec=2.0)
            player.destroy_node()
    finally:
        rclpy.shutdown(context=context)
        if main_thread:
            signal.signal(signal.SIGTERM, on_term)
    print(f"{args.bag}: published {player.published} messages on {len(player.topic_publishers)} topics")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    bag = commands.add_parser("bag", help="rosbag2 bags").add_subparsers(dest="bag_command", metavar="ACTION")
    info = bag.add_parser("info", help="summarise a bag: topics, counts, episodes, metadata (a folder of bags: "
                                       "a line each)")
    info.add_argument("bag", type=Path, help="a bag, or a folder of bags (a recorder's out_dir): a line each and "
                                             "the sums; with --json a list of the bags' infos")
    info.add_argument("--json", action="store_true")
    info.add_argument("--verify", action="store_true",
                      help="check metadata.yaml's message counts, start time and duration against the data; "
                           "exit 1 on a mismatch")
    info.set_defaults(func=_cmd_bag_info)
    imp = bag.add_parser("import-t42", help="convert a public T42 test-path pickle into a bag")
    imp.add_argument("pickle", type=Path)
    imp.add_argument("out", type=Path, help="bag directory to create")
    imp.set_defaults(func=_cmd_bag_import_t42)
    rep = bag.add_parser("repair", help="rewrite a bag left by a killed recorder (its files and metadata.yaml kept "
                                        "as *.orig); exit 1 when a topic read could not be carried over")
    rep.add_argument("bag", type=Path, help="bag directory")
    rep.set_defaults(func=_cmd_bag_repair)
    play = bag.add_parser("play", help="publish a bag's messages on their topics over ROS 2 (rclpy), as ros2 bag play")
    play.add_argument("bag", type=Path, help="bag directory")
    play.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1.0)")
    play.add_argument("--topics", nargs="+", default=None, help="play only these topics (as named in the bag)")
    play.add_argument("--loop", action="store_true", help="play again from the start, until Ctrl-C")
    play.add_argument("--clock", type=float, nargs="?", const=40.0, default=0.0, metavar="HZ",
                      help="publish /clock from the bag's time at HZ (40 when HZ is not given), "
                           "as ros2 bag play --clock; for a suite under a namespace (t42 up --namespace /left) "
                           "add --remap /clock:=/left/clock")
    play.add_argument("--remap", "-m", nargs="+", type=_remap_rule, default=[], metavar="OLD:=NEW",
                      help="publish topic OLD (as named in the bag) on NEW, as ros2 bag play --remap; e.g. "
                           "/hand/object_pose:=/left/hand/object_pose")
    play.add_argument("--wait-subscribers", type=float_arg(0, 3600), default=2.0, metavar="S",
                      help="wait up to S seconds for every topic's subscriber to match before starting (default 2)")
    play.set_defaults(func=_cmd_bag_play)
