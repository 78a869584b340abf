"""evaluation/report.py: the plain statements a run's report makes about the paper's claims, from its numbers."""

from __future__ import annotations

from t42_transfer.evaluation.report import findings


def _cell(divergence: float, lyapunov: float = -0.01) -> dict[str, tuple[float, float, int]]:
    return {"divergence_mean": (divergence, 1.0, 5), "lyapunov_mean": (lyapunov, 0.0, 5)}


def test_findings_state_each_claim_at_exactly_the_amounts_the_numbers_support() -> None:
    summary = {  # mean steps before divergence at two amounts of target data
        "direct": {0.01: _cell(50.0), 0.1: _cell(60.0)},
        "naive_finetune": {0.01: _cell(40.0), 0.1: _cell(70.0, lyapunov=0.002)},
        "cumulative_residual": {0.01: _cell(55.0), 0.1: _cell(65.0)},
        "trajectory_finetune": {0.01: _cell(45.0), 0.1: _cell(80.0)},
        "hold_still": {0.01: _cell(48.0, 0.0), 0.1: _cell(48.0, 0.0)},
    }
    lines = findings(summary, {"split": "fraction", "name": "hand-made"})
    assert lines[0] == ("At 0.01 (fraction of target data), the longest mean time before divergence is "
                        "cumulative_residual (55.0 steps), then direct (50.0); the shortest is naive_finetune (40.0).")
    assert "is trajectory_finetune (80.0 steps), then naive_finetune (70.0)" in lines[1]
    said = "\n".join(lines)
    assert "worse than no adaptation (direct) at 0.01 of the 2 amounts" in said
    assert "Cumulative residual has the longest time before divergence at 0.01 of the 2" in said
    assert "Trajectory fine-tuning beats naive fine-tuning at 0.01, 0.1 of the 2" in said
    assert "lasts 48.0 steps before divergence; methods that fall short of it: naive_finetune at 0.01; " \
           "trajectory_finetune at 0.01." in said
    assert "methods that exceed it at some amount: naive_finetune." in said  # (holding still's 0 is no method's)
