"""The paper authors' own saved models on hand A's test paths: every file, both dropout modes, both thresholds.

``run`` scores every authors' file in MODELS_DIR (``../shared/data/authors_models``: hand B's source,
hand A's own models and the four B -> A transfer families, eight amounts x five repeats) on hand
A's cyl35 paths (default 0-3), open loop from each path's first true state with its recorded
actions (:func:`t42_transfer.evaluation.evaluate.score_model`, the paper's definition unless
``--definition authors``), with dropout off (the deterministic model) and with dropout on
(``--draws`` K draws, the mean over them; seeded by ``--seed``).  The authors saved their models in
training mode and never called ``.eval()``: their published numbers were taken with dropout on.

Hand A's actions are negated inside every imported model (``negate_actions``: the authors negate
A's actions for every model run on A), the data are A's as recorded.  The cumulative residual is
scored at every rollout setting of ``--alphas`` x ``--gammas`` (the files store neither gamma nor
a reason to prefer one alpha; 0.993 is the authors' code's gamma, 0.9997 with alpha 0.3 the
paper's text); the recurrent residual at ``--recurrent-alphas``.

One JSON per group (``direct``, ``new_model``, ``naive_finetune``, ``trajectory_finetune``,
``recurrent_residual_a<alpha>``, ``cumulative_residual_a<alpha>_g<gamma>``) plus ``hold_still``
in OUT (default docs/experiments/authors_models); each row carries its file's sha256, the 1-minute load
average when it was scored and its seconds.  A row already in OUT with the same settings is kept
(an interrupted run resumes).  ``table`` prints the markdown tables from OUT (mean and sample
standard deviation over the five repeats per family x amount, each mode and threshold, beside
hold-still and B's model used directly).

    nice -n 10 .venv/bin/python scripts/authors_rows.py run          # all files (~25 min on 2 busy cores)
    .venv/bin/python scripts/authors_rows.py table > /tmp/tables.md
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

MODELS_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "authors_models"
OUT = Path("docs/experiments/authors_models")
NAME = re.compile(r"(?:real_(?P<hand>[AB])|transferB2A_(?P<method>[a-z_]+?))_heldout(?P<h>[0-9.]+)_(?P<r>[0-9]+)\.pkl")
GROUPS = {"real_B": "direct", "real_A": "new_model", "retrain_naive": "naive_finetune",
          "retrain": "trajectory_finetune", "traj_transfer_timeless": "cumulative_residual",
          "traj_transfer_timeless_recurrent": "recurrent_residual"}
LABELS = {"naive_finetune": "naive fine-tuning", "trajectory_finetune": "trajectory fine-tuning",
          "new_model": "A's own model (new)", "direct": "B used directly"}
KEYS = ("divergence_mean_4mm", "divergence_mean_10mm", "position_mse_mean")


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _write(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(tmp, path)


def _group(base: str, alpha: float | None, gamma: float | None) -> str:
    if base == "cumulative_residual":
        return f"{base}_a{alpha:g}_g{gamma:g}"
    if base == "recurrent_residual":
        return f"{base}_a{alpha:g}"
    return base


def _jobs(args: argparse.Namespace) -> list[tuple[str, Path, dict[str, Any], dict[str, float]]]:
    jobs = []
    for path in sorted(args.models_dir.glob("*.pkl")):
        match = NAME.fullmatch(path.name)
        if match is None:
            continue
        base = GROUPS[f"real_{match['hand']}" if match["hand"] else match["method"]]
        info = {"file": path.name, "heldout": float(match["h"]), "repeat": int(match["r"])}
        if base == "cumulative_residual":
            settings = [{"alpha": a, "gamma": g} for a in args.alphas for g in args.gammas]
        elif base == "recurrent_residual":
            settings = [{"alpha": a} for a in args.recurrent_alphas]
        else:
            settings = [{}]
        for kw in settings:
            jobs.append((_group(base, kw.get("alpha"), kw.get("gamma")), path, info, kw))
    priority = ["direct", "naive_finetune", "cumulative_residual", "recurrent_residual", "trajectory_finetune",
                "new_model"]
    # repeat by repeat, so that a run cut short still covers every family and amount
    return sorted(jobs, key=lambda j: (j[2]["repeat"], next(i for i, p in enumerate(priority) if j[0].startswith(p)),
                                       j[2]["heldout"], j[0]))


def run(args: argparse.Namespace) -> int:
    import torch

    from t42_transfer.evaluation.evaluate import score_model
    from t42_transfer.evaluation.experiment import load_spec
    from t42_transfer.evaluation.experiment_config import parse_data_spec
    from t42_transfer.models.authors import import_authors_model
    from t42_transfer.models.baselines import HoldStill

    torch.set_num_threads(args.threads)
    spec = parse_data_spec("{real: A}", "data")
    data = load_spec(spec, args.cache).data
    episodes = data.subset(args.paths)
    args.out.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    meta = {"data": "{real: A} (hand A's cyl35 paths as recorded; actions negated inside each model)",
            "paths": list(args.paths), "steps": episodes.num_transitions, "definition": args.definition,
            "dropout_draws": args.draws, "seed": args.seed, "torch_threads": args.threads, "commit": commit,
            "command": "scripts/authors_rows.py " + " ".join(sys.argv[2:])}
    options = {"definition": args.definition, "indices": args.paths}
    docs: dict[str, dict[str, Any]] = {}

    def doc(group: str) -> dict[str, Any]:
        if group not in docs:
            file = args.out / f"{group}.json"
            docs[group] = json.loads(file.read_text()) if file.exists() else {"meta": meta, "rows": []}
        return docs[group]

    hold_file = args.out / "hold_still.json"
    if not hold_file.exists():
        started = time.perf_counter()
        hold = score_model(HoldStill(), episodes, None, **options)
        _write(hold_file, {"meta": meta, "scores": hold.as_dict(), "load_1min": _load(),
                           "seconds": round(time.perf_counter() - started, 2)})
    jobs = [j for j in _jobs(args) if args.only is None or re.search(args.only, j[1].name)]
    for n, (group, path, info, kw) in enumerate(jobs, 1):
        rows = doc(group)["rows"]
        same = {"file": path.name, **kw, "definition": args.definition, "paths": list(args.paths),
                "dropout_draws": args.draws, "seed": args.seed}
        if any(all(r.get(k) == v for k, v in same.items()) for r in rows):
            continue
        started = time.perf_counter()
        model = import_authors_model(path, negate_actions=True, **kw)[0].model
        off = score_model(model, episodes, path.name, **options)
        on = score_model(model, episodes, path.name, dropout_draws=args.draws, seed=args.seed, **options)
        row = {**info, **same, "sha256": _sha256(path), "dropout_off": off.as_dict(), "dropout_on": on.as_dict(),
               "load_1min": _load(), "seconds": round(time.perf_counter() - started, 2),
               "at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
        rows.append(row)
        _write(args.out / f"{group}.json", docs[group])
        print(f"[{n}/{len(jobs)}] {group} {path.name}: 4 mm off {off.divergence_mean_4mm:.2f} on "
              f"{on.divergence_mean_4mm:.2f} ({row['seconds']} s, load {row['load_1min']})", flush=True)
    return 0


def _stats(values: list[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.1f}"
    return f"{statistics.fmean(values):.1f} ± {statistics.stdev(values):.1f}"


def table(args: argparse.Namespace) -> int:
    groups = {p.stem: json.loads(p.read_text()) for p in sorted(args.out.glob("*.json")) if p.stem != "hold_still"}
    hold = json.loads((args.out / "hold_still.json").read_text())["scores"]
    direct = groups.pop("direct")["rows"][0]
    new_full = [r for r in groups.get("new_model", {"rows": []})["rows"] if r["heldout"] == 0.1]
    order = ["naive_finetune", "trajectory_finetune", "new_model"]
    order += sorted(g for g in groups if g.startswith("cumulative_residual"))
    order += sorted(g for g in groups if g.startswith("recurrent_residual"))
    order = [g for g in order if g in groups]
    amounts = sorted({r["heldout"] for g in order for r in groups[g]["rows"]} - {0.1})
    metrics = [("divergence_mean_4mm", "4 mm"), ("divergence_mean_10mm", "10 mm")]
    if args.mse:
        metrics.append(("position_mse_mean", "position MSE (mm²)"))
    loads = [r["load_1min"] for g in groups.values() for r in g["rows"]]
    meta = next(iter(groups.values()))["meta"]
    print(f"Hand A paths {','.join(map(str, meta['paths']))} ({meta['steps']} steps), {meta['definition']} "
          f"definition; dropout on = mean of {meta['dropout_draws']} draws (seed {meta['seed']}); "
          f"mean ± sample sd over the repeats; load average (1 min) while scoring {min(loads):.1f}-{max(loads):.1f}.")
    for key, name in metrics:
        for mode in ("dropout_off", "dropout_on"):
            print(f"\n**{name}, {mode.replace('_', ' ')}** (columns: hand A's random-action training data kept)\n")
            print("| model | " + " | ".join(f"{100 * (1 - h):.1f} %" for h in amounts) + " |")
            print("|---" * (len(amounts) + 1) + "|")
            print(f"| hold still | {hold[key]:.1f} (every amount) |" + " |" * (len(amounts) - 1))
            print(f"| B used directly | {direct[mode][key]:.1f} (every amount) |" + " |" * (len(amounts) - 1))
            if new_full:
                print(f"| A's own model, 90 % of A's data | {new_full[0][mode][key]:.1f} |" + " |" * (len(amounts) - 1))
            for g in order:
                cells = []
                for h in amounts:
                    values = [r[mode][key] for r in groups[g]["rows"] if r["heldout"] == h]
                    cells.append((_stats(values) + ("" if len(values) == 5 else f" (n={len(values)})"))
                                 if values else "-")
                print(f"| {_name(g)} | " + " | ".join(cells) + " |")
    print("\n**Summary**: per mode and threshold, the files (family x amount x repeat) that outlast B used "
          "directly and hold still, and the longest-lasting model by its mean over the repeats at each amount\n")
    print("| mode, threshold | " + " | ".join(_name(g) for g in order) + " | longest per amount (10 % ... 0.3 %) |")
    print("|---" * (len(order) + 2) + "|")
    for mode in ("dropout_off", "dropout_on"):
        for key, name in metrics[:2]:
            counts = []
            for g in order:
                rows = [r for r in groups[g]["rows"] if r["heldout"] != 0.1]
                beat_direct = sum(r[mode][key] > direct[mode][key] for r in rows)
                beat_hold = sum(r[mode][key] > hold[key] for r in rows)
                counts.append(f"{beat_direct} / {beat_hold} of {len(rows)}")
            best = []
            for h in amounts:
                means = {g: statistics.fmean(v) for g in order
                         if (v := [r[mode][key] for r in groups[g]["rows"] if r["heldout"] == h])}
                top = max(means, key=means.get)
                best.append("direct" if direct[mode][key] >= means[top] else _name(top))
            print(f"| {mode.replace('_', ' ')}, {name} | " + " | ".join(counts) + " | " + "; ".join(best) + " |")
    return 0


def _name(group: str) -> str:
    match = re.fullmatch(r"cumulative_residual_a([0-9.]+)_g([0-9.]+)", group)
    if match:
        return f"cum. res. α {match[1]} γ {match[2]}"
    match = re.fullmatch(r"recurrent_residual_a([0-9.]+)", group)
    if match:
        return f"rec. res. α {match[1]}"
    return LABELS.get(group, group)


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("command", choices=("run", "table"))
    parser.add_argument("--models-dir", type=Path, default=MODELS_DIR)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--cache", type=Path, default=Path("runs") / "data")
    parser.add_argument("--paths", type=lambda s: tuple(int(x) for x in s.split(",")), default=(0, 1, 2, 3))
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--definition", choices=("paper", "authors"), default="paper")
    parser.add_argument("--alphas", type=_floats, default=[1.0, 0.3], help="cumulative residual (default 1,0.3)")
    parser.add_argument("--gammas", type=_floats, default=[0.9997, 0.993, 0.97],
                        help="cumulative residual (default 0.9997,0.993,0.97)")
    parser.add_argument("--recurrent-alphas", type=_floats, default=[1.0, 0.3],
                        help="recurrent residual (default 1,0.3)")
    parser.add_argument("--only", default=None, metavar="REGEX", help="only the files whose names match")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--mse", action="store_true", help="table: position MSE too")
    args = parser.parse_args(argv)
    return run(args) if args.command == "run" else table(args)


if __name__ == "__main__":
    sys.exit(main())
