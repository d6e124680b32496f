"""Statistics of the evaluation: means with t-intervals, and the paper's one-way repeated-measures ANOVA (episodes
are the subjects, policies the within-subject factor) with Holm-corrected paired t-tests as post-hoc comparisons.

    mean, half = mean_ci(x)                          # 95% t-interval: mean +- half
    res = rm_anova(scores, ["dp-base", "rl", "L1"])  # scores (n_episodes, n_policies)
    res.f, res.p, res.posthoc                        # posthoc: list of Comparison(a, b, diff, t, p, p_holm)
    rank = rank_tests(scores, names)                 # Friedman + Holm-corrected Wilcoxon signed-rank: no normality

The ANOVA (the paper's test) assumes normal, spherical differences; returns with rare falls (-200) are far from
that, so the rank-based tests are reported beside it.
"""
from __future__ import annotations

import dataclasses
import itertools
import warnings

import numpy as np
from scipy import stats


def mean_ci(x, level: float = 0.95) -> tuple[float, float]:
    """Mean and the half-width of its `level` t-interval (nan half-width for fewer than 2 values)."""
    x = np.asarray(x, np.float64)
    if len(x) < 2:
        return float(x.mean()), float("nan")
    return float(x.mean()), float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x)))


@dataclasses.dataclass
class Comparison:
    a: str
    b: str
    diff: float  # mean of (a - b) over subjects
    t: float  # paired t statistic (inf when every difference is the same non-zero number)
    p: float  # two-sided, uncorrected
    p_holm: float  # Holm-corrected over all pairs


@dataclasses.dataclass
class AnovaResult:
    f: float
    df_num: float
    df_den: float
    p: float
    posthoc: list[Comparison]

    def summary(self) -> str:
        head = f"one-way repeated-measures ANOVA: F({self.df_num:g}, {self.df_den:g}) = {self.f:.3f}, p = {self.p:.3g}"
        rows = [f"  {c.a} - {c.b}: mean diff {c.diff:+.4g}, t = {c.t:.3g}, p = {c.p:.3g}, Holm p = {c.p_holm:.3g}"
                for c in self.posthoc]
        return "\n".join([head, "post-hoc paired t-tests (Holm):", *rows])


def rm_anova(scores, names: list[str]) -> AnovaResult:
    """One-way repeated-measures ANOVA of `scores` (n_subjects, k_conditions) via statsmodels' `AnovaRM`, and every
    pair of conditions compared by a paired t-test (scipy), Holm-corrected (statsmodels)."""
    import pandas as pd
    from statsmodels.stats.anova import AnovaRM
    from statsmodels.stats.multitest import multipletests

    scores = np.asarray(scores, np.float64)
    if scores.ndim != 2 or scores.shape[1] != len(names) or scores.shape[0] < 2 or len(names) < 2:
        raise ValueError(f"scores: expected (n_subjects >= 2, {len(names)} conditions), got shape {scores.shape}")
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores: every value must be finite")
    n, k = scores.shape
    frame = pd.DataFrame(
        dict(subject=np.repeat(np.arange(n), k), condition=np.tile(np.asarray(names, object), n), score=scores.ravel())
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a perfect fit (zero error) gives F = inf, p = 0
        table = AnovaRM(frame, depvar="score", subject="subject", within=["condition"]).fit().anova_table
    row = table.iloc[0]
    pairs = list(itertools.combinations(range(k), 2))
    raw = []
    for i, j in pairs:
        d = scores[:, i] - scores[:, j]
        if np.all(d == d[0]):  # zero variance: the t-test degenerates
            t, p = (0.0, 1.0) if d[0] == 0 else (float(np.sign(d[0]) * np.inf), 0.0)
        else:
            t, p = stats.ttest_rel(scores[:, i], scores[:, j])
        raw.append((float(d.mean()), float(t), float(p)))
    holm = multipletests([p for _, _, p in raw], method="holm")[1]
    posthoc = [Comparison(names[i], names[j], d, t, p, float(ph)) for (i, j), (d, t, p), ph in zip(pairs, raw, holm)]
    return AnovaResult(f=float(row["F Value"]), df_num=float(row["Num DF"]), df_den=float(row["Den DF"]),
                       p=float(row["Pr > F"]), posthoc=posthoc)


@dataclasses.dataclass
class RankResult:
    chi2: float  # Friedman statistic (tie-corrected)
    df: int  # k - 1
    p: float
    posthoc: list[Comparison]  # t = Wilcoxon W statistic, diff = median of (a - b)

    def summary(self) -> str:
        head = f"Friedman test: chi2({self.df}) = {self.chi2:.3f}, p = {self.p:.3g}"
        rows = [f"  {c.a} - {c.b}: median diff {c.diff:+.4g}, W = {c.t:.4g}, p = {c.p:.3g}, Holm p = {c.p_holm:.3g}"
                for c in self.posthoc]
        return "\n".join([head, "post-hoc Wilcoxon signed-rank tests (Holm):", *rows])


def rank_tests(scores, names: list[str]) -> RankResult:
    """Friedman test over the conditions of `scores` (n_subjects, k), and every pair by a Wilcoxon signed-rank
    test (zero differences dropped), Holm-corrected."""
    from statsmodels.stats.multitest import multipletests

    scores = np.asarray(scores, np.float64)
    if scores.ndim != 2 or scores.shape[1] != len(names) or scores.shape[0] < 2 or len(names) < 3:
        raise ValueError(f"scores: expected (n_subjects >= 2, {len(names)} >= 3 conditions), got shape {scores.shape}")
    chi2, p = stats.friedmanchisquare(*scores.T)
    pairs = list(itertools.combinations(range(len(names)), 2))
    raw = []
    for i, j in pairs:
        d = scores[:, i] - scores[:, j]
        if np.all(d == 0):
            raw.append((0.0, float("nan"), 1.0))
            continue
        w = stats.wilcoxon(scores[:, i], scores[:, j], zero_method="wilcox")
        raw.append((float(np.median(d)), float(w.statistic), float(w.pvalue)))
    holm = multipletests([p for _, _, p in raw], method="holm")[1]
    posthoc = [Comparison(names[i], names[j], d, w, p, float(ph)) for (i, j), (d, w, p), ph in zip(pairs, raw, holm)]
    return RankResult(chi2=float(chi2), df=len(names) - 1, p=float(p), posthoc=posthoc)
