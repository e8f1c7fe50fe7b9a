"""Pieces of the speed-against-error benchmark that decide what it reports."""

from __future__ import annotations

from stochastic_fields_bench.speed import curve_marks, evaluate_targets


def test_curve_marks_geometric_with_both_ends():
    marks = curve_marks(1000, 4)
    assert marks == [10, 46, 215, 1000]
    assert curve_marks(5, 8) == [5]  # total below the first mark
    assert curve_marks(300, 1) == [300]


def _scene(ratio_det: float, evals_ratio: float, dpsnr: float, nll128: float, nll_ad: float) -> dict:
    return {"render": {"skipping": {"evals_ratio": evals_ratio, "psnr_difference_db": dpsnr},
                       "deterministic_ratio": {"ratio": ratio_det, "K": 16},
                       "k_sweep": [{"K": 128, "nll": nll128, "time_s": 10.0}],
                       "adaptive_by_rtol": [{"rtol": 0.05, "nll": nll_ad, "time_s": 2.0, "K_mean": 40}]}}


def test_targets_from_hand_made_results():
    grid_curve = [{"psnr": 12.0, "elapsed_s": 5.0}, {"psnr": 16.1, "elapsed_s": 20.0}, {"psnr": 18.0, "elapsed_s": 90.0}]
    mlp_curve = [{"psnr": 11.0, "elapsed_s": 100.0}, {"psnr": 16.0, "elapsed_s": 400.0}]
    results = {"scenes": {"fern": {"training": {"grid": {"curve": grid_curve}, "mlp": {"curve": mlp_curve}},
                                   **_scene(1.2, 3.5, -0.05, 2.0, 2.03)},
                          "synthetic": _scene(1.7, 2.0, 0.2, 1.0, 1.1)}}
    t = evaluate_targets(results)
    fast = t["fast_backend_time_to_mlp_psnr"]
    assert fast["grid_time_to_reach_s"] == 20.0 and fast["ratio"] == 20.0 / 400.0 and fast["met"]
    assert t["skipping_evals_ratio"]["fern"]["met"] and not t["skipping_evals_ratio"]["synthetic"]["met"]
    assert t["snerf_over_deterministic_render"]["fern"]["met"]
    assert not t["snerf_over_deterministic_render"]["synthetic"]["met"]
    assert t["adaptive_k"]["fern"][0]["met"] and not t["adaptive_k"]["synthetic"][0]["met"]


def test_rao_blackwell_entries_are_compared_with_their_own_k128():
    """An adaptive render with Rao-Blackwellised colours is judged against the Rao-Blackwell K = 128
    render (not the drawn-colour one), and its deterministic ratio is reported beside the default's."""
    scene = _scene(2.0, 1.0, 0.0, 30.0, 31.0)
    scene["render"]["k_sweep_rao_blackwell"] = [{"K": 128, "nll": 24.0, "time_s": 4.0}]
    scene["render"]["k_sweep_rao_blackwell_k128_seed_nll"] = {"nll": [24.0, 24.2, 23.9], "relative_sd": 0.006}
    scene["render"]["adaptive_by_rtol"].append({"rtol": 0.01, "nll": 24.3, "time_s": 3.0, "K_mean": 80,
                                                "rule": "precision", "colour_estimator": "rao_blackwell"})
    scene["render"]["deterministic_ratio_rao_blackwell"] = {"ratio": 1.4, "K": 16}
    t = evaluate_targets({"scenes": {"synthetic": scene}})
    draws, rb = t["adaptive_k"]["synthetic"]
    assert draws["colour_estimator"] == "draws" and draws["nll_k128"] == 30.0 and not draws["met"]  # 3.3% off
    assert rb["nll_k128"] == 24.0 and abs(rb["relative_nll_difference"] - 0.0125) < 1e-12 and rb["met"]
    assert rb["k128_nll_seed_relative_sd"] == 0.006 and draws["k128_nll_seed_relative_sd"] is None
    det = t["snerf_over_deterministic_render"]["synthetic"]
    assert not det["met"] and det["rao_blackwell"] == {"ratio": 1.4, "met": True}


def test_adaptive_k_at_the_cap_does_not_count():
    """An adaptive render that drew K = 128 everywhere is K = 128, however its timing came out."""
    scene = _scene(1.0, 3.0, 0.0, 20.0, 20.0)
    scene["render"]["adaptive_by_rtol"][0].update(K_mean=128.0, max_draws=128, time_s=9.0)
    assert not evaluate_targets({"scenes": {"synthetic": scene}})["adaptive_k"]["synthetic"][0]["met"]
