"""Score the tables' S-NeRF (default) runs on the paper split's validation views: the held-out photos
the tables do not score (a measurement; it decides nothing).

Each ``--run SEED=OUT`` names the ``--out`` folder of one ``benchmarks/eval_tables.py --methods
snerf_default --seed SEED`` run. Per scene the run is scored by ``stochastic-fields eval --views``
on the paper split's test views other than the tables' four (``tables_cap_study.validation_views``:
fern 12, flower 23), as a user scores a run (depth against the SCORE capture points those photos
see, intervals cross-fitted); the output goes to ``--work``/seed_SEED/SCENE (resumable: a finished
eval is kept). ``depth_interval_seeds.py --evals SEED=WORK/seed_SEED`` then tabulates them beside
the tables' own rows, with issue 36's checks::

    python benchmarks/studies/paper_validation_views.py --run 0=runs/tables_35 --run 1=runs/tables_35_seed_1 \\
        --run 2=runs/tables_35_seed_2 --work runs/paper_validation_35
    python benchmarks/studies/depth_interval_seeds.py --evals 0=runs/paper_validation_35/seed_0 ... --out OUT

It answers whether a level the tables' four views miss is missed by the split's other photos too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from depth_interval_seeds import parse_run  # noqa: E402
from tables_cap_study import SCENES, score_run, validation_views  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=parse_run, action="append", required=True, metavar="SEED=OUT",
                        help="an eval_tables.py --out folder holding S-NeRF (default), and its seed (repeatable)")
    parser.add_argument("--work", type=Path, required=True, help="where each eval is written (resumable)")
    args = parser.parse_args(argv)
    views = {scene: validation_views(scene) for scene in SCENES}
    for seed, out in sorted(args.run):
        for scene in SCENES:
            run = out / scene / "snerf_default"
            if not (run / "checkpoint.pt").is_file():
                parser.error(f"{run}: no finished S-NeRF (default) run (checkpoint.pt missing)")
            print(f"seed {seed} {scene}: {len(views[scene])} validation views ({', '.join(map(str, views[scene]))})",
                  flush=True)
            score_run(run, views[scene], args.work / f"seed_{seed}" / scene)
    return 0


if __name__ == "__main__":
    sys.exit(main())
