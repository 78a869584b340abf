"""The client side of the suite's actions in msg_adapters (what the demo sends and reads): Reach and Transfer goals,
feedback and results, each the inverse of what the servers build and read."""

from __future__ import annotations

import math

import numpy as np
import pytest
import t42_interfaces.action  # noqa: F401  (a broken interface build fails, never skips)

from msg_adapters.reach import reach_feedback, reach_goal, reach_outcome, reach_progress, reach_request, reach_result
from msg_adapters.transfer import (
    Scores,
    TransferOutcome,
    transfer_feedback,
    transfer_goal,
    transfer_outcome,
    transfer_progress,
    transfer_request,
    transfer_result,
)


def test_a_reach_goal_reads_back_as_the_planner_reads_it() -> None:
    goal = reach_goal(np.float32([12.5, -80.25]), 1_500_000_000, tolerance_mm=10.0, steps=30, replan_every=5)
    assert goal.target.header.frame_id == "t42_base" and (goal.target.point.x, goal.tolerance_m) == (0.0125, 0.01)
    request = reach_request(goal)
    assert request.xy_mm.tolist() == [12.5, -80.25] and request.stamp_ns == 1_500_000_000
    assert (request.tolerance_mm, request.steps, request.replan_every) == (10.0, 30, 5)
    defaults = reach_request(reach_goal([0.0, 0.0], 0))
    assert (defaults.tolerance_mm, defaults.steps, defaults.replan_every) == (0.0, 0, 0)  # the planner's own


def test_reach_feedback_and_result_read_back_in_mm() -> None:
    assert reach_progress(reach_feedback(7, 4.5, 2.0)) == (7, pytest.approx(4.5), pytest.approx(2.0))
    executed, predicted = np.float32([[0, 0], [1, 2], [3, 4]]), np.float32([[0, 0], [2, 2], [3, 3], [4, 4]])
    outcome = reach_outcome(reach_result("miss", "miss: far", 3.25, executed, 10, predicted, 20))
    assert (outcome.success, outcome.verdict, outcome.reason) == (False, "miss", "miss: far")
    assert outcome.final_error_mm == pytest.approx(3.25) and outcome.predicted_start_ns == 20
    assert np.array_equal(outcome.executed_mm, executed) and np.array_equal(outcome.predicted_mm, predicted)
    refused = reach_outcome(reach_result("refused", "no_model: none", None, np.zeros((0, 2)), 0, np.zeros((0, 2)), 0))
    assert refused.final_error_mm is None and refused.predicted_mm.shape == (0, 2) and not refused.success
    assert reach_outcome(reach_result("hit", "", 1.0, executed, 10, predicted, 20)).success


def test_a_transfer_goal_and_its_result_and_feedback_read_back() -> None:
    assert transfer_request(transfer_goal()) == transfer_request(transfer_goal("", []))
    request = transfer_request(transfer_goal("residual", ["/b/episode_000", "rel/episode_001"]))
    assert request.method == "residual" and request.bags == ("/b/episode_000", "rel/episode_001")
    assert request.problem is None and transfer_request(transfer_goal()).problem is None
    assert transfer_request(transfer_goal("", ["/b/e0", "  "])).problem.startswith("bags[1] is an empty path")
    outcome = TransferOutcome(True, "done", "/m/transferred_000.safetensors", Scores(50.0, 6.5), Scores(40.0, 20.0),
                              Scores(5.0, 400.0), (("l2_finetune", 50.0), ("residual", math.nan)),
                              (("/b/x", "missing"),))
    back = transfer_outcome(transfer_result(outcome))
    assert back.candidates[0] == ("l2_finetune", 50.0) and math.isnan(back.candidates[1][1])
    assert back == outcome.__class__(**{**outcome.__dict__, "candidates": back.candidates})
    progress = transfer_progress(transfer_feedback("training", {"phase": "L2 fine-tune", "epoch": 3, "epochs": 10,
                                                                "train_loss": 0.5}))
    assert progress[:4] == ("training: L2 fine-tune", 3, 10, 0.5) and math.isnan(progress.val_loss)
    assert transfer_progress(transfer_feedback("saving", {"epoch": 3})).epoch == 0  # outside training
