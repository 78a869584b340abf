"""A plan on disk: JSON (everything), CSV (one row per step, for spreadsheets and drivers), PNG (the predicted path)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from t42_transfer.conventions import STATE_NAMES
from t42_transfer.planning.planner import Plan
from t42_transfer.planning.workspace import Workspace


def write_plan(plan: Plan, out: Path, workspace: Workspace, info: dict[str, Any] | None = None) -> list[Path]:
    """Write ``plan.json``, ``plan.csv`` and ``plan.png`` into ``out``; returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "plan.json", out / "plan.csv", out / "plan.png"]
    payload = {**(info or {}), "workspace": workspace.to_dict(), "plan": plan.to_dict()}
    files[0].write_text(json.dumps(payload, indent=2) + "\n")
    with files[1].open("w", newline="") as f:
        writer = csv.writer(f)
        # Row k: the action applied at step k and the state predicted after it; row 0 is the start.
        writer.writerow(["step", "action1", "action2", *(f"predicted_{n}" for n in STATE_NAMES)])
        for k, state in enumerate(plan.predicted):
            action = plan.actions[k - 1] if k else (np.nan, np.nan)
            writer.writerow([k, *("" if np.isnan(v) else f"{v:.6g}" for v in action), *(f"{v:.6g}" for v in state)])
    plot_plan(plan, workspace, files[2])
    return files


def plot_plan(plan: Plan, workspace: Workspace, path: Path) -> Path:
    """The predicted object path from the start towards the goal, inside the workspace outline."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    xy, goal = plan.predicted[:, :2], plan.goal
    fig, ax = plt.subplots(figsize=(5.0, 4.5))
    _outline(ax, workspace, np.vstack([xy, goal[None]]))
    ax.plot(xy[:, 0], xy[:, 1], "-", color="C0", lw=1.2, label=f"predicted ({len(plan.actions)} steps)")
    ax.plot(*xy[0], "o", color="C0", label="start")
    ax.plot(*goal, "x", color="C3", ms=9, mew=2, label="goal")
    title = "plan ok" if plan.ok else f"plan not ok: {plan.status}"
    if np.isfinite(plan.error_mm):
        title += f", predicted error {plan.error_mm:.1f} mm"
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7)
    return save(fig, path)


def _outline(ax: Any, workspace: Workspace, points: np.ndarray) -> None:
    """The workspace boundary as the 0.5 contour of its indicator on a grid covering it and ``points``."""
    x_min, x_max, y_min, y_max = workspace.bounds()
    low = np.minimum(points.min(0), (x_min, y_min)) - 5.0
    high = np.maximum(points.max(0), (x_max, y_max)) + 5.0
    gx, gy = np.meshgrid(np.linspace(low[0], high[0], 200), np.linspace(low[1], high[1], 200))
    inside = workspace.contains_xy(torch.as_tensor(np.stack([gx, gy], -1), dtype=torch.float64)).numpy()
    if inside.any() and not inside.all():
        ax.contour(gx, gy, inside.astype(float), levels=[0.5], colors="0.5", linestyles="--", linewidths=0.8)
        ax.plot([], [], "--", color="0.5", lw=0.8, label="trained workspace")
