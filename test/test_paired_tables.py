"""scripts/paired_tables.py on hand-made results: the tables behind docs/evaluation.md."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tables():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("paired_tables", REPO / "scripts" / "paired_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(root: Path, name: str, scores: dict[str, list[list[float]]]) -> Path:
    """A run whose ``method`` scores ``scores[method][amount index][seed]`` steps at 4 mm (10 mm: twice that)."""
    rows = [{"method": m, "amount": a, "seed": s, "divergence_mean_4mm": v, "divergence_mean_10mm": 2 * v}
            for m, per_amount in scores.items() for a, seeds in zip((0.01, 0.1), per_amount, strict=True)
            for s, v in enumerate(seeds)]
    (root / name).mkdir()
    (root / name / "results.json").write_text(json.dumps({"config": {}, "rows": rows}))
    return root / name


def test_grid_gives_means_and_paired_differences(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    run = _run(tmp_path, "a", {"direct": [[10, 10], [10, 10]], "naive_finetune": [[12, 14], [11, 15]]})
    text = tables.grid_table([run], "divergence_mean_4mm", "direct")
    assert "| direct | 10.0 |" in text
    # differences 2, 4, 1, 5: mean 3, won 4 of 4
    assert "| naive_finetune | 13.0 (+3.0, " in text and "; 4/0) |" in text
    assert "| naive_finetune | 26.0 (+6.0, " in tables.grid_table([run], "divergence_mean_10mm", "direct")


def test_a_run_without_the_reference_shows_its_means_unpaired(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    full = _run(tmp_path, "full", {"direct": [[10, 10], [10, 10]], "recurrent_residual": [[12, 14], [11, 15]]})
    sweep = _run(tmp_path, "sweep", {"recurrent_residual": [[20, 22], [21, 25]]})  # one method, no direct
    text = tables.grid_table([full, sweep], "divergence_mean_4mm", "direct")
    assert "| recurrent_residual | 13.0 (+3.0, " in text and text.rstrip().endswith("| 22.0 |")
    assert "| direct | 10.0 | - |" in text


def test_a_variant_of_the_reference_method_is_paired_with_the_bases_cells(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    base = _run(tmp_path, "grid", {"direct": [[10, 10], [10, 10]], "recurrent_residual": [[12, 14], [11, 15]]})
    other = _run(tmp_path, "other_form", {"recurrent_residual": [[13, 16], [11, 19]]})  # +1, +2, 0, +4
    text = tables.variants_table(base, [other], "recurrent_residual")
    assert "| other_form, recurrent_residual (other_form) | 14.8 (+1.8, " in text and "; 3/0) |" in text


def test_winners_name_the_best_per_amount_and_its_lead(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    run = _run(tmp_path, "a", {"direct": [[10, 10], [30, 30]], "naive_finetune": [[12, 14], [20, 22]],
                               "l2_finetune": [[11, 11], [25, 27]]})
    row = tables.winners_table([run], "divergence_mean_4mm").splitlines()[-1]
    first, second = (cell.strip(" |") for cell in row.split(" | ")[1:3])
    assert first.startswith("naive (13), +2.0") and first.endswith("over L2")
    assert second.startswith("direct (30), +4.0") and second.endswith("over L2")


def test_variants_pair_each_run_with_the_base_reference(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    base = _run(tmp_path, "base", {"direct": [[10, 10], [10, 10]], "naive_finetune": [[50, 50], [50, 50]]})
    sweep = _run(tmp_path, "sweep", {"cumulative_residual": [[9, 9], [7, 7]]})
    text = tables.variants_table(base, [sweep], "direct")
    assert "| sweep, cumulative_residual | 8.0 (-2.0, " in text and "; 0/4) | 16.0 (-4.0, " in text
    assert "naive_finetune" not in text  # only the variant runs' methods are rows (and the base's hold-still)
    still = _run(tmp_path, "with_still", {"direct": [[10, 10], [10, 10]], "hold_still": [[4, 4], [4, 4]]})
    assert "| with_still, hold_still | 4.0 (-6.0, " in tables.variants_table(still, [sweep], "direct")


def test_ranking_orders_by_difference_and_marks_the_intervals(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    run = _run(tmp_path, "a", {"direct": [[10, 10], [10, 10]], "naive_finetune": [[12, 14], [11, 15]],
                               "cumulative_residual": [[7, 8], [6, 9]], "trajectory_finetune": [[12, 8], [9, 11]],
                               "hold_still": [[1, 1], [1, 1]]})
    row = tables.ranking_table([run], "direct").splitlines()[-1]
    four_mm = row.split(" | ")[1]
    # intervals exclude 0 for naive and cumres, but with 4 cells and 3 comparisons neither survives Holm (†)
    assert four_mm == "naive +3.0*†, trajectory +0.0, cumres -2.5!†"
    clear = _run(tmp_path, "b", {"direct": [[10, 10, 10], [10, 10, 10]], "naive_finetune": [[20, 21, 20], [21, 20, 21]],
                                 "cumulative_residual": [[7, 8, 7], [6, 7, 6]]})
    assert tables.ranking_table([clear], "direct").splitlines()[-1].split(" | ")[1] == "naive +10*, cumres -3.2!"


def test_tables_give_t_p_with_its_holm_adjustment_over_the_tables_methods(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from t42_transfer.evaluation.stats import holm, t_test_p

    run = _run(tmp_path, "a", {"direct": [[10, 10], [10, 10]], "naive_finetune": [[12, 14], [11, 15]],
                               "cumulative_residual": [[9, 11], [8, 10]]})
    text = tables.tables(run)
    raw = [t_test_p([2, 4, 1, 5]), t_test_p([-1, 1, -2, 0])]
    adjusted = holm(raw)
    assert "| naive_finetune | 4 | +3.0 | " in text and f"| {raw[0]:.2g} ({adjusted[0]:.2g}) |" in text
    assert f"| {raw[1]:.2g} ({adjusted[1]:.2g}) |" in text and adjusted[0] == 2 * raw[0]


def test_adjusted_gives_each_rankings_interval_p_and_holm_and_what_survives(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from t42_transfer.evaluation.stats import holm, t_test_p

    run = _run(tmp_path, "a", {"direct": [[10, 10], [10, 10]], "naive_finetune": [[12, 14], [11, 15]],
                               "cumulative_residual": [[9, 11], [8, 10]], "hold_still": [[1, 1], [1, 1]]})
    clear = _run(tmp_path, "b", {"direct": [[10, 10, 10], [10, 10, 10]],
                                 "naive_finetune": [[20, 21, 20], [21, 20, 21]]})
    lines = tables.adjusted_table([run, clear], "direct").splitlines()
    assert [line.split(" | ")[0] for line in lines[2:]] == ["| a, naive", "| a, cumres", "| b, naive"]  # no hold
    raw = [t_test_p([2, 4, 1, 5]), t_test_p([-1, 1, -2, 0])]
    adjusted = holm(raw)
    naive_4mm = lines[2].split(" | ")[2]
    # the interval excludes 0 (the ranking's *), but not after Holm over the two methods: it does not survive
    assert naive_4mm.startswith("+3.0 (+") and naive_4mm.endswith(f", {raw[0]:.2g} ({adjusted[0]:.2g}), no")
    assert lines[3].split(" | ")[1] == "4" and lines[3].split(" | ")[2].endswith(", -")  # cumres: interval over 0
    assert lines[4].split(" | ")[2].endswith(", yes")  # one method, six clear cells: survives


def test_crossovers_list_the_comparisons_whose_amounts_disagree_in_sign(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    run = _run(tmp_path, "a", {"direct": [[10, 10], [10, 10]], "trajectory_finetune": [[6, 7], [14, 15]],
                               "naive_finetune": [[12, 14], [11, 15]], "cumulative_residual": [[9.5, 10], [10.2, 10]]})
    lines = tables.crossovers_table([run], "direct").splitlines()[2:]
    # trajectory: -3.5 at the first amount, +4.5 at the second, at both thresholds; naive gains at both amounts;
    # cumres crosses by less than a step at 4 mm, and by -0.5 / +0.2 steps x 2 at 10 mm: under a step, left out
    assert [line.split(" | ")[0] for line in lines] == ["| a, 4 mm, trajectory", "| a, 10 mm, trajectory"]
    assert lines[0].split(" | ")[1] == "+0.5 (-6.9 to +7.9)"  # -4, -3, +4, +5: sd 4.65, t(3) 3.18
    assert lines[0].split(" | ")[2].startswith("0.01: -3.5 (") and "0.1: +4.5 (" in lines[0]


def test_means_give_each_methods_mean_per_amount_at_both_thresholds(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    run = _run(tmp_path, "a", {"direct": [[10, 12], [20, 21]], "naive_finetune": [[3, 4], [5, 8]]})
    lines = tables.means_table([run]).splitlines()
    assert lines[0] == "| run, method: 4 mm / 10 mm | 0.01 | 0.1 |"
    assert lines[2:] == ["| a, direct | 11 / 22 | 20 / 41 |", "| a, naive_finetune | 4 / 7 | 6 / 13 |"]


def test_sources_pair_within_each_source_and_pool_over_them(tables, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Three runs with other source models: direct differs per source, so only within-source pairs are right."""
    s0 = _run(tmp_path, "s0", {"direct": [[10, 10], [10, 10]], "naive_finetune": [[12, 14], [11, 15]]})  # +3
    s1 = _run(tmp_path, "s1", {"direct": [[50, 50], [50, 50]], "naive_finetune": [[49, 49], [49, 49]]})  # -1
    s2 = _run(tmp_path, "s2", {"direct": [[20, 20], [20, 20]], "naive_finetune": [[22, 22], [22, 22]]})  # +2
    text = tables.sources_table([s0, s1, s2], "direct")
    row = next(line for line in text.splitlines() if line.startswith("| naive_finetune |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1].startswith("+3.0 (") and cells[2].startswith("-1.0 (") and cells[3].startswith("+2.0 (")
    assert cells[4].startswith("12, +1.3,")  # 12 cells pooled: (4 * 3 - 4 * 1 + 4 * 2) / 12
    assert cells[5].startswith("+1.3 (") and cells[6] == "1 of 3"
    # Pairing across sources would mix direct's 10, 50 and 20: the pooled mean would still be +1.3, so check that a
    # source's own interval is its own: s1's differences are all -1, a zero-width interval.
    assert cells[2] == "-1.0 (-1.0 to -1.0)"
    assert "10 mm" in text and cells[0] == "naive_finetune"
