"""Pieces of the speed-against-error benchmark that decide what it reports."""

from __future__ import annotations

from stochastic_fields.bench import curve_marks, evaluate_targets


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
