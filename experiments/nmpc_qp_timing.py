"""The receding-horizon SQP's QPs: the active-set method on both forms of the Hessian against DAQP.

Runs the first ``--duration`` seconds of each paper scenario in closed loop, keeps every QP the
SQP hands to ``active_set_newton`` (box constraints alone, the default options), and then
solves each of them again: ``active_set_newton`` on the per-unit split and on the dense form
(``box_qp.DENSE_UP_TO`` chooses between them in the SQP), each from its previous QP's sets as
in the SQP, and DAQP (``casadi.conic``, called on preallocated buffers as the SQP calls it) on
the dense Hessian. Reports the median and p95 times, how often the active sets cycled, and the
largest relative difference of the objective values to DAQP's.

    python experiments/nmpc_qp_timing.py --duration 3 --option intervals=20 --out FILE
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402

from platoon_opt import load_scenario, simulate  # noqa: E402
from platoon_opt.solvers import get_allocator  # noqa: E402
from platoon_opt.solvers.nmpc import box_qp, solve  # noqa: E402
from platoon_opt.solvers.nmpc.box_qp import DENSE_UP_TO, BlockLowRank, BoxSolution, active_set_newton  # noqa: E402
from platoon_opt.solvers.nmpc.compiled import Evaluator  # noqa: E402
from platoon_opt.study.config import parse_options  # noqa: E402
from platoon_opt.study.machine import machine  # noqa: E402


def captured_qps(duration: float, options: dict) -> list[tuple]:
    """(hessian, gradient, lower, upper) of every active-set solve in the closed loops."""
    qps: list[tuple] = []

    def keep(hessian, gradient, lower, upper, guess=None):
        qps.append((BlockLowRank(hessian.blocks, hessian.coupling), gradient, lower, upper))
        return active_set_newton(hessian, gradient, lower, upper, guess)

    solve.active_set_newton = keep
    try:
        for name in ("paper_no_obstacles", "paper_obstacles"):
            simulate(load_scenario(name), get_allocator("nmpc", **options), duration=duration)
    finally:
        solve.active_set_newton = active_set_newton
    return qps


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--duration", type=float, default=3.0)
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--out", type=Path, help="append the result to this markdown file")
    args = parser.parse_args()
    options = parse_options(args.option)
    load = os.getloadavg()[0]
    qps = captured_qps(args.duration, options)
    size = qps[0][1].size
    daqp = Evaluator(
        ca.conic(
            "daqp",
            "daqp",
            {"h": ca.Sparsity.dense(size, size), "a": ca.Sparsity.dense(0, size)},
            {"error_on_fail": False},
        )
    )
    empty = np.zeros(0)
    # The active-set method on each form of the Hessian (box_qp.DENSE_UP_TO picks one in the
    # SQP): each form keeps its own chain of guesses, as the SQP would.
    forms = {"split": 0, "dense form": size}
    times: dict[str, list[float]] = {"DAQP": [], **{form: [] for form in forms}}
    guesses: dict[str, BoxSolution | None] = dict.fromkeys(forms)
    differences, cycled = [], dict.fromkeys(forms, 0)
    for hessian, gradient, lower, upper in qps:
        dense = hessian.dense()
        start = time.perf_counter()
        reference = daqp(dense, gradient, empty, empty, empty, lower, upper)[0].copy()
        times["DAQP"].append(time.perf_counter() - start)
        for form, dense_up_to in forms.items():
            box_qp.DENSE_UP_TO = dense_up_to
            fresh = BlockLowRank(hessian.blocks, hessian.coupling)  # nothing cached
            start = time.perf_counter()
            solution = active_set_newton(fresh, gradient, lower, upper, guesses[form])
            times[form].append(time.perf_counter() - start)
            guesses[form] = solution if solution.x is not None else None
            if solution.x is None:
                cycled[form] += 1
                continue
            found, best = (0.5 * x @ dense @ x + gradient @ x for x in (solution.x, reference))
            differences.append(abs(found - best) / max(1.0, abs(best)))
    box_qp.DENSE_UP_TO = DENSE_UP_TO
    medians = "; ".join(
        f"{name} median {np.median(ms := np.array(values) * 1e3):.2f} ms, p95 {np.percentile(ms, 95):.2f}"
        for name, values in times.items()
    )
    line = (
        f"`nmpc` {options or '(defaults)'}: {len(qps)} QPs of {size} variables from the first "
        f"{args.duration:g} s of both scenarios; {medians}; cycled {cycled}; largest relative "
        f"objective difference to DAQP {max(differences):.1e}"
    )
    print(line)
    if args.out is not None:
        with args.out.open("a") as out:
            out.write(
                f"## QP solvers, {time.strftime('%Y-%m-%d %H:%M')}, load average before "
                f"{load:.2f}, machine {machine()}\n\n- {line}\n\n"
            )


if __name__ == "__main__":
    main()
