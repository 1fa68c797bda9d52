"""An allocator's answer does not depend on the unrelated problems it answered before.

Each problem is answered fresh (a new allocator; for ``nmpc`` also a new model cache, so that no
CasADi buffer, DAQP workspace or plan has been used before) and by one allocator object that
answers every problem in turn, forward and then backward, so that each answer comes after two
different histories. The problems are the soak's family (platoon_opt.study.problems, half of
them of its degenerate kinds) and tests/conftest.py::random_problem.

What is compared: the handed velocities (n, 2), to 1e-7 of the largest fresh speed component
(floored at 1 mm/s), and the status. The velocities are the answer (what the units drive), the
one output every allocator has; the paper's iteration has no objective, and for ``nmpc`` an
objective alone could hide another local solution, so its plan's cost is compared besides.
Warm starts may speed a solve up, never change its answer beyond that tolerance.

``nmpc`` takes a problem ``resolve_every`` steps after its plan's, of the same platoon size and
time step, for the next step of its run and starts from the plan (docs/nmpc.md, section 6); the
problems here are all posed at t = 0, so each is a cold start, as an unrelated problem must be.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pytest

from platoon_opt import Allocation, AllocationProblem
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc import compiled as nmpc_compiled
from platoon_opt.study.problems import DEGENERATE_KINDS, specs
from tests.conftest import random_problem

RELATIVE = 1e-7
# Velocities are compared relative to the largest fresh component, at least this (m/s).
VELOCITY_FLOOR = 1e-3


def problems(count: int, max_units: int, seed: int) -> list[AllocationProblem]:
    """``count`` problems of at most ``max_units`` units: the soak family's first of each
    degenerate kind, then its random ones, then ``random_problem``'s."""
    chosen, kinds = [], set(DEGENERATE_KINDS)
    for spec in specs(seed, 4000, degenerate_rate=0.5):
        if spec.n > max_units:
            continue
        if spec.kind in kinds or (spec.kind == "random" and len(chosen) < count - 2):
            kinds.discard(spec.kind)
            chosen.append(spec.build())
        if len(chosen) >= count - 2 and not kinds:
            break
    rng = np.random.default_rng(seed)
    chosen += [random_problem(rng, n) for n in (2, max_units)]
    return chosen


def assert_same_answer(fresh: Allocation, after: Allocation, what: str) -> None:
    assert after.status == fresh.status, what
    scale = max(float(np.max(np.abs(fresh.velocities))), VELOCITY_FLOOR)
    difference = float(np.max(np.abs(after.velocities - fresh.velocities)))
    assert difference <= RELATIVE * scale, f"{what}: velocities differ by {difference:.3g} m/s"


def check_history(
    make: Callable[[], object], posed: Sequence[AllocationProblem], fresh_context: Callable[[], None]
) -> list[Allocation]:
    """Answer each problem fresh (``fresh_context`` run before each), then all of them by one
    allocator forward and backward; assert the answers agree. Returns the fresh answers."""
    fresh = []
    for problem in posed:
        fresh_context()
        fresh.append(make().allocate(problem))  # type: ignore[attr-defined]
    fresh_context()
    allocator = make()
    order = [*range(len(posed)), *reversed(range(len(posed)))]
    for turn, index in enumerate(order):
        after = allocator.allocate(posed[index])  # type: ignore[attr-defined]
        what = f"{allocator.name}, problem {index} (turn {turn})"  # type: ignore[attr-defined]
        assert_same_answer(fresh[index], after, what)
        if "cost" in fresh[index].info:
            assert after.info["cost"] == pytest.approx(fresh[index].info["cost"], rel=RELATIVE), what
    return fresh


@pytest.mark.parametrize("gears", ["either", "model"])
@pytest.mark.parametrize("m", [1, 4, 50])
def test_iterative_answers_do_not_depend_on_earlier_problems(m, gears):
    posed = problems(30, 12, seed=21)
    check_history(lambda: get_allocator("iterative", max_iterations=m, gears=gears), posed, lambda: None)


@pytest.fixture
def fresh_models(monkeypatch) -> Callable[[], None]:
    """Empties nmpc's process-wide model cache when called (the original is restored after)."""

    def empty() -> None:
        monkeypatch.setattr(nmpc_compiled, "_HORIZONS", {})

    return empty


@pytest.mark.parametrize(
    "options",
    # 0.02 s intervals have rate rows: DAQP solves every step's QP (docs/nmpc.md, section 4.3).
    [{}, {"gears": "rule"}, {"resolve_every": 2}],
    ids=["defaults", "rule-gears", "rate-rows"],
)
def test_nmpc_answers_do_not_depend_on_earlier_problems(options, fresh_models):
    posed = problems(10, 4, seed=5)
    fresh = check_history(lambda: get_allocator("nmpc", **options), posed, fresh_models)
    # The problems exercise the solve (not only the fallback).
    assert sum(not answer.fell_back for answer in fresh) >= len(posed) - 2


def test_nmpc_ipopt_answers_do_not_depend_on_earlier_problems(fresh_models):
    posed = problems(4, 3, seed=9)
    options = {"backend": "ipopt", "intervals": 5}
    fresh = check_history(lambda: get_allocator("nmpc", **options), posed, fresh_models)
    assert sum(not answer.fell_back for answer in fresh) >= 2
