"""``stochastic-fields calibrate``: fit a run's uncertainty recalibration (``calibration.calibrate_run``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

import argparse
import math

from ..defaults import (CALIBRATION_PAIR_POINTS, CALIBRATION_POINTS, CROSS_FIT_FOLDS, DEFAULT_CALIBRATION_PAIR_POINTS,
                        DEFAULT_CALIBRATION_POINTS, DEPTH_EDGE_TERM, DEPTH_FREE_SPACE, DEPTH_PARALLAX_TERM,
                        DEPTH_RELATIVE_FLOOR, DEPTH_STD_FLOOR, FREE_PATH_RECALIBRATION)


def add_arguments(p) -> None:
    p.add_argument("--run", required=True, help="Trained run folder.")
    p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
    p.add_argument("--seed", type=int, default=0, help="Seed of the K draws of the calibration renders.")
    p.add_argument("--points", choices=CALIBRATION_POINTS, default=DEFAULT_CALIBRATION_POINTS,
                   help="Capture points to fit on: 'held-out' (default) fits every point the training did not "
                        "fit, so the map sees most of the scene's surfaces, and stores its cross-fitted fold "
                        f"maps ({CROSS_FIT_FOLDS} folds of the SCORE blocks) that eval scores its intervals with; "
                        "'calibrate' fits the CALIBRATE points only (docs/uncertainty.md, studies 18 and 18b).")
    p.add_argument("--pair-points", choices=CALIBRATION_PAIR_POINTS, default=DEFAULT_CALIBRATION_PAIR_POINTS,
                   help="Which capture points a calibration view (halfway between two training views) renders: "
                        "'both' (default), those both views of its pair observed, or 'either', those one of them "
                        "observed (docs/studies.md, study 38: either holds paper-split fern's photos at every level "
                        "but widens every band by about 40%%).")
    p.add_argument("--std-floor", action=argparse.BooleanOptionalAction, default=DEPTH_STD_FLOOR,
                   help="Fit a depth std floor tau first, so that depth_std = s * sqrt(raw^2 + tau^2) "
                        f"(docs/uncertainty.md, study 11; default: {'on' if DEPTH_STD_FLOOR else 'off'}).")
    p.add_argument("--free-space", action=argparse.BooleanOptionalAction, default=DEPTH_FREE_SPACE,
                   help="Check each rendered depth against the training views' free space: depth_std = "
                        "s * sqrt(raw^2 + (beta e)^2 + ...), e how far the point lies in front of a training view's "
                        "rendered surface, also written as depth_free_space (renders the training views once into "
                        "RUN/training_depth.npz; the weight beta is fitted, 0 where the check does not help; "
                        "docs/uncertainty.md, studies 22d and 22e: narrower bands that hold on every scene measured; "
                        f"default: {'on' if DEPTH_FREE_SPACE else 'off'}).")
    p.add_argument("--free-space-weight", type=_weight, default=None, metavar="BETA",
                   help="Weight of the free-space violation, depth_std = s * sqrt(raw^2 + (BETA e)^2 + ...) "
                        "(default: fitted with the depth-proportional term by the CRPS on the map's points; 0 "
                        "keeps the map unchecked where the check does not help; docs/uncertainty.md, studies 22d "
                        "and 22e).")
    p.add_argument("--relative-floor", action=argparse.BooleanOptionalAction, default=DEPTH_RELATIVE_FLOOR,
                   help="Fit a depth-proportional std term rho, so that depth_std = s * sqrt(raw^2 + (rho depth)^2): "
                        "a pixel rendered on the wrong surface errs by a fraction of its depth, not a multiple of its "
                        "std, and without the term those few pixels widen every 95%% band (docs/uncertainty.md, "
                        f"studies 20 and 20b; default: {'on' if DEPTH_RELATIVE_FLOOR else 'off'}).")
    p.add_argument("--edge-term", action=argparse.BooleanOptionalAction, default=DEPTH_EDGE_TERM,
                   help="Add an occlusion-edge term, depth_std = s * sqrt(raw^2 + ... + (gamma Delta)^2), Delta the range "
                        "of the depths rendered within 2 pixels, written as depth_edge: a pixel beside an occlusion "
                        "edge may render the other surface (8 more renders of the calibration points; gamma fitted, "
                        f"0 where edges do not explain the errors; docs/studies.md, study 30; default: "
                        f"{'on' if DEPTH_EDGE_TERM else 'off'}).")
    p.add_argument("--edge-weight", type=_edge_weight, default=None, metavar="GAMMA",
                   help="Weight of the occlusion-edge size with --edge-term (default: fitted with the depth-proportional "
                        "term by the CRPS on the map's points).")
    p.add_argument("--parallax-term", action=argparse.BooleanOptionalAction, default=DEPTH_PARALLAX_TERM,
                   help="Add the training views' parallax term, depth_std = s * sqrt(raw^2 + ... + (kappa depth / "
                        "max(sin theta, 0.01))^2), theta the widest angle between training views that see the rendered "
                        "point, written as depth_parallax (degrees): a surface the photos saw with little parallax is "
                        "placed less surely (renders the training views once into RUN/training_depth.npz; kappa "
                        "fitted, 0 where the parallax does not explain the errors; docs/studies.md, study 42; "
                        f"default: {'on' if DEPTH_PARALLAX_TERM else 'off'}).")
    p.add_argument("--parallax-weight", type=_parallax_weight, default=None, metavar="KAPPA",
                   help="Weight of the parallax term with --parallax-term (default: fitted with the depth-proportional "
                        "term by the CRPS on the map's points).")
    p.add_argument("--free-path", action=argparse.BooleanOptionalAction, default=FREE_PATH_RECALIBRATION,
                   help="Also fit the recalibration of free-path's P(free) on segments whose answer the held-out "
                        "points know (RUN/free_path_calibration.json; docs/uncertainty.md; default: "
                        f"{'on' if FREE_PATH_RECALIBRATION else 'off'}).")


def _weight(text: str, option: str = "--free-space-weight") -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"{option}: expected a finite number >= 0, got {text!r}")
    return value


def _edge_weight(text: str) -> float:
    return _weight(text, "--edge-weight")


def _parallax_weight(text: str) -> float:
    return _weight(text, "--parallax-weight")


def run(args) -> None:
    from ..calibration import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
    if args.free_path:
        from pathlib import Path

        from ..products.free_path_calibration import recalibrate_free_path
        from ..trainer import load_trained_model

        _, model, dataset = load_trained_model(Path(args.run), device=args.device)
        recalibrate_free_path(args.run, model, dataset, seed=args.seed)
