"""The verdict over several keys (gsticker_plugin/verify/stats.py: correct_keys), on hand-made key results."""

import pytest

from gsticker_plugin import metrics
from gsticker_plugin.verify.stats import correct_keys


def _result(pvalue: float, vote: int = 48, empirical=None):
    return {"model_pvalue": pvalue, "vote_statistic": vote, "thresholds": {"empirical": empirical}}


def test_holm_owns_only_the_keys_whose_corrected_pvalue_is_within_the_family_wise_rate():
    alpha = metrics.combined_fpr_bound(1e-6, 0.5)
    results = [_result(alpha / 10), _result(alpha / 2.5), _result(0.3)]
    out = correct_keys(results, 1e-6, 0.5, "holm")
    assert out["family_wise_fpr"] == pytest.approx(alpha) and out["keys"] == 3
    # Holm: smallest x3, next x2, largest x1 (monotone): 3a/10 and 2a/2.5 are within a, 0.3 is not
    assert [r["owned"] for r in results] == [True, True, False]
    assert results[0]["adjusted_pvalue"] == pytest.approx(3 * alpha / 10)


def test_bonferroni_is_never_more_lenient_than_holm():
    alpha = metrics.combined_fpr_bound(1e-6, 0.5)
    holm, bonf = [_result(alpha / 10), _result(0.6 * alpha)], [_result(alpha / 10), _result(0.6 * alpha)]
    correct_keys(holm, 1e-6, 0.5, "holm")
    correct_keys(bonf, 1e-6, 0.5, "bonferroni")
    assert [r["owned"] for r in holm] == [True, True] and [r["owned"] for r in bonf] == [True, False]


def test_a_key_below_its_empirical_threshold_is_not_owned_whatever_its_pvalue():
    results = [_result(1e-12, vote=42, empirical=44)]
    correct_keys(results, 1e-6, 0.5, "holm")
    assert results[0]["owned"] is False and results[0]["verdict"] == "not shown"
