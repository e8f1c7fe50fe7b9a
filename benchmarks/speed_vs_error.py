"""Speed against error (issue 5): the same benchmark as ``stochastic-fields bench``.

    .venv/bin/python benchmarks/speed_vs_error.py --quick --out benchmarks/results

See ``stochastic_fields_bench.speed`` for what is measured; ``--help`` lists the budget flags.
"""

from __future__ import annotations

import argparse

from stochastic_fields_bench import bench_command, speed


def main() -> None:
    parser = argparse.ArgumentParser(description=speed.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_command.add_arguments(parser)
    bench_command.run(parser.parse_args())


if __name__ == "__main__":
    main()
