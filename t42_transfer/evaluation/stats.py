"""Statistics for judging methods: paired differences over matched cells, and intervals for success rates.

Two methods run on the same cells (same amount of target data, seed and test
paths) are compared by the differences cell by cell, which removes what the cells
share (an easy split, a lucky seed).  :func:`compare_paired` reports the mean
difference with a Student t interval and a percentile bootstrap interval (fixed
seed), how many cells each method wins, and two-sided p-values of the sign test
and of Wilcoxon's signed-rank test (exact for up to :data:`EXACT_WILCOXON_MAX`
non-zero differences, ties included; normal approximation beyond).  Everything is
plain numpy and the standard library: scipy is not a runtime dependency.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np

MATCH_KEYS = ("amount", "seed")
"""What makes two result rows the same cell by default (an experiment's rows share their test paths per seed)."""
EXACT_WILCOXON_MAX = 200
BOOTSTRAP_RESAMPLES = 10_000


def _check_confidence(confidence: float) -> float:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return confidence


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a success rate: sound at 0 or n successes and for small n, unlike ``p +- z se``."""
    if n <= 0 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n > 0, got {successes} of {n}")
    z = NormalDist().inv_cdf(0.5 + _check_confidence(confidence) / 2)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # At 0 or n successes the bound is exactly 0 or 1; rounding would leave ~1e-17.
    return (0.0 if successes == 0 else max(0.0, centre - half)), (1.0 if successes == n else min(1.0, centre + half))


# ------------------------------------------------------------------ Student t


def _betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta ``I_x(a, b)`` by its continued fraction (modified Lentz), to ~1e-15."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):  # the fraction converges fast only below the mean: use the symmetry
        return 1.0 - _betainc(b, a, 1.0 - x)
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    f = d
    for m in range(1, 10_000):
        for numerator in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                          -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + numerator * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + numerator / c
            c = c if abs(c) > tiny else tiny
            f *= c * d
        if abs(c * d - 1.0) < 1e-16:
            break
    return math.exp(log_front) * f / a


def student_t_cdf(t: float, df: float) -> float:
    """P(T <= t) for Student's t with ``df`` degrees of freedom."""
    if df <= 0:
        raise ValueError(f"df must be positive, got {df!r}")
    tail = 0.5 * _betainc(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def student_t_quantile(p: float, df: float) -> float:
    """The ``p`` quantile of Student's t (bisection on :func:`student_t_cdf`, to 1e-12 relative)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"p must be in (0, 1), got {p!r}")
    if p < 0.5:
        return -student_t_quantile(1.0 - p, df)
    low, high = 0.0, 1.0
    while student_t_cdf(high, df) < p:
        low, high = high, 2.0 * high
    for _ in range(200):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if student_t_cdf(mid, df) < p else (low, mid)
        if high - low <= 1e-12 * high:
            break
    return 0.5 * (low + high)


def t_interval(differences: Sequence[float] | np.ndarray, confidence: float = 0.95) -> tuple[float, float]:
    """Student t interval of the mean: ``mean +- t_{(1+c)/2, n-1} * sd / sqrt(n)`` (needs n >= 2)."""
    d = _finite(differences, "differences")
    if len(d) < 2:
        raise ValueError(f"a t interval needs at least 2 differences, got {len(d)}")
    half = student_t_quantile(0.5 + _check_confidence(confidence) / 2, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d))
    return float(d.mean() - half), float(d.mean() + half)


def t_test_p(differences: Sequence[float] | np.ndarray) -> float:
    """Two-sided p of the paired t test that the mean difference is 0 (n >= 2; 1.0 for all-equal differences
    of mean 0, 0.0 for all-equal non-zero ones)."""
    d = _finite(differences, "differences")
    if len(d) < 2:
        raise ValueError(f"a t test needs at least 2 differences, got {len(d)}")
    sd = d.std(ddof=1)
    if sd == 0:
        return 1.0 if d.mean() == 0 else 0.0
    t = abs(d.mean()) / (sd / math.sqrt(len(d)))
    return min(1.0, 2.0 * (1.0 - student_t_cdf(t, len(d) - 1)))


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm-adjusted p-values (step-down; monotone in the raw order; capped at 1), in the order given: a family's
    conclusion at level alpha survives where its adjusted p is below alpha."""
    p = _finite(p_values, "p_values")
    if ((p < 0) | (p > 1)).any():
        raise ValueError("p-values must lie in [0, 1]")
    adjusted, running = np.empty_like(p), 0.0
    for rank, i in enumerate(np.argsort(p, kind="stable")):
        running = max(running, min(1.0, (len(p) - rank) * p[i]))
        adjusted[i] = running
    return adjusted.tolist()


def bootstrap_interval(
    differences: Sequence[float] | np.ndarray,
    confidence: float = 0.95,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean: the same numbers for the same ``seed``."""
    d = _finite(differences, "differences")
    if len(d) < 1 or resamples < 1:
        raise ValueError(f"need differences and resamples >= 1, got {len(d)} and {resamples}")
    tail = (1.0 - _check_confidence(confidence)) / 2
    means = d[np.random.default_rng(seed).integers(len(d), size=(resamples, len(d)))].mean(axis=1)
    low, high = np.quantile(means, [tail, 1.0 - tail])
    return float(low), float(high)


# ------------------------------------------------------------------ rank tests


def sign_test(differences: Sequence[float] | np.ndarray) -> tuple[int, int, int, float]:
    """``(wins, losses, ties, p)``: positive, negative and zero differences and the exact two-sided
    binomial p-value of wins against losses (ties left out)."""
    d = _finite(differences, "differences")
    wins, losses = int(np.sum(d > 0)), int(np.sum(d < 0))
    n, k = wins + losses, min(wins, losses)
    if n == 0:
        return wins, losses, len(d), 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return wins, losses, len(d) - n, min(1.0, 2.0 * tail)


def _ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, tied values sharing their mean rank."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    sorted_values = values[order]
    start = 0
    for end in range(1, len(values) + 1):
        if end == len(values) or sorted_values[end] != sorted_values[start]:
            ranks[order[start:end]] = 0.5 * (start + 1 + end)
            start = end
    return ranks


def spearman(x: Sequence[float] | np.ndarray, y: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """Spearman's rank correlation of paired values and its two-sided p (the t approximation, n - 2 degrees of
    freedom); ties share their mean rank.  ValueError below 3 pairs or for a constant side (no ranking)."""
    a, b = _finite(x, "x"), _finite(y, "y")
    if len(a) != len(b) or len(a) < 3:
        raise ValueError(f"need at least 3 pairs of equal length, got {len(a)} and {len(b)}")
    ra, rb = _ranks(a), _ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        raise ValueError("a constant side has no ranking to correlate")
    rho = float(np.clip(np.corrcoef(ra, rb)[0, 1], -1.0, 1.0))
    if 1.0 - rho * rho < 1e-15:  # a perfect ranking, up to rounding
        return rho, 0.0
    t = abs(rho) * math.sqrt((len(a) - 2) / (1.0 - rho * rho))
    return rho, min(1.0, 2.0 * (1.0 - student_t_cdf(t, len(a) - 2)))


def wilcoxon_signed_rank(differences: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """``(W+, p)``: the sum of the ranks of |d| over positive ``d`` and its two-sided p-value.

    Zero differences are left out (Wilcoxon's convention).  Up to
    :data:`EXACT_WILCOXON_MAX` non-zero differences the p-value is exact: every sign
    pattern is equally likely under the null, ties keep their mean ranks, and the
    distribution of W+ is counted by dynamic programming over doubled (integer)
    ranks.  Beyond, the normal approximation with the tie-corrected variance.
    """
    d = _finite(differences, "differences")
    d = d[d != 0]
    n = len(d)
    if n == 0:
        return 0.0, 1.0
    ranks = _ranks(np.abs(d))
    w_plus = float(ranks[d > 0].sum())
    mean = n * (n + 1) / 4.0
    if n <= EXACT_WILCOXON_MAX:
        doubled = np.rint(2 * ranks).astype(np.int64)
        counts = np.zeros(int(doubled.sum()) + 1)
        counts[0] = 1.0
        for r in doubled:  # each rank joins W+ or not, with probability 1/2
            counts[r:] = 0.5 * (counts[r:] + counts[:-r])
            counts[:r] *= 0.5
        # Two-sided: every W+ at least as far from its mean (n(n+1)/4, doubled: n(n+1)/2) as the observed one.
        far = abs(2 * w_plus - 2 * mean)
        p = float(counts[np.abs(np.arange(len(counts)) - 2 * mean) >= far - 1e-9].sum())
        return w_plus, min(1.0, p)
    _, tie_counts = np.unique(ranks, return_counts=True)
    variance = n * (n + 1) * (2 * n + 1) / 24.0 - float(np.sum(tie_counts**3 - tie_counts)) / 48.0
    z = abs(w_plus - mean) / math.sqrt(variance)
    return w_plus, min(1.0, 2.0 * (1.0 - NormalDist().cdf(z)))


# ------------------------------------------------------------------ paired comparisons


@dataclass(frozen=True)
class PairedComparison:
    """Method ``a`` against method ``b`` over matched cells, differences ``a - b``."""

    n: int
    mean_a: float
    mean_b: float
    mean_difference: float
    t_interval: tuple[float, float]
    bootstrap_interval: tuple[float, float]
    wins: int
    """Cells where ``a`` scores higher (better for divergence time, worse for an error)."""
    losses: int
    ties: int
    sign_p: float
    wilcoxon_p: float
    t_p: float
    """Two-sided paired t-test p (the test behind ``t_interval``); adjust a family of them with :func:`holm`."""
    confidence: float


def compare_paired(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    confidence: float = 0.95,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = 0,
) -> PairedComparison:
    """Paired comparison of two methods' scores on the same cells, ``a[i]`` beside ``b[i]`` (n >= 2)."""
    a, b = _finite(a, "a"), _finite(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"paired scores need equal lengths, got {len(a)} and {len(b)}")
    d = a - b
    wins, losses, ties, sign_p = sign_test(d)
    return PairedComparison(
        n=len(d), mean_a=float(a.mean()), mean_b=float(b.mean()), mean_difference=float(d.mean()),
        t_interval=t_interval(d, confidence), bootstrap_interval=bootstrap_interval(d, confidence, resamples, seed),
        wins=wins, losses=losses, ties=ties, sign_p=sign_p, wilcoxon_p=wilcoxon_signed_rank(d)[1], t_p=t_test_p(d),
        confidence=confidence,
    )


def matched_scores(
    rows: Iterable[Mapping[str, Any]],
    metric: str,
    method: str,
    baseline: str,
    match: Sequence[str] = MATCH_KEYS,
) -> tuple[list[tuple[Hashable, ...]], np.ndarray, np.ndarray]:
    """``(cells, method's scores, baseline's scores)`` over the cells both methods have, in cell order.

    Rows are result rows (``method``, the ``match`` keys, ``metric``), e.g. an
    experiment's ``results.json`` rows; a cell one method lacks is left out, and a
    cell a method has twice is refused (the match keys are missing one).
    """
    scores: dict[str, dict[tuple[Hashable, ...], float]] = {method: {}, baseline: {}}
    for row in rows:
        if row.get("method") not in scores:
            continue
        missing = [k for k in (*match, metric) if k not in row]
        if missing:
            raise ValueError(f"a {row['method']} row lacks {missing}")
        cell = tuple(row[k] for k in match)
        if cell in scores[row["method"]]:
            raise ValueError(f"two {row['method']} rows share {dict(zip(match, cell, strict=True))}: "
                             "match on more keys")
        scores[row["method"]][cell] = float(row[metric])
    cells = sorted(set(scores[method]) & set(scores[baseline]), key=repr)
    return (cells, np.array([scores[method][c] for c in cells]), np.array([scores[baseline][c] for c in cells]))


def one_per_draw(rows: Iterable[Mapping[str, Any]], key: str = "train_draw") -> list[dict[str, Any]]:
    """``rows`` with the cells that drew the same training data merged: seeds of one method and amount whose rows
    carry the same ``key`` are one cell (their numbers averaged, the smallest seed kept), not several, so a paired
    interval does not count one draw twice.  Rows without ``key`` (older runs) are kept as they are."""
    merged: dict[tuple[Any, ...], list[Mapping[str, Any]]] = {}
    out: list[dict[str, Any]] = []
    for row in rows:
        if key not in row:
            out.append(dict(row))
            continue
        merged.setdefault((row["method"], row.get("amount"), row[key]), []).append(row)
    for group in merged.values():
        first = dict(min(group, key=lambda r: r.get("seed", 0)))
        for name, value in first.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool) and name not in ("seed", "amount"):
                first[name] = sum(r[name] for r in group) / len(group)
        first["draws_merged"] = len(group)
        out.append(first)
    return out


def compare_methods(rows: Iterable[Mapping[str, Any]], metric: str, method: str, baseline: str, *,
                    match: Sequence[str] = MATCH_KEYS, by: str | None = None,
                    **options: Any) -> dict[Hashable, PairedComparison]:
    """:func:`compare_paired` of ``method`` against ``baseline`` on ``metric``: all matched cells together
    (key ``"all"``), or one comparison per value of the match key ``by`` (e.g. per amount)."""
    cells, a, b = matched_scores(rows, metric, method, baseline, match)
    if by is None:
        return {"all": compare_paired(a, b, **options)}
    if by not in match:
        raise ValueError(f"by must be one of the match keys {tuple(match)}, got {by!r}")
    column = [c[list(match).index(by)] for c in cells]
    groups = sorted(set(column), key=lambda v: (isinstance(v, str), v))
    picks = {g: np.array([v == g for v in column]) for g in groups}
    return {g: compare_paired(a[m], b[m], **options) for g, m in picks.items()}


def _finite(values: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite numbers")
    return array
