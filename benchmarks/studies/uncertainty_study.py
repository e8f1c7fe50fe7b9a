"""Controlled study of S-NeRF's uncertainty on real and synthetic scenes: one factor at a time.

Each row is S-NeRF with the learned pixel noise (the tables' "S-NeRF + learned noise") with ONE
change, trained and scored by the same runner as the benchmark tables
(``stochastic_fields_bench.tables``: CPU budget, 1000 steps, 4 test views, seed 0), plus the deep
ensemble and the deterministic NeRF as references. Depth is scored on the SCORE capture points
only (``capture_points``); each S-NeRF row reports its depth intervals raw and recalibrated from
the CALIBRATE points (``calibration``), so the recalibration factor is measured on every row.
Test views choose nothing: the rows are fixed before the run.

    python benchmarks/studies/uncertainty_study.py --out benchmarks/results/uncertainty_study

Resumable like the tables (finished stages are skipped). Writes ``study.md`` and ``study.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"

Row = tuple[str, str, tuple[tuple[str, object], ...], str]

#: The references beside every study's rows.
REFERENCE_ROWS: tuple[Row, ...] = (
    ("ensemble", "ensemble", (), "reference: deep ensemble of 5"),
    ("deterministic", "deterministic", (), "reference: deterministic NeRF"),
)


#: Study 1: (row name, method of stochastic_fields_bench.tables.METHOD_SPECS, extra config overrides,
#: what the row changes); each row changes one thing of S-NeRF + learned pixel noise.
ROWS: tuple[Row, ...] = (
    ("base", "snerf_predictive", (), "S-NeRF + learned pixel noise, independent noise per point (the paper)"),
    ("shared_noise", "snerf_predictive", (("render.shared_noise", True),),
     "noise shared along each ray per draw (trajectory-consistent draws), training and rendering"),
    ("rao_blackwell", "snerf_predictive", (("render.colour_estimator", "rao_blackwell"),),
     "Rao-Blackwellised colour statistics at render time (less Monte-Carlo noise in the variance)"),
    ("depth", "snerf_predictive", (("loss.lambda_depth", 0.1),),
     "+ sparse-depth likelihood of the FIT capture points (weight 0.1)"),
) + REFERENCE_ROWS

#: Study 2: one change of today's default (study 1's decision: + sparse-depth likelihood).
ROWS_NOISE_HEAD: tuple[Row, ...] = (
    ("default", "snerf_default", (("loss.per_point_noise", False),),
     "S-NeRF default before this study: learned global pixel noise, sparse-depth likelihood"),
    ("per_point_noise", "snerf_default", (("loss.per_point_noise", True), ("loss.noise_head_decoupled", False)),
     "+ per-point observation noise beta(x) beside the global one (likelihood and predictive variance)"),
    ("per_point_noise_decoupled", "snerf_default", (("loss.per_point_noise", True), ("loss.noise_head_decoupled", True)),
     "+ per-point observation noise that only explains residuals: colours and densities keep the global-noise "
     "likelihood's gradient (stop-gradient weighting)"),
) + REFERENCE_ROWS

#: Study 4: few-view geometry, one change of today's default (study 2's decision: + decoupled noise head).
ROWS_GEOMETRY: tuple[Row, ...] = (
    ("default", "snerf_default", (("loss.lambda_depth", 0.1),),
     "S-NeRF default before this study (sparse-depth likelihood at weight 0.1, decoupled per-point noise)"),
    ("coarse_to_fine", "snerf_default", (("field.grid_coarse_to_fine", 0.5),),
     "the finer grid levels fade in over the first half of training, coarsest first"),
    ("tv_strong", "snerf_default", (("train.tv_weight", 1e-2),), "10x the grid's total-variation weight (1e-2)"),
    ("depth_strong", "snerf_default", (("loss.lambda_depth", 0.3),),
     "3x the sparse-depth likelihood weight (0.3; the default from this study to study 6)"),
) + REFERENCE_ROWS

#: Study 5: colour recalibration from pixel blocks of the training views held out of training.
ROWS_COLOUR: tuple[Row, ...] = (
    ("default", "snerf_default", (("loss.lambda_depth", 0.3),),
     "S-NeRF default at the time (sparse-depth likelihood at weight 0.3, decoupled per-point noise)"),
    ("colour_holdout", "snerf_default", (("loss.lambda_depth", 0.3), ("train.holdout_fraction", 0.1)),
     "10% of each training view's 16-pixel blocks held out of training; the colour std recalibrated on them"),
) + REFERENCE_ROWS


#: Study 6: the sparse-depth weight beyond study 4's 0.3 (its trend: every metric improved from 0.1 to 0.3).
ROWS_DEPTH_WEIGHT: tuple[Row, ...] = (
    ("default", "snerf_default", (("loss.lambda_depth", 0.3),),
     "S-NeRF default before this study (sparse-depth likelihood at weight 0.3, decoupled per-point noise)"),
    ("depth_1", "snerf_default", (("loss.lambda_depth", 1.0),),
     "the sparse-depth likelihood at weight 1.0 (today's default since this study)"),
) + REFERENCE_ROWS


#: Study 8: the training likelihood's colour estimator (drawn colours against their exact expectation).
ROWS_LIKELIHOOD: tuple[Row, ...] = (
    ("default", "snerf_default", (),
     "S-NeRF default (study 6's depth_1): the training likelihood draws every sample's colour"),
    ("rb_likelihood", "snerf_default", (("loss.likelihood_estimator", "rao_blackwell"),),
     "the training likelihood takes the colours' expectation given each density draw (Rao-Blackwellised)"),
) + REFERENCE_ROWS


#: Study 9: how many Monte-Carlo samples a training step draws (the training-cost target, issue 19's 5b).
ROWS_TRAINING_SAMPLES: tuple[Row, ...] = (
    ("default", "snerf_default", (),
     "S-NeRF default (study 6's depth_1): K = 8 training trajectories, KL on 4096 ray samples and 12^3 random points"),
    ("draws4", "snerf_default", (("train.train_draws", 4),),
     "K = 4 training trajectories per ray (the Monte-Carlo expected log-likelihood from half the draws)"),
    ("kl_quarter", "snerf_default", (("loss.observed_kl_samples", 1024), ("loss.random_points_per_axis", 8)),
     "the KL terms' Monte-Carlo means over about a quarter of the points: 1024 ray samples and 8^3 random points"),
) + REFERENCE_ROWS


#: The seed spread: today's default trained again from other seeds (initialisation, ray batches,
#: draws), nothing else changed; how far a ruled metric moves by chance alone.
ROWS_SEEDS: tuple[Row, ...] = (
    ("default", "snerf_default", (), "S-NeRF default, seed 0 (study 6's depth_1 runs)"),
    ("seed1", "snerf_default", (("train.seed", 1),), "S-NeRF default, seed 1"),
    ("seed2", "snerf_default", (("train.seed", 2),), "S-NeRF default, seed 2"),
) + REFERENCE_ROWS


#: Study 9b: study 9's K = 4 row again from seeds 1 and 2, judged on three-seed means against the
#: default's (the seed rows above), because one seed's spread is as large as the rule's tolerances.
ROWS_DRAWS4_SEEDS: tuple[Row, ...] = ROWS_SEEDS[:3] + (
    ("draws4", "snerf_default", (("train.train_draws", 4),), "K = 4 training trajectories, seed 0 (study 9's row)"),
    ("draws4_seed1", "snerf_default", (("train.train_draws", 4), ("train.seed", 1)), "K = 4, seed 1"),
    ("draws4_seed2", "snerf_default", (("train.train_draws", 4), ("train.seed", 2)), "K = 4, seed 2"),
) + REFERENCE_ROWS


def seed_rows(name: str) -> tuple[str, str, str]:
    """A row's three seed rows: ``name``, ``name_seed1``, ``name_seed2``."""
    return (name, f"{name}_seed1", f"{name}_seed2")


def seeded(name: str, overrides: tuple[tuple[str, object], ...], why: str) -> tuple[Row, Row, Row]:
    """One change of S-NeRF (default) trained from seeds 0, 1 and 2: the rows ``seed_rows(name)``, each with
    ``overrides`` (and ``train.seed`` but for seed 0), described as "``why``, seed N"."""
    return tuple((seed_rows(name)[seed], "snerf_default", overrides + ((("train.seed", seed),) if seed else ()),
                  f"{why}, seed {seed}") for seed in (0, 1, 2))


#: Study 9c: K = 4 for the colour likelihood, 8 for the depth likelihood (study 9b found the depth
#: ranking lost with K = 4 everywhere), three seeds each against the default's three.
ROWS_SPLIT_DRAWS: tuple[Row, ...] = ROWS_SEEDS[:3] + seeded(
    "draws4_depth8", (("train.train_draws", 4), ("loss.depth_draws", 8)),
    "K = 4 training trajectories for the colour rays, 8 for the capture-point rays") + REFERENCE_ROWS


#: Study 10: the training schedule at the CPU budget (issue 19's first factor: is the reconstruction
#: gap a budget effect?). A schedule is shared by every method, so each row trains S-NeRF (default)
#: and the deterministic NeRF with the same change; the seed-0 default and reference rows are
#: study 6's runs.
ROWS_SCHEDULE: tuple[Row, ...] = (
    ("default", "snerf_default", (), "S-NeRF default (study 6's depth_1): lr 5e-3 decaying to 5e-4 over 1000 steps"),
    ("lr_2x", "snerf_default", (("train.lr", 1e-2),), "twice the learning rate (1e-2, decaying to 1e-3)"),
    ("lr_2x_det", "deterministic", (("train.lr", 1e-2),), "deterministic NeRF, twice the learning rate"),
    ("steps_2x", "snerf_default", (("train.iterations", 2000),), "twice the steps (2000; the same lr schedule)"),
    ("steps_2x_det", "deterministic", (("train.iterations", 2000),), "deterministic NeRF, twice the steps"),
) + ROWS_SEEDS[1:3] + tuple(
    (f"{name}_seed{seed}", "snerf_default", overrides + (("train.seed", seed),), f"{why}, seed {seed} (trained only if "
     "the seed-0 row passes the rule)")
    for name, overrides, why in (("lr_2x", (("train.lr", 1e-2),), "twice the learning rate"),
                                 ("steps_2x", (("train.iterations", 2000),), "twice the steps"))
    for seed in (1, 2)) + REFERENCE_ROWS


#: Study 16: the KL terms (issue 19's "KL weights; the observed-ray prior"): one change of the default
#: per row, each trained from seeds 0, 1 and 2 and judged on three-seed means against the default's.
ROWS_KL: tuple[Row, ...] = ROWS_SEEDS[:3] + tuple(
    row for name, overrides, why in (
        ("no_observed_prior", (("loss.kl", "fixed_prior"),),
         "no observed-ray prior: the random-point KL only (the paper's 'fixed prior' ablation)"),
        ("kl_random_4x", (("loss.lambda_random", 4e-2),), "4x the random-point KL weight (4e-2)"),
        ("kl_random_quarter", (("loss.lambda_random", 2.5e-3),), "a quarter of the random-point KL weight (2.5e-3)"),
        ("kl_observed_quarter", (("loss.lambda_observed", 1.25e-2),),
         "a quarter of the observed-ray KL weight (1.25e-2; study 16b, added after the first three rows' result)"))
    for row in seeded(name, overrides, why)) + REFERENCE_ROWS


#: Study 17: the paper's MLP backbone at the grid's wall time (issue 19's "backbone" factor). The
#: step count is the default's mean training time (158 s) over one MLP step of its objective (4.19 s).
MLP_EQUAL_TIME_ITERATIONS: int = 38
ROWS_BACKBONE: tuple[Row, ...] = (
    ("default", "snerf_default", (), "S-NeRF default, seed 0 (study 16b's kl_observed_quarter run)"),
    ("mlp_equal_time", "snerf_default",
     (("field.backend", "mlp"), ("train.lr", 5e-4), ("train.iterations", MLP_EQUAL_TIME_ITERATIONS)),
     f"the paper's 8 x 256 MLP at its learning rate (5e-4), {MLP_EQUAL_TIME_ITERATIONS} steps: the grid's wall time"),
) + REFERENCE_ROWS


#: Study 18b: the default trained from two seeds no study had used, to confirm study 18's cross-fitted
#: diagnostic on runs it has not seen (renders of benchmarks/studies/photo_calibration_study.py).
ROWS_FRESH_SEEDS: tuple[Row, ...] = tuple(
    (f"seed{seed}", "snerf_default", (("train.seed", seed),), f"S-NeRF default, seed {seed} (study 18b)")
    for seed in (3, 4)) + REFERENCE_ROWS


#: --study NAME -> its rows.
STUDIES: dict[str, tuple[Row, ...]] = {"factors": ROWS, "noise_head": ROWS_NOISE_HEAD, "geometry": ROWS_GEOMETRY,
                                       "colour": ROWS_COLOUR, "depth_weight": ROWS_DEPTH_WEIGHT,
                                       "likelihood": ROWS_LIKELIHOOD, "training_samples": ROWS_TRAINING_SAMPLES,
                                       "seeds": ROWS_SEEDS, "draws4_seeds": ROWS_DRAWS4_SEEDS,
                                       "split_draws": ROWS_SPLIT_DRAWS, "schedule": ROWS_SCHEDULE,
                                       "kl": ROWS_KL, "backbone": ROWS_BACKBONE,
                                       "fresh_seeds": ROWS_FRESH_SEEDS}

COLUMNS: tuple[tuple[str, str], ...] = (
    ("psnr", "PSNR"), ("nll", "NLL"), ("auce_colour", "AUCE"), ("nll_raw", "NLL raw"), ("auce_colour_raw", "AUCE raw"),
    ("colour_scale", "colour x(68%)"), ("spearman_mse_var", "Spearman MSE-var"),
    ("pooled_spearman", "Spearman pooled"), ("ause_rmse_normalised", "AUSE norm."),
    ("depth_abs_rel", "depth abs-rel"), ("depth_spearman_view", "depth Spearman"),
    ("depth_spearman", "depth Spearman pooled"),
    ("cov68_raw", "cov68 raw"), ("cov95_raw", "cov95 raw"), ("cov68", "cov68 cal."), ("cov95", "cov95 cal."),
    ("depth_scale", "cal. x(68%)"), ("train_s", "train s"),
)


#: Study 8's tolerances, used by every training study since (docs/uncertainty.md): the most a row's
#: three-seed mean may move the wrong way against the default's (signed: negative = may fall by).
RULE_TOLERANCES: dict[str, float] = {"psnr": -0.2, "nll": 0.05, "spearman_mse_var": -0.02,
                                     "depth_spearman_view": -0.02, "depth_abs_rel": 0.005,
                                     "coverage_distance": 0.02}

#: Study 16's gains on issue 19's unmet targets (mean over the scenes): a row must reach one of them.
RULE_GAINS: dict[str, float] = {"depth_spearman_view": 0.02, "coverage_distance": -0.02, "psnr": 0.2}

#: The nominal central levels the coverage distance is measured from.
NOMINAL_COVERAGE: tuple[float, float] = (0.683, 0.95)

#: The default's three seed rows (the ``seeds`` study's runs).
DEFAULT_SEED_ROWS: tuple[str, ...] = tuple(row[0] for row in ROWS_SEEDS[:3])


def coverage_distance(numbers: dict[str, float]) -> float:
    """|cov68 - 0.683| + |cov95 - 0.95| of the recalibrated depth intervals (pooled)."""
    return abs(numbers["cov68"] - NOMINAL_COVERAGE[0]) + abs(numbers["cov95"] - NOMINAL_COVERAGE[1])


def seed_mean(by_row: dict[str, dict[str, float]], rows: tuple[str, ...], metric: str) -> float:
    """Mean of ``metric`` (or the coverage distance) over ``rows``; every row must have run."""
    missing = [r for r in rows if r not in by_row]
    if missing:
        raise ValueError(f"rows {missing} have no finished run (have {sorted(by_row)})")
    values = [coverage_distance(by_row[r]) if metric == "coverage_distance" else by_row[r][metric] for r in rows]
    return sum(values) / len(values)


def judge_seeded(results: dict[str, dict[str, dict[str, float]]], candidates: tuple[str, ...]) -> dict:
    """Study 16's rule on three-seed means (docs/uncertainty.md): each candidate row against the
    default's three seeds, on every scene, within RULE_TOLERANCES; then, averaged over the scenes, a
    gain of at least one of RULE_GAINS. Of the rows that pass, the largest mean per-view depth
    Spearman gain is taken (None: the default stays).

    Args:
        results: scene -> row -> numbers (``study.json``'s "results").
        candidates: row names whose seed rows (``seed_rows``) all ran on every scene.
    Returns:
        {"rows": {row: {"scenes": {scene: {"delta": {metric: d}, "failed": [metrics]}},
                        "mean_delta": {metric: d}, "gains": [metrics], "passes": bool}}, "taken": row or None}
    """
    metrics = list(dict.fromkeys([*RULE_TOLERANCES, *RULE_GAINS]))
    out: dict = {"rows": {}, "taken": None}
    for row in candidates:
        scenes = {}
        for scene, by_row in results.items():
            delta = {m: seed_mean(by_row, seed_rows(row), m) - seed_mean(by_row, DEFAULT_SEED_ROWS, m) for m in metrics}
            failed = [m for m, tol in RULE_TOLERANCES.items() if (delta[m] < tol if tol < 0 else delta[m] > tol)]
            scenes[scene] = {"delta": delta, "failed": failed}
        mean_delta = {m: sum(s["delta"][m] for s in scenes.values()) / len(scenes) for m in metrics}
        gains = [m for m, g in RULE_GAINS.items() if (mean_delta[m] <= g if g < 0 else mean_delta[m] >= g)]
        passes = bool(gains) and not any(s["failed"] for s in scenes.values())
        out["rows"][row] = {"scenes": scenes, "mean_delta": mean_delta, "gains": gains, "passes": passes}
    passing = [r for r in candidates if out["rows"][r]["passes"]]
    if passing:
        out["taken"] = max(passing, key=lambda r: out["rows"][r]["mean_delta"]["depth_spearman_view"])
    return out


def rule_margins(decision: dict) -> dict[str, dict[str, dict[str, float]]]:
    """scene -> row -> metric -> delta / |tolerance|, signed so that > 0 is better and <= -1 fails
    (what ``plots.plot_rule_margins`` draws)."""
    margins: dict[str, dict[str, dict[str, float]]] = {}
    for row, judged in decision["rows"].items():
        for scene, s in judged["scenes"].items():
            margins.setdefault(scene, {})[row] = {
                m: (s["delta"][m] / abs(tol)) * (1.0 if tol < 0 else -1.0) for m, tol in RULE_TOLERANCES.items()}
    return margins


def write_rule(out: Path, results: dict, candidates: tuple[str, ...], command: str) -> dict:
    """Judge ``candidates`` (``judge_seeded``) and write ``rule.md``, ``rule.json`` and ``rule_margins.png``."""
    from stochastic_fields.io_utils import atomic_write_text
    from stochastic_fields.plots import plot_rule_margins

    decision = judge_seeded(results, candidates)
    lines = ["# The rule on three-seed means", "", f"Command: `{command}`", "",
             "Each row's mean over seeds 0, 1, 2 minus the default's (seeds 0, 1, 2). Tolerances: "
             + ", ".join(f"{m} {t:+g}" for m, t in RULE_TOLERANCES.items())
             + "; a row must also gain, averaged over the scenes, one of "
             + ", ".join(f"{m} {g:+g}" for m, g in RULE_GAINS.items()) + ".", "",
             "| row | scene | " + " | ".join(RULE_TOLERANCES) + " | failed |", "|---|---|" + "---|" * (len(RULE_TOLERANCES) + 1)]
    for row, judged in decision["rows"].items():
        for scene, s in judged["scenes"].items():
            lines.append(f"| {row} | {scene} | " + " | ".join(f"{s['delta'][m]:+.4f}" for m in RULE_TOLERANCES)
                         + f" | {', '.join(s['failed']) or '-'} |")
        lines.append(f"| {row} | **mean** | " + " | ".join(f"{judged['mean_delta'][m]:+.4f}" for m in RULE_TOLERANCES)
                     + f" | gains: {', '.join(judged['gains']) or 'none'}; **{'passes' if judged['passes'] else 'fails'}** |")
    lines += ["", f"Taken: **{decision['taken'] or 'none (the default stays)'}**.", ""]
    atomic_write_text(out / "rule.md", "\n".join(lines))
    atomic_write_text(out / "rule.json", json.dumps({"command": command, **decision}, indent=2, default=float))
    plot_rule_margins(rule_margins(decision), out / "rule_margins.png",
                      title="Three-seed mean change against the default, in tolerances (<= -1 fails)")
    print("\n".join(lines))
    return decision


def _row_numbers(run_dir: Path) -> dict[str, float]:
    from stochastic_fields_bench.tables import load_method_result

    r = load_method_result(run_dir)
    m = r["metrics"]
    s = m["summary"]

    def mean(key: str) -> float:
        return s[key]["mean"] if key in s else math.nan

    pooled = m.get("pooled", {})
    depth = pooled.get("depth", {})
    raw = pooled.get("depth_raw", depth)
    cal = m.get("depth_calibration") or {}
    return {
        "psnr": mean("psnr"), "nll": mean("nll"), "auce_colour": mean("auce_colour"),
        "nll_raw": mean("nll_raw"), "auce_colour_raw": mean("auce_colour_raw"),
        "colour_scale": (cal.get("colour") or {}).get("std_scale", math.nan),
        "spearman_mse_var": mean("spearman_mse_var"), "pooled_spearman": pooled.get("spearman_mse_var", math.nan),
        "ause_rmse_normalised": mean("ause_rmse_normalised"),
        "depth_abs_rel": depth.get("abs_rel", math.nan), "depth_spearman": depth.get("spearman", math.nan),
        "depth_spearman_view": mean("depth/spearman"),
        "cov68_raw": raw.get("coverage_68", math.nan), "cov95_raw": raw.get("coverage_95", math.nan),
        "cov68": depth.get("coverage_68", math.nan), "cov95": depth.get("coverage_95", math.nan),
        "depth_scale": (cal.get("depth") or {}).get("std_scale", math.nan),
        "depth_points": depth.get("num_used", math.nan),
        "train_s": r["stages"].get("train", {}).get("train_s", math.nan),
    }


def measure_cost(out: Path, scene: str, data_root: Path, *, rows: tuple[str, ...] = ("depth", "deterministic"),
                 study: tuple[Row, ...] = ROWS, reference: str = "deterministic", rounds: int = 4, steps: int = 25,
                 render_repeats: int = 3) -> dict:
    """Training and rendering cost of ``rows`` against ``reference`` on one scene, interleaved in
    one process (1 thread): ``rounds`` x ``steps`` training steps per row after a warm-up (the
    trainer's loop time, no set-up or checkpoints), and ``render_repeats`` full renders of the first
    scored test view by each row's trained model. Medians; ratios to the reference."""
    import copy
    import tempfile

    import numpy as np
    import torch

    from stochastic_fields.data import load_dataset
    from stochastic_fields_bench.tables import (METHOD_SPECS, BenchmarkSettings, base_config, method_config,
                                               resolve_scene, select_views)
    from stochastic_fields.trainer import Trainer, load_trained_model
    from stochastic_fields_bench.runner import time_renders_interleaved, time_training_interleaved

    scene_path = resolve_scene(scene, data_root)
    dataset = load_dataset(scene_path, images="images_8", split_every=5)
    view = select_views(list(dataset.test_indices), BenchmarkSettings())[0]
    specs = {name: (method, dict(overrides)) for name, method, overrides, _ in study}
    trainers = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in rows:
            method, overrides = specs[r]
            cfg = method_config(METHOD_SPECS[method], base_config(BenchmarkSettings(overrides=tuple(overrides.items())),
                                                                  dataset), scene_path)
            cfg.train.checkpoint_every = 0
            cfg.train.eval_every = 0
            trainers[r] = Trainer(copy.deepcopy(cfg), Path(tmp) / r, dataset)
            trainers[r].train(progress=False, max_steps=5)  # warm-up
        chunks = time_training_interleaved(trainers, rounds * steps, steps)
        step_s = {r: [t / n for t, n in v] for r, v in chunks.items()}
    models = {r: load_trained_model(out / r / dataset.name / specs[r][0], dataset=dataset)[1] for r in rows}
    render_s = time_renders_interleaved({r: (models[r], None) for r in rows}, dataset.rays(view), render_repeats)
    med = lambda v: float(np.median(v))  # noqa: E731
    return {"scene": dataset.name, "view": int(view), "threads": torch.get_num_threads(),
            "train_step_s": {r: med(v) for r, v in step_s.items()},
            "render_s": {r: med(v) for r, v in render_s.items()},
            "train_ratio": {r: med(step_s[r]) / med(step_s[reference]) for r in rows},
            "render_ratio": {r: med(render_s[r]) / med(render_s[reference]) for r in rows}}


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.0f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/uncertainty_study"))
    p.add_argument("--scenes", nargs="+", default=["synthetic", "fern", "flower"],
                   help="LLFF scene names under --data-root, folders, or 'synthetic' (the embedded scene, "
                        "generated into OUT/_scenes).")
    p.add_argument("--study", choices=sorted(STUDIES), default="factors",
                   help="Which rows: 'factors' (study 1, factors of S-NeRF + learned noise), 'noise_head' "
                        "(study 2, the per-point observation noise against today's default), 'geometry' "
                        "(study 4, few-view geometry regularisers against today's default), 'colour' "
                        "(study 5, colour recalibration from held-out pixel blocks against today's default) or "
                        "'depth_weight' (study 6, the sparse-depth weight 1.0 against today's 0.3) or "
                        "'likelihood' (study 8, the training likelihood's colours drawn or Rao-Blackwellised) or "
                        "'training_samples' (study 9, fewer training trajectories or fewer KL points) or "
                        "'seeds' (today's default from seeds 0, 1 and 2: the spread of every metric by chance) or "
                        "'draws4_seeds' (study 9b: K = 4 against the default, seeds 0, 1 and 2 each) or "
                        "'split_draws' (study 9c: K = 4 for the colour rays and 8 for the depth rays, three seeds) or "
                        "'schedule' (study 10: twice the learning rate or twice the steps, S-NeRF and deterministic NeRF) or "
                        "'kl' (study 16: no observed-ray prior, or the random-point KL weight x4 or /4; 16b: the observed-ray KL weight /4; three seeds) or "
                        "'backbone' (study 17: the paper's MLP at the grid's wall time) or 'fresh_seeds' (study 18b: "
                        "the default from seeds 3 and 4).")
    p.add_argument("--rows", nargs="+", default=None, help="Rows of the study to run (default: all of them).")
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    p.add_argument("--cost", action="store_true",
                   help="Only measure the training-step and render cost of the study's S-NeRF rows (factors: depth; "
                        "noise_head: per_point_noise_decoupled, default) against the deterministic NeRF on fern (interleaved, "
                        "one process; needs those rows trained) into OUT/cost.json; the table run includes it.")
    p.add_argument("--collect-only", action="store_true",
                   help="Train and score nothing: rebuild study.md/json from the finished runs under OUT.")
    p.add_argument("--judge", nargs="+", default=None, metavar="ROW",
                   help="Train nothing: judge these rows' three seeds (ROW, ROW_seed1, ROW_seed2) against the "
                        "default's from OUT/study.json by study 16's rule; writes OUT/rule.md, rule.json and "
                        "rule_margins.png.")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    import torch

    from stochastic_fields_bench.tables import BenchmarkSettings, run_scene

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    out = Path(args.out)
    if args.judge:
        from stochastic_fields.io_utils import read_json

        command = "python benchmarks/studies/uncertainty_study.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
        write_rule(out, read_json(out / "study.json", "study results")["results"], tuple(args.judge), command)
        return 0
    if args.cost:
        from stochastic_fields.io_utils import atomic_write_text

        cost_rows = {"factors": ("depth", "deterministic"),
                     "noise_head": ("per_point_noise_decoupled", "default", "deterministic"),
                     "geometry": ("default", "deterministic"),
                     "colour": ("colour_holdout", "default", "deterministic"),
                     "depth_weight": ("depth_1", "default", "deterministic"),
                     "likelihood": ("rb_likelihood", "default", "deterministic"),
                     "training_samples": ("draws4", "kl_quarter", "default", "deterministic"),
                     "seeds": ("default", "deterministic"),
                     "draws4_seeds": ("draws4", "default", "deterministic"),
                     "split_draws": ("draws4_depth8", "default", "deterministic"),
                     "schedule": ("default", "deterministic"),
                     "kl": ("no_observed_prior", "default", "deterministic"),
                     "backbone": ("mlp_equal_time", "default", "deterministic"),
                     "fresh_seeds": ("seed3", "deterministic")}[args.study]
        cost = measure_cost(out, "fern", args.data_root, rows=cost_rows, study=STUDIES[args.study])
        atomic_write_text(out / "cost.json", json.dumps(cost, indent=2))
        print(json.dumps(cost, indent=2))
        return 0
    scenes = []
    for scene in args.scenes:
        if scene == "synthetic":
            from stochastic_fields.data.synthetic import make_synthetic_scene

            path = out / "_scenes" / "synthetic"
            if not (path / "transforms.json").exists() and not args.collect_only:
                make_synthetic_scene(path)
            scenes.append(str(path))
        else:
            scenes.append(scene)
    study_rows = STUDIES[args.study]
    names = [r[0] for r in study_rows]
    if args.rows is not None and not set(args.rows) <= set(names):
        p.error(f"--rows must be among {names} for --study {args.study}, got {args.rows}")
    rows = [r for r in study_rows if args.rows is None or r[0] in args.rows]
    for name, method, overrides, _ in ([] if args.collect_only else rows):
        settings = BenchmarkSettings(timing=False, overrides=overrides)
        for scene in scenes:
            run_scene(scene, [method], out / name, settings, data_root=args.data_root, progress=not args.quiet)
    results: dict[str, dict[str, dict[str, float]]] = {}
    for name, method, _, _ in rows:
        for scene in scenes:
            run_dir = out / name / Path(scene).name / method
            if (run_dir / "metrics.json").exists():
                results.setdefault(Path(scene).name, {})[name] = _row_numbers(run_dir)
    cost = json.loads((out / "cost.json").read_text()) if (out / "cost.json").exists() else None
    command = "python benchmarks/studies/uncertainty_study.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    lines = ["# Uncertainty study: one factor at a time", "", f"Command: `{command}`", "",
             "Rows (fixed before the run):", ""]
    lines += [f"- **{n}** ({m}): {why}" + (f"; overrides {dict(o)}" if o else "") for n, m, o, why in rows]
    lines += ["", "Columns: colour PSNR / NLL / AUCE / Spearman MSE-variance (per-view mean and pooled) / "
              "normalised AUSE-RMSE on the test views; depth abs-rel (pooled), Spearman |err|-std (per-view mean "
              "and pooled), and the share of SCORE capture points (synthetic: the test pixels whose surface lies in a SCORE block, opacity > 0.5) inside the central "
              "68% / 95% intervals, raw and recalibrated (pooled); the recalibration factor at one sigma; "
              "training seconds (1 thread, machine shared with other work: compare within a column only).", ""]
    for scene, by_row in results.items():
        lines += [f"## {scene}", "", "| row | " + " | ".join(c[1] for c in COLUMNS) + " |",
                  "|---|" + "---|" * len(COLUMNS)]
        for name, nums in by_row.items():
            lines.append(f"| {name} | " + " | ".join(_fmt(nums[c[0]]) for c in COLUMNS) + " |")
        lines.append("")
    if cost is not None:
        lines += [f"## Cost ({cost['scene']}, {cost['threads']} thread, interleaved in one process)", "",
                  "| row | train s/step | x deterministic | render s (view %d) | x deterministic |" % cost["view"],
                  "|---|---|---|---|---|"]
        for r in cost["train_step_s"]:
            lines.append(f"| {r} | {cost['train_step_s'][r]:.3f} | {cost['train_ratio'][r]:.2f} | "
                         f"{cost['render_s'][r]:.2f} | {cost['render_ratio'][r]:.2f} |")
        lines.append("")
    from stochastic_fields.io_utils import atomic_write_text

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "study.md", "\n".join(lines))
    atomic_write_text(out / "study.json", json.dumps({"command": command, "results": results, "cost": cost,
                                                      "wall_s_this_invocation": time.perf_counter() - t0},
                                                     indent=2, default=float))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
