"""The evaluation's statistics against a worked textbook example (sums of squares by hand)."""
import numpy as np
import pytest
from scipy import stats as sps

from gsp_jax import stats

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
