"""The paper's Tables 1-3 on real scenes, side by side, plus the stronger metrics (issue 4,
docs/definitions.md §5-§8).

Protocol (docs/definitions.md §7): every method is trained on the same scene, split (``index % 5 == 0`` trains),
budget (iterations, rays per batch, samples per ray, field backend and resolution) and seed,
then scored on every test view. One configuration per method for every scene: no per-scene
tuning.

Layout of an output folder::

    <out>/<scene>/<method>/        one run folder per method (Trainer: config.json, checkpoint.pt,
                                    train_log.jsonl) plus
        stages.json                 finished stages with the fingerprint of their inputs
        metrics.json                per-view and pooled scores, conventions
        curves.npz                  pooled sparsification / calibration curves (for the plots)
        timing.json                 render time of one full view (Table 2)
        views/                      products of the first ``product_views`` test views
    <out>/tables.json, tables.md    Tables 1-5 with conventions and the paper's figures
    <out>/plots/<scene>_*.png       sparsification and calibration plots

Stages (train -> eval -> timing) are resumable: a stage whose fingerprint matches is skipped, an
interrupted training resumes from its checkpoint, and a finished table can be rebuilt from the
files alone (``collect_results``).

Scores (per test view, then mean over views; undefined values are counted, not averaged):
``evaluation.score_view`` (PSNR, SSIM, NLL at the variance floor, Pearson/Spearman of per-pixel
MSE vs variance, AUSE-RMSE) plus AUSE-MAE, normalised AUSEs, colour AUCE, and depth scores
against COLMAP points (LLFF) or the dataset's depth maps (synthetic). Pooled values (every test
pixel of the scene at once) are kept beside them. A method whose uncertainty map is constant
(the deterministic NeRF) has undefined correlations and AUSE: ranking by a constant is
arbitrary.

Modules (this one gathers their public names): ``methods`` (what is compared, the paper's
figures), ``budget`` (what every method is trained and scored with), ``runner`` (the resumable
stages; scoring through ``stochastic_fields.evaluation``), ``report`` (tables and plots).
"""

from __future__ import annotations

from .budget import CPU_BUDGET_OVERRIDES, CPU_BUDGET_VIEWS, PROTOCOLS, BenchmarkSettings, base_config, select_views
from .methods import DEFAULT_METHODS, DEFAULT_SCENES, METHOD_SPECS, MethodSpec, PAPER_SNERF, PAPER_TABLE1, PAPER_TABLE2, PAPER_TABLE3, TABLE1_METHODS, TABLE3_METHODS, method_config
from .report import build_tables, format_markdown, write_plots
from .runner import TABLES_DIST_TIMEOUT_S, CALIBRATION_PROTOCOL, assign_stages, SCORED_POINTS, TABLE_CONVENTIONS, check_compatible, collect_results, config_fingerprint, evaluate_run, json_default, load_method_result, load_stages, resolve_scene, run_benchmark, run_method, run_scene, save_stages, scene_inputs, time_render

__all__ = [
    "CPU_BUDGET_OVERRIDES",
    "CPU_BUDGET_VIEWS",
    "PROTOCOLS",
    "BenchmarkSettings",
    "base_config",
    "select_views",
    "DEFAULT_METHODS",
    "DEFAULT_SCENES",
    "METHOD_SPECS",
    "MethodSpec",
    "PAPER_SNERF",
    "PAPER_TABLE1",
    "PAPER_TABLE2",
    "PAPER_TABLE3",
    "TABLE1_METHODS",
    "TABLE3_METHODS",
    "method_config",
    "build_tables",
    "format_markdown",
    "write_plots",
    "CALIBRATION_PROTOCOL",
    "SCORED_POINTS",
    "TABLE_CONVENTIONS",
    "check_compatible",
    "collect_results",
    "config_fingerprint",
    "evaluate_run",
    "json_default",
    "load_method_result",
    "load_stages",
    "resolve_scene",
    "run_benchmark",
    "assign_stages",
    "TABLES_DIST_TIMEOUT_S",
    "run_method",
    "run_scene",
    "scene_inputs",
    "save_stages",
    "time_render",
]
