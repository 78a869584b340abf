"""The README's main job: the whole transfer story on simulated hands, as separate ROS 2 node processes.

1. **Source model**: random-action episodes of the simulated *source* hand go into
   a rosbag2 bag, and the paper's transition model is trained on it (cached in the
   output directory and reused while the demo's sizes stay the same).
2. **The suite** starts as separate rclpy processes on a private ROS domain (discovery
   kept on this machine), through the supervisor ``t42 up`` uses: the mock driver on the simulated *target* hand, the
   recorder, the transfer server and the planner.  The driver is the clock of the
   graph (``sim_time``, ``/clock``) and runs ``rate_factor`` times faster than real
   time; every other node runs with ``use_sim_time``.
3. **Target data through topics**: the explorer node (another process) resets the
   hand and sends random-action trajectories; it starts and stops the recorder,
   which writes one MCAP bag per episode and announces each closed bag on
   ``recorder/bag_closed``: the demo waits for the one the stop closed, not on files.
4. **Transfer**: one goal of the ``/t42/transfer`` action (the server's method, the
   bags closed since the last transfer); its feedback shows each epoch; the result
   names the model (with its held-out scores), which the planner loads when the
   server announces it on ``/t42/model_updated``.
5. **Peg-in-hole**: for each goal the hand is reset; the goal is a point the true
   target hand reaches from that grasp in ``n`` steps, at least twice the
   tolerance from the start and from where holding still would leave the object;
   it is sent to the planner as a ``/t42/reach`` action goal; the driver executes the
   planned ``JointTrajectory`` open loop, with the action's feedback each step and its
   result (the planner's own verdict, the measured and predicted paths); the rule of
   :func:`~t42_transfer.evaluation.peg_in_hole.verdict` decides success (completed,
   half way towards the goal at least, within the tolerance), and doing nothing
   is scored by the same rule on the same grasps.  The recorder records these
   episodes like any other.
6. **Second round**: ``/t42/transfer`` again, now with the executed plans among
   the episodes, then new goals of the same kind: does the suite improve with use?
   Each round's model is also scored on the same held-out target episodes
   (collected apart, never seen by the suite) beside the source model and the
   hold-still baseline.
7. **Report**: ``report.md``, ``demo.json`` and ``paths.png`` (planned vs executed
   paths) in the run directory; node logs in ``logs/``.
"""

from typing import Any

__all__ = ["run_demo"]


def __getattr__(name: str) -> Any:
    """``run_demo`` on first use: ``t42``'s parser reads the demo's settings without loading its story."""
    if name == "run_demo":
        from t42_transfer.demo.story import run_demo

        return run_demo
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
