"""What the studies of one std term in the depth map share (studies 42 and 44): each trained run scored
twice on the same photos by ``stochastic-fields eval``, with the map ``train`` wrote ("today") and with
the map refitted with the term (``stochastic-fields calibrate FLAGS --no-free-path``), and the group
means the studies' rules read.

Paper split: the held-out views the tables do not score (``tables_cap_study.validation_views``);
capture split: the run's held-out photos (``eval``'s default). The run's calibration files are put
back as ``train`` left them after each run (resumable: each arm's calibration and eval are kept
under ``--work``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "benchmarks" / "studies"))

from stochastic_fields.calibration import ONE_SIGMA_LEVEL  # noqa: E402
from stochastic_fields.config import load_config  # noqa: E402
from stochastic_fields.io_utils import atomic_write_text  # noqa: E402
from study_helpers import save_results, study_command  # noqa: E402

TODAY = "today"
#: Files ``calibrate`` writes into a run (restored after the study).
CALIBRATION_FILES: tuple[str, ...] = ("calibration.json", "training_depth.npz", "training_fit.json",
                                      "free_path_calibration.json")
#: The levels every rule holds within MAX_LEVEL_GAP of nominal (99% reported).
LEVELS: tuple[str, ...] = ("50", "68", "90", "95")
MAX_LEVEL_GAP: float = 0.05


@dataclass(frozen=True)
class MapTerm:
    """The candidate arm: ``calibrate`` with ``flags``; its fitted weight is ``calibration.json``'s
    ``depth[weight_key]``, reported as ``symbol``."""

    arm: str
    flags: tuple[str, ...]
    weight_key: str
    symbol: str


def nominal(level: str) -> float:
    """The coverage a level names ("68": the one-sigma level)."""
    return ONE_SIGMA_LEVEL if level == "68" else int(level) / 100


def protocol(run: Path) -> str:
    """"paper" or "capture": the run's split."""
    return "paper" if load_config(run / "config.json").data.split == "paper" else "capture"


def scored_views(run: Path, scene: str) -> list[int] | None:
    """Paper split: the held-out views the tables do not score; otherwise None (eval's default: the
    run's held-out photos)."""
    if protocol(run) != "paper":
        return None
    from tables_cap_study import validation_views  # deferred: reads the scene

    return validation_views(scene)


def _cli(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "stochastic_fields.cli", *args], check=True)


def _put(files: Path, run: Path) -> None:
    """Make ``run``'s calibration files those saved in ``files`` (absent there: removed)."""
    for name in CALIBRATION_FILES:
        (run / name).unlink(missing_ok=True)
        if (files / name).is_file():
            shutil.copy2(files / name, run / name)


def _save(run: Path, files: Path) -> None:
    files.mkdir(parents=True, exist_ok=True)
    for name in CALIBRATION_FILES:
        if (run / name).is_file():
            shutil.copy2(run / name, files / name)


def scores(metrics_path: Path, calibration_path: Path, term: MapTerm) -> dict:
    """What the rules read from an ``eval`` metrics.json, with the map's fitted weights."""
    pooled = json.loads(metrics_path.read_text())["pooled"]
    iv, depth = pooled["depth_intervals"], pooled["depth"]
    depth_map = json.loads(calibration_path.read_text())["depth"]
    return {**{f"coverage_{n}": iv[f"coverage_{n}"] for n in (*LEVELS, "99")},
            "halfwidth_median_95": iv["halfwidth_median_95"], "interval_score_95": iv["interval_score_95"],
            "crps": iv["crps"], "coverage_68_narrowest_third": iv["coverage_68_narrowest_third"],
            "spearman": depth["spearman"], "abs_rel": depth["abs_rel"], "points": depth["num_used"],
            term.symbol: depth_map.get(term.weight_key, 0.0), "rho": depth_map.get("relative_floor", 0.0),
            "beta": depth_map.get("free_space_weight", 0.0) if depth_map.get("free_space") else 0.0}


def analyse_run(label: str, run: Path, work: Path, term: MapTerm) -> dict:
    """Both arms of one run, {"protocol", "views", "today": scores, term.arm: scores}."""
    scene = label.split(":")[0]
    views = scored_views(run, scene)
    view_args = [] if views is None else ["--views", ",".join(map(str, views))]
    original = work / "original"
    if not (original / "calibration.json").is_file():
        _save(run, original)
    out = {"protocol": protocol(run), "views": views}
    try:
        for arm in (TODAY, term.arm):
            folder = work / arm.replace(" ", "_")
            if arm == TODAY:
                files = original
            else:
                files = folder / "calibration"
                if not (files / "calibration.json").is_file():
                    _put(original, run)
                    _cli("calibrate", "--run", str(run), *term.flags, "--no-free-path")
                    _save(run, files)
            if not (folder / "metrics.json").is_file():
                _put(files, run)
                _cli("eval", "--run", str(run), *view_args, "--no-products", "--quiet", "--out", str(folder))
            out[arm] = scores(folder / "metrics.json", files / "calibration.json", term)
    finally:
        _put(original, run)  # the run as train left it
    return out


def group_means(results: dict) -> dict[str, dict[str, dict[str, float]]]:
    """{"PROTOCOL SCENE": {arm: mean of each score over the group's runs}} (arms: the dict entries)."""
    groups: dict[str, list[dict]] = {}
    for label, res in results.items():
        groups.setdefault(f"{res['protocol']} {label.split(':')[0]}", []).append(res)
    return {g: {arm: {k: float(np.mean([r[arm][k] for r in rs])) for k in rs[0][arm]}
                for arm, v in rs[0].items() if isinstance(v, dict)}
            for g, rs in sorted(groups.items())}


def level_failures(group: str, candidate: dict, today: dict | None = None) -> list[str]:
    """The levels of ``candidate`` farther than MAX_LEVEL_GAP from nominal; with ``today``, a level
    today's map already misses may stay out if it comes no farther from nominal."""
    failed = []
    for n in LEVELS:
        gap = abs(candidate[f"coverage_{n}"] - nominal(n))
        allowed = MAX_LEVEL_GAP
        if today is not None:
            allowed = max(allowed, abs(today[f"coverage_{n}"] - nominal(n)))
        if gap > allowed:
            failed.append(f"{group}: coverage at {n}% {100 * candidate[f'coverage_{n}']:.1f}% (within "
                          f"{100 * allowed:.1f} points)")
    return failed


def proper_score_failures(group: str, today: dict, candidate: dict, *, max_crps_rise: float,
                          paper_band_growth: float) -> list[str]:
    """The checks both rules share: the CRPS / depth rises by at most ``max_crps_rise`` (relative),
    the median 95% half-width / depth grows by at most ``paper_band_growth`` at the paper split and
    not at all on a capture."""
    failed = []
    if candidate["crps"] > today["crps"] * (1.0 + max_crps_rise):
        failed.append(f"{group}: CRPS {today['crps']:.4f} -> {candidate['crps']:.4f} "
                      f"(at most +{100 * max_crps_rise:.0f}%)")
    growth = candidate["halfwidth_median_95"] - today["halfwidth_median_95"]
    limit = paper_band_growth if group.startswith("paper") else 0.0
    if growth > limit:
        failed.append(f"{group}: median 95% band {100 * today['halfwidth_median_95']:.1f} -> "
                      f"{100 * candidate['halfwidth_median_95']:.1f}% (at most +{100 * limit:.1f} points)")
    return failed


def _row(name: str, arm: str, m: dict, term: MapTerm) -> str:
    cov = " / ".join(f"{100 * m[f'coverage_{n}']:.1f}" for n in (*LEVELS, "99"))
    weight = "-" if arm == TODAY else f"{m[term.symbol]:.3g}"
    return (f"| {name} | {arm} | {weight} | {cov} | {100 * m['coverage_68_narrowest_third']:.1f} | "
            f"{100 * m['halfwidth_median_95']:.1f}% | {m['interval_score_95']:.3f} | {m['crps']:.4f} | "
            f"{m['spearman']:.3f} | {m['abs_rel']:.4f} |")


def report(title: str, results: dict, command: str, term: MapTerm,
           verdict: Callable[[dict], tuple[bool, list[str]]]) -> str:
    head = [f"| run | map | {term.symbol} | cov 50 / 68 / 90 / 95 / 99 | narrowest third, cov 68 | median 95% "
            "half-width | IS95 / depth | CRPS / depth | Spearman |err|-std | abs-rel |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    lines = [f"# {title}", "", f"Command: {command}", "",
             "Scored by `stochastic-fields eval` (cross-fitted fold maps judge the intervals); paper split: the "
             "held-out views the tables do not score; capture split: the run's held-out photos.", "",
             "## Group means", ""] + head
    means = group_means(results)
    for g, arms in means.items():
        lines += [_row(g, arm, arms[arm], term) for arm in (TODAY, term.arm)]
    taken, failed = verdict(means)
    lines += ["", "## Verdict", "", "Taken: the term becomes the default." if taken else
              "Not taken; failed conditions:", *[f"- {f}" for f in failed], "", "## Runs", ""] + head
    for label, res in results.items():
        lines += [_row(f"{res['protocol']} {label}", arm, res[arm], term) for arm in (TODAY, term.arm)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None, *, doc: str, script: str, title: str, term: MapTerm,
         verdict: Callable[[dict], tuple[bool, list[str]]]) -> int:
    """A study's command line: ``--run SCENE:SEED=RUN`` (repeated), ``--work``, ``--out``; writes
    ``OUT/results.json`` after each run and ``OUT/study.md`` at the end."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="SCENE:SEED=RUN")
    p.add_argument("--work", type=Path, required=True, help="Evals and calibrations of each arm (large).")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    saved = args.out / "results.json"
    results = json.loads(saved.read_text()) if saved.is_file() else {}
    for item in args.run:
        label, sep, path = item.partition("=")
        if not sep or ":" not in label or not path:
            p.error(f"--run {item!r}: expected SCENE:SEED=RUN")
        if label not in results:
            results[label] = analyse_run(label, Path(path), args.work / label.replace(":", "_"), term)
            save_results(args.out, results)
        r = results[label]
        print(f"{label}: IS95 {r[TODAY]['interval_score_95']:.3f} -> {r[term.arm]['interval_score_95']:.3f}, "
              f"band {100 * r[TODAY]['halfwidth_median_95']:.1f} -> {100 * r[term.arm]['halfwidth_median_95']:.1f}%, "
              f"Spearman {r[TODAY]['spearman']:.3f} -> {r[term.arm]['spearman']:.3f}")
    atomic_write_text(args.out / "study.md", report(title, results, study_command(script, argv), term, verdict))
    return 0
