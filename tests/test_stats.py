"""The evaluation's statistics against a worked textbook example (sums of squares by hand)."""
import numpy as np
import pytest
from scipy import stats as sps

from gsp_jax.core import stats

# 4 subjects x 3 conditions. By hand: grand mean 5; condition means 3, 5, 7 -> SS_cond = 4 (4 + 0 + 4) = 32;
# subject means 4, 5, 16/3, 17/3 -> SS_subj = 3 (1 + 0 + 1/9 + 4/9) = 14/3; SS_total = 42;
# SS_error = 42 - 32 - 14/3 = 16/3 on (3 - 1)(4 - 1) = 6 df; F = (32 / 2) / ((16/3) / 6) = 18 on (2, 6);
# p = (1 + F * 2/6)^(-6/2) = 7^-3 (the F(2, d) tail in closed form).
SCORES = np.array([[2, 4, 6], [3, 5, 7], [4, 4, 8], [3, 7, 7]], float)


def test_rm_anova_matches_the_worked_example():
    res = stats.rm_anova(SCORES, ["a", "b", "c"])
    assert res.f == pytest.approx(18.0, rel=1e-9)
    assert (res.df_num, res.df_den) == (2, 6)
    assert res.p == pytest.approx(7.0**-3, rel=1e-6)


def test_posthoc_paired_t_tests_with_holm():
    """a - b: differences -2, -2, 0, -4 -> mean -2, sd sqrt(8/3), t = -2 / (sd / 2) = -sqrt(6) on 3 df; the same
    for b - c; a - c is -4 for every subject (t = -inf, p = 0). Holm over the 3 pairs: both sqrt(6) tests get
    2 p."""
    res = stats.rm_anova(SCORES, ["a", "b", "c"])
    by = {(c.a, c.b): c for c in res.posthoc}
    p6 = 2 * sps.t.sf(np.sqrt(6), 3)
    for pair in [("a", "b"), ("b", "c")]:
        assert by[pair].diff == pytest.approx(-2.0)
        assert by[pair].t == pytest.approx(-np.sqrt(6), rel=1e-9)
        assert by[pair].p == pytest.approx(p6, rel=1e-9)
        assert by[pair].p_holm == pytest.approx(2 * p6, rel=1e-9)
    assert by[("a", "c")].t == -np.inf and by[("a", "c")].p == 0.0 and by[("a", "c")].p_holm == 0.0


def test_mean_ci_and_bad_input():
    m, half = stats.mean_ci([1.0, 2.0, 3.0])  # sd 1, n 3: half = t(0.975, 2) / sqrt(3)
    assert m == 2.0 and half == pytest.approx(4.302652729911275 / np.sqrt(3), rel=1e-9)
    with pytest.raises(ValueError, match="scores"):
        stats.rm_anova(SCORES[:, :2], ["a", "b", "c"])
    with pytest.raises(ValueError, match="finite"):
        stats.rm_anova(np.where(SCORES == 7, np.nan, SCORES), ["a", "b", "c"])


def test_friedman_matches_the_worked_example():
    """Ranks within subjects: (1,2,3), (1,2,3), (1.5,1.5,3), (1,2.5,2.5) -> rank sums 4.5, 8, 11.5;
    chi2 = 12 / (4*3*4) * (4.5^2 + 8^2 + 11.5^2) - 3*4*4 = 6.125, tie-corrected by 1 - (6 + 6) / (4 * (27 - 3))
    = 0.875 -> 7.0 on 2 df, p = exp(-7/2) (the chi2(2) tail in closed form)."""
    res = stats.rank_tests(SCORES, ["a", "b", "c"])
    assert res.chi2 == pytest.approx(7.0, rel=1e-9)
    assert res.p == pytest.approx(np.exp(-3.5), rel=1e-9)
    by = {(c.a, c.b): c for c in res.posthoc}
    assert by[("a", "c")].diff == -4.0 and by[("a", "c")].t == 0.0  # every difference negative: W+ = 0


def test_spearman_is_pearson_of_the_ranks_and_nan_for_a_constant():
    """Without ties, Spearman's rho is the Pearson correlation of the ranks (computed here by argsort)."""
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=40), rng.normal(size=40)
    y = 0.5 * x + y
    rank = lambda v: np.argsort(np.argsort(v)).astype(float)  # noqa: E731
    assert stats.spearman(x, y) == pytest.approx(np.corrcoef(rank(x), rank(y))[0, 1], abs=1e-12)
    assert stats.spearman(x, -x) == pytest.approx(-1.0) and np.isnan(stats.spearman(x, np.ones(40)))


def test_auc_is_the_share_of_hold_fall_pairs_ordered_right():
    """Brute force over every (hold, fall) pair: 1 if the hold scores higher, 1/2 if tied."""
    hold, fall = [3.0, 1.0, 2.0, 2.0], [2.0, 0.0, 5.0]
    pairs = [1.0 if h > f else 0.5 if h == f else 0.0 for h in hold for f in fall]
    assert stats.auc(hold, fall) == pytest.approx(np.mean(pairs))
    assert np.isnan(stats.auc([], fall)) and stats.auc([1.0], [0.0]) == 1.0


def test_sign_test_p_is_the_exact_binomial_tail():
    """8 cases only b failed against 5 only a did: p = 2 sum_{k<=5} C(13, k) / 2^13; no discordant case: p = 1."""
    from math import comb

    a = [False] * 8 + [True] * 5 + [False] * 3 + [True] * 2  # 3 both held, 2 both failed
    b = [True] * 8 + [False] * 5 + [False] * 3 + [True] * 2
    wins, losses, p = stats.sign_test(a, b)
    assert (wins, losses) == (8, 5)
    assert p == pytest.approx(2 * sum(comb(13, k) for k in range(6)) / 2**13)
    assert stats.sign_test([True, False], [True, False])[2] == 1.0
    with pytest.raises(ValueError, match="failures of"):
        stats.sign_test([True], [True, False])


def test_cluster_bootstrap_se_resamples_whole_clusters():
    """Clusters whose samples agree perfectly within and across give rho = 1 in every resample: SE 0. With noise
    the SE is positive, the same for the same seed, and shrinks as clusters are added (about 1/sqrt(clusters))."""
    x = np.arange(30.0)
    assert stats.cluster_bootstrap_se(x, 2 * x, np.repeat(np.arange(10), 3), seed=0) == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(1)

    def se(n_clusters, seed=0):
        x = rng.normal(size=n_clusters * 4)
        return stats.cluster_bootstrap_se(x, x + rng.normal(size=x.size), np.repeat(np.arange(n_clusters), 4), seed)

    small, large = se(8), se(128)
    assert small > 0 and large < small
    x = np.linspace(0, 1, 24)
    y = np.sin(13 * x)
    c = np.repeat(np.arange(6), 4)
    assert stats.cluster_bootstrap_se(x, y, c, seed=3) == stats.cluster_bootstrap_se(x, y, c, seed=3)


def test_relative_returns_against_a_reference():
    """Differences to the reference, their optimal counts (within 1e-4) and falls (<= r_min), and the ANOVA's F
    against `rm_anova` of the same differences."""
    rng = np.random.default_rng(2)
    ref = rng.normal(size=12)
    returns = {"a": ref - np.abs(rng.normal(size=12)), "b": ref.copy(), "c": ref - 1.0, "ref": ref}
    returns["a"][0] = -200.0
    out = stats.relative_returns(returns, "ref", ["a", "b", "c"], r_min=-200.0)
    assert out["relative"]["b"] == dict(mean=0.0, ci95=0.0, optimal=12, falls=0)
    assert out["relative"]["c"]["mean"] == pytest.approx(-1.0) and out["relative"]["c"]["optimal"] == 0
    assert out["relative"]["a"]["falls"] == 1
    scores = np.stack([returns[n] - ref for n in "abc"], 1)
    assert out["anova"]["f"] == pytest.approx(stats.rm_anova(scores, list("abc")).f)
