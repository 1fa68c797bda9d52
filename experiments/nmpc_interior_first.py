"""Which of the split Hessian's QP solvers should come first: closed loops of `nmpc` with the
interior point first and with the active-set exchange first (``solve.INTERIOR_FIRST_FROM``),
alternating, CPU time of each (docs/nmpc.md, section 4.3).

    python experiments/nmpc_interior_first.py units_50 units_200 --duration 2 --rounds 2
    python experiments/nmpc_interior_first.py units_200 --units 100

``--units`` changes the scenario's platoon size (the formation keeps its variance).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from platoon_opt import load_scenario, simulate  # noqa: E402
from platoon_opt.solvers import get_allocator  # noqa: E402
from platoon_opt.solvers.nmpc import solve  # noqa: E402

ORDERS = {"interior point first": 0, "exchange first": 10**9}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenarios", nargs="+")
    parser.add_argument("--duration", type=float, default=2.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--units", type=int, help="platoon size instead of the scenario's")
    args = parser.parse_args()
    for name in args.scenarios:
        scenario = load_scenario(name)
        if args.units is not None:
            scenario = dataclasses.replace(scenario, n=args.units)
        n = scenario.n
        for _ in range(args.rounds):
            for order, first_from in ORDERS.items():
                solve.INTERIOR_FIRST_FROM = first_from
                start = time.process_time()
                trajectory = simulate(scenario, get_allocator("nmpc"), seed=0, duration=args.duration)
                cpu = time.process_time() - start
                print(
                    f"{name} n={n} {args.duration:g} s, {order}: {cpu:.1f} s of CPU, mean x at the end "
                    f"{trajectory.x[-1].mean():.9f} m, fallbacks {int(trajectory.fell_back.sum())}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
