"""Paired statistics and success-rate intervals on hand-made examples with answers worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from t42_transfer.evaluation.stats import (
    EXACT_WILCOXON_MAX,
    bootstrap_interval,
    compare_methods,
    compare_paired,
    holm,
    matched_scores,
    one_per_draw,
    sign_test,
    spearman,
    student_t_cdf,
    student_t_quantile,
    t_interval,
    t_test_p,
    wilcoxon_signed_rank,
    wilson_interval,
)

T_975_DF4 = 2.7764451051977987  # Student t tables: the 97.5 % point with 4 degrees of freedom


def test_wilson_interval_by_hand():
    # 8 of 10 at 95 %: centre (0.8 + z^2/20) / (1 + z^2/10), half-width z sqrt(0.016 + z^2/400) / (1 + z^2/10).
    z = 1.959963984540054
    centre = (0.8 + z * z / 20) / (1 + z * z / 10)
    half = z * math.sqrt(0.8 * 0.2 / 10 + z * z / 400) / (1 + z * z / 10)
    assert wilson_interval(8, 10) == pytest.approx((centre - half, centre + half), abs=1e-12)
    assert wilson_interval(8, 10) == pytest.approx((0.4902, 0.9433), abs=1e-4)
    low, high = wilson_interval(0, 10)
    assert low == 0.0 and high == pytest.approx(z * z / 10 / (1 + z * z / 10), abs=1e-12)  # 0.2775
    assert wilson_interval(10, 10)[1] == 1.0
    assert wilson_interval(8, 10, confidence=0.5)[1] < wilson_interval(8, 10)[1]
    for bad in ((11, 10, 0.95), (1, 0, 0.95), (1, 10, 1.0)):
        with pytest.raises(ValueError):
            wilson_interval(*bad)


@pytest.mark.parametrize(
    ("df", "quantile"), [(1, 12.706204736174696), (4, T_975_DF4), (9, 2.2621571627409915), (29, 2.045229642132703)]
)
def test_student_t_quantiles_match_the_tables(df, quantile):
    assert student_t_quantile(0.975, df) == pytest.approx(quantile, rel=1e-10)
    assert student_t_quantile(0.025, df) == pytest.approx(-quantile, rel=1e-10)
    assert student_t_cdf(quantile, df) == pytest.approx(0.975, abs=1e-10)
    assert student_t_cdf(0.0, df) == 0.5
    # Cauchy (df 1) has a closed form: P(T <= t) = 1/2 + atan(t) / pi.
    assert student_t_cdf(3.0, 1) == pytest.approx(0.5 + math.atan(3.0) / math.pi, abs=1e-13)
    assert student_t_quantile(0.975, 10_000) == pytest.approx(1.959963984540054, abs=5e-4)


def test_t_interval_by_hand():
    # 1..5: mean 3, sd sqrt(2.5), so the 95 % half-width is t(4) * sqrt(2.5 / 5).
    half = T_975_DF4 * math.sqrt(0.5)
    assert t_interval([1, 2, 3, 4, 5]) == pytest.approx((3 - half, 3 + half), abs=1e-10)
    with pytest.raises(ValueError, match="at least 2"):
        t_interval([1.0])
    with pytest.raises(ValueError, match="finite"):
        t_interval([1.0, float("nan")])


def test_bootstrap_interval_by_hand():
    # Resampling [0, 1] twice gives means 0, 1/2, 1 with chances 1/4, 1/2, 1/4.
    assert bootstrap_interval([0.0, 1.0]) == (0.0, 1.0)
    assert bootstrap_interval([0.0, 1.0], confidence=0.4) == (0.5, 0.5)
    assert bootstrap_interval([2.5] * 7) == (2.5, 2.5)
    data = np.random.default_rng(1).normal(1.0, 2.0, 40)
    first = bootstrap_interval(data, seed=3)
    assert first == bootstrap_interval(data, seed=3) != bootstrap_interval(data, seed=4)
    # For 40 roughly normal numbers it agrees with the t interval to a few percent of its width.
    low, high = t_interval(data)
    assert abs(first[0] - low) < 0.1 * (high - low) and abs(first[1] - high) < 0.1 * (high - low)


def test_sign_test_by_hand():
    # 6 wins, 1 loss, 1 tie: p = 2 (C(7,0) + C(7,1)) / 2^7 = 0.125.
    assert sign_test([3, 1, 2, -1, 0, 5, 6, 7]) == (6, 1, 1, 0.125)
    assert sign_test([1, -1]) == (1, 1, 0, 1.0)
    assert sign_test([0, 0]) == (0, 0, 2, 1.0)


@pytest.mark.parametrize(
    ("differences", "w_plus", "p"),
    [
        # ranks 1, 2, 3, 4; W+ = 6; only W+ = 5 (2 of 16 patterns) is nearer the mean 5.
        ([1, 2, 3, -4], 6.0, 14 / 16),
        # all five positive: W+ = 15, as extreme as it gets on either side: 2 of 32.
        ([1, 2, 3, 4, 5], 15.0, 2 / 32),
        # |d| ties: ranks 2, 2, 2, 4; W+ = 8; W+ in {0, 2, 8, 10} for 8 of 16 patterns.
        ([1, 1, -1, 2], 8.0, 8 / 16),
        # zeros are left out: the same as [1, 1, -1, 2].
        ([1, 0, 1, -1, 0, 2], 8.0, 8 / 16),
    ],
)
def test_wilcoxon_signed_rank_by_hand(differences, w_plus, p):
    assert wilcoxon_signed_rank(differences) == pytest.approx((w_plus, p), abs=1e-12)


def test_paired_comparison_by_hand():
    a, b = [10, 12, 15, 11, 14], [8, 12, 11, 10, 9]  # differences 2, 0, 4, 1, 5
    result = compare_paired(a, b)
    half = T_975_DF4 * math.sqrt(4.3 / 5)  # the differences' variance is 17.2 / 4
    assert result.n == 5 and result.mean_difference == pytest.approx(2.4)
    assert (result.mean_a, result.mean_b) == pytest.approx((12.4, 10.0))
    assert result.t_interval == pytest.approx((2.4 - half, 2.4 + half), abs=1e-10)
    lo, hi = result.bootstrap_interval
    assert 0.0 <= lo < 2.4 < hi <= 5.0  # resampled means lie between the smallest and largest difference
    assert (result.wins, result.losses, result.ties) == (4, 0, 1)
    assert result.sign_p == pytest.approx(2 / 16)
    assert result.wilcoxon_p == pytest.approx(2 / 16)  # nonzero ranks all positive, n = 4
    with pytest.raises(ValueError, match="equal lengths"):
        compare_paired([1, 2, 3], [1, 2])


def _rows() -> list[dict]:
    """direct and naive on amounts 0.01, 0.1 and seeds 0-2; naive lacks (0.1, 2); a third method is ignored."""
    rows = []
    for amount, base in ((0.01, 10.0), (0.1, 20.0)):
        for seed in range(3):
            rows.append({"method": "direct", "amount": amount, "seed": seed, "divergence_mean": base + seed})
            if (amount, seed) != (0.1, 2):
                rows.append({"method": "naive", "amount": amount, "seed": seed,
                             "divergence_mean": base + seed + (1.0 if amount == 0.01 else 4.0 + seed)})
            rows.append({"method": "other", "amount": amount, "seed": seed, "divergence_mean": 0.0})
    return rows


def test_matched_scores_and_per_amount_comparisons():
    cells, naive, direct = matched_scores(_rows(), "divergence_mean", "naive", "direct")
    assert cells == [(0.01, 0), (0.01, 1), (0.01, 2), (0.1, 0), (0.1, 1)]
    np.testing.assert_array_equal(naive - direct, [1, 1, 1, 4, 5])
    by_amount = compare_methods(_rows(), "divergence_mean", "naive", "direct", by="amount")
    assert list(by_amount) == [0.01, 0.1]
    assert by_amount[0.01].mean_difference == 1.0 and by_amount[0.01].t_interval == (1.0, 1.0)
    assert by_amount[0.1].n == 2 and by_amount[0.1].mean_difference == 4.5
    assert compare_methods(_rows(), "divergence_mean", "naive", "direct")["all"].wins == 5
    duplicated = _rows() + [{"method": "naive", "amount": 0.01, "seed": 0, "divergence_mean": 1.0}]
    with pytest.raises(ValueError, match="match on more keys"):
        matched_scores(duplicated, "divergence_mean", "naive", "direct")
    with pytest.raises(ValueError, match="lacks"):
        matched_scores(_rows(), "position_mse_mean", "naive", "direct")
    with pytest.raises(ValueError, match="match keys"):
        compare_methods(_rows(), "divergence_mean", "naive", "direct", by="method")
    # A further key (e.g. the test-path kind) keeps cells apart.
    tagged = [dict(r, test_paths=kind) for kind in ("random", "sustained") for r in _rows()]
    cells, _, _ = matched_scores(tagged, "divergence_mean", "naive", "direct", match=("amount", "seed", "test_paths"))
    assert len(cells) == 10


def test_holm_by_hand():
    # sorted 0.01, 0.02, 0.03, 0.5 -> 4 x 0.01, 3 x 0.02, max(2 x 0.03, previous), 1 x 0.5; back in the given order
    assert holm([0.03, 0.5, 0.01, 0.02]) == pytest.approx([0.06, 0.5, 0.04, 0.06])
    assert holm([0.4, 0.3]) == pytest.approx([0.6, 0.6])  # step-down keeps the adjusted order monotone
    assert holm([0.9, 0.8, 0.7]) == [1.0, 1.0, 1.0] and holm([]) == []
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        holm([0.2, 1.5])


def test_t_test_p_by_hand():
    d = [1.0, 2.0, 3.0, 4.0, 5.0]  # mean 3, sd sqrt(2.5), t = 3 / sqrt(0.5) = 4.2426 with 4 df
    assert t_test_p(d) == pytest.approx(2 * (1 - student_t_cdf(3 / math.sqrt(0.5), 4)), rel=1e-12)
    assert 0.01 < t_test_p(d) < 0.02  # tables: t_{0.995, 4} = 4.604 > 4.2426 > t_{0.99, 4} = 3.747
    assert t_test_p([2.0, 2.0]) == 0.0 and t_test_p([0.0, 0.0, 0.0]) == 1.0
    assert compare_paired([3.0, 4.0, 6.0], [1.0, 1.0, 1.0]).t_p == pytest.approx(t_test_p([2.0, 3.0, 5.0]))


def test_agrees_with_scipy():
    scipy_stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(7)
    for n in (6, 15, 40):
        d = rng.normal(0.4, 1.0, n)
        assert wilcoxon_signed_rank(d)[1] == pytest.approx(scipy_stats.wilcoxon(d, method="exact").pvalue, rel=1e-9)
        assert t_test_p(d) == pytest.approx(scipy_stats.ttest_1samp(d, 0.0).pvalue, rel=1e-9)
        assert t_interval(d, 0.9) == pytest.approx(
            scipy_stats.t.interval(0.9, n - 1, loc=d.mean(), scale=scipy_stats.sem(d)), rel=1e-9)
    tied = np.round(rng.normal(0.3, 1.0, 12))  # ties and zeros: exact over every sign pattern
    exact = scipy_stats.wilcoxon(tied, method=scipy_stats.PermutationMethod(n_resamples=np.inf)).pvalue
    assert wilcoxon_signed_rank(tied)[1] == pytest.approx(exact, rel=1e-9)
    large = np.round(rng.normal(0.2, 1.0, EXACT_WILCOXON_MAX + 50), 1)  # normal approximation, tie-corrected
    approx = scipy_stats.wilcoxon(large, method="asymptotic", correction=False).pvalue
    assert wilcoxon_signed_rank(large)[1] == pytest.approx(approx, rel=1e-9)
    for df in (2, 7, 60):
        assert student_t_quantile(0.95, df) == pytest.approx(scipy_stats.t.ppf(0.95, df), rel=1e-10)


def test_seeds_that_drew_the_same_episodes_are_one_cell():
    rows = [{"method": m, "amount": 1, "seed": seed, "train_draw": draw, "score": score}
            for m, scores in (("a", (10.0, 14.0, 30.0)), ("b", (8.0, 8.0, 20.0)))
            for seed, draw, score in zip((0, 1, 2), ("x", "x", "y"), scores, strict=True)]
    merged = one_per_draw([*rows, {"method": "a", "amount": 1, "seed": 9, "score": 1.0}])  # an older run's row
    cells, a, b = matched_scores([r for r in merged if r["seed"] != 9], "score", "a", "b")
    assert cells == [(1, 0), (1, 2)] and a.tolist() == [12.0, 30.0] and b.tolist() == [8.0, 20.0]
    assert [r["draws_merged"] for r in merged if r["seed"] == 0] == [2, 2]
    assert {"method": "a", "amount": 1, "seed": 9, "score": 1.0} in merged


def test_spearman_ranks_with_ties_and_agrees_with_scipy():
    rho, p = spearman([1, 2, 3, 4, 5], [10, 20, 30, 40, 1000])
    assert rho == pytest.approx(1.0) and p < 1e-6  # monotone, whatever the scale
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1])[0] == pytest.approx(-1.0)
    scipy_stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(4)
    for n in (5, 12, 40):
        x, y = rng.normal(size=n), rng.normal(size=n)
        y[: n // 3] = x[: n // 3]  # some agreement
        x[1] = x[0]  # a tie
        expected = scipy_stats.spearmanr(x, y)
        got = spearman(x, y)
        assert got[0] == pytest.approx(expected.statistic, abs=1e-12)
        assert got[1] == pytest.approx(expected.pvalue, rel=1e-6)
    with pytest.raises(ValueError, match="at least 3"):
        spearman([1, 2], [3, 4])
    with pytest.raises(ValueError, match="constant"):
        spearman([1, 1, 1], [1, 2, 3])
