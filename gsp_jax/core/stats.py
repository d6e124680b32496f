"""Statistics of the evaluation: means with t-intervals, and the paper's one-way repeated-measures ANOVA (episodes
are the subjects, policies the within-subject factor) with Holm-corrected paired t-tests as post-hoc comparisons.

    mean, half = mean_ci(x)                          # 95% t-interval: mean +- half
    res = rm_anova(scores, ["dp-base", "rl", "L1"])  # scores (n_episodes, n_policies)
    res.f, res.p, res.posthoc                        # posthoc: list of Comparison(a, b, diff, t, p, p_holm)
    rank = rank_tests(scores, names)                 # Friedman + Holm-corrected Wilcoxon signed-rank: no normality
    spearman(x, y), auc(hold, fall)                  # how a score ranks outcomes (the surrogate against physics)
    cluster_bootstrap_se(x, y, episode, seed)        # ... and the SE of that rank correlation, episodes resampled
    sign_test(a_failed, b_failed)                    # paired failures of two conditions: exact sign test

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


# ------------------------------------------------------------- the surrogate against physics: ranks and sign tests
def spearman(x, y) -> float:
    """Spearman rank correlation of two equal-length samples; nan where either is constant."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(stats.spearmanr(x, y).statistic)


def auc(score_hold, score_fall) -> float:
    """P(a hold's score > a fall's score), ties half (the Mann-Whitney U over the product); nan if either is
    empty."""
    a, b = np.asarray(score_hold, float).ravel(), np.asarray(score_fall, float).ravel()
    if not len(a) or not len(b):
        return float("nan")
    ranks = stats.rankdata(np.concatenate([a, b]))  # ties get their mean rank: half a win each
    return float((ranks[: len(a)].sum() - len(a) * (len(a) + 1) / 2) / (len(a) * len(b)))


def cluster_bootstrap_se(x, y, cluster, seed: int, n: int = 200) -> float:
    """Standard error of `spearman(x, y)` pooled over samples (N,), resampling whole clusters (N,) ids with
    replacement `n` times (a cluster's samples, e.g. one episode's sequences, are not independent)."""
    x, y, cluster = np.asarray(x), np.asarray(y), np.asarray(cluster)
    rng = np.random.default_rng(seed)
    ids = np.unique(cluster)
    members = [np.flatnonzero(cluster == c) for c in ids]
    vals = []
    for _ in range(n):
        idx = np.concatenate([members[i] for i in rng.integers(0, len(ids), len(ids))])
        vals.append(spearman(x[idx], y[idx]))
    vals = np.asarray(vals)
    return float(np.nanstd(vals[np.isfinite(vals)])) if np.isfinite(vals).any() else float("nan")


def sign_test(a_failed, b_failed) -> tuple[int, int, float]:
    """(cases where only b failed, cases where only a failed, the two-sided exact sign test's p-value that the two
    are equally likely) from paired failures (N,) bool of two conditions a and b."""
    a, b = np.asarray(a_failed, bool), np.asarray(b_failed, bool)
    if a.shape != b.shape:
        raise ValueError(f"sign_test: failures of {a.shape} and {b.shape} cases")
    wins, losses = int(np.sum(~a & b)), int(np.sum(a & ~b))
    p = 1.0 if wins + losses == 0 else float(stats.binomtest(wins, wins + losses, 0.5).pvalue)
    return wins, losses, p


def relative_returns(returns: dict, reference: str, compared, r_min: float) -> dict:
    """Fig. 4a's analysis of per-episode returns {policy: (N,)}: each compared policy's return minus the reference's
    (mean and 95% half-width; episodes where it is optimal within 1e-4; falls: returns <= r_min), and the
    RM-ANOVA and rank tests of those differences ({"anova": None, ...} where statsmodels is missing)."""
    rets = {n: np.asarray(r, np.float64) for n, r in returns.items()}
    compared = list(compared)
    rel = {n: rets[n] - rets[reference] for n in compared}
    summary = {n: dict(zip(["mean", "ci95"], mean_ci(rel[n])))
               | dict(optimal=int(np.sum(rel[n] > -1e-4)), falls=int(np.sum(rets[n] <= r_min))) for n in compared}
    scores = np.stack([rel[n] for n in compared], axis=1)
    try:
        anova = rm_anova(scores, compared)
        rank = rank_tests(scores, compared)
    except ImportError as e:  # statsmodels missing (a bare GPU image): `reproduce --report-only` redoes this
        return dict(relative=summary, anova=None, rank=None, anova_text=f"statistics skipped: {e}")
    return dict(relative=summary, anova_text=anova.summary() + "\n" + rank.summary(),
                anova=dict(f=anova.f, df=[anova.df_num, anova.df_den], p=anova.p,
                           posthoc=[vars(c) for c in anova.posthoc]),
                rank=dict(chi2=rank.chi2, df=rank.df, p=rank.p, posthoc=[vars(c) for c in rank.posthoc]))
