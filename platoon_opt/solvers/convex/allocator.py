"""``ConvexAllocator``: one convex program per step (``formulation``), solved by a backend
(``backends``), behind the names ``qp``, ``qp-projection``, ``cone``, ``cone-projection`` and
``casadi-qp`` (``platoon_opt.solvers.convex``). With ``backend="dual"`` the dual allocator
(``platoon_opt.solvers.dual``) solves the same program instead, and the compiled engine runs it
(``compiled``).

Every unit uses the sector of the gear the model's gear rule chose (``problem.gear``) or, with
``gears="either"``, of the gear whose sector lies nearer its nominal velocity (with
``gears="catching-up"`` only while the platoon catches up), optionally
narrowed to what the steering reaches in one step, the nominal velocities steered alike
(``rate_aware``); units under the precedence rule are pinned or anchored (docs/programs.md,
section 3). Failures (section 5): first every
backend that solves the program asked for (``backend``, then ``fallbacks``), then the ``dual``
allocator on the same program (exact, a different method), then the backends that solve another
program (a ``cone`` variant's fallbacks without cones solve the inscribed polygon), last the
nominal velocity projected onto each unit's set. A backend fails when it raises, returns no
solution, reports anything but an exact solve, or returns a point that is not finite or leaves its
constraints by more than ``FEASIBILITY_TOLERANCE``. The status is "optimal" when the first backend
succeeds, else ``"fallback:<backend>:<reason>; ...-><what was used>"``; an answer to another
program sets ``Allocation.program_changed`` and ``info["program"]``. ``allocate`` never raises
and never returns NaN.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from platoon_opt.allocation import Allocation
from platoon_opt.engine import CompiledStep
from platoon_opt.errors import ConfigurationError
from platoon_opt.limits import inner_projection, unit_rows
from platoon_opt.problem import AllocationProblem
from platoon_opt.scenarios import Scenario
from platoon_opt.solvers.convex import formulation as fm
from platoon_opt.solvers.convex.backends import (
    BackendFailure,
    Workspaces,
    known_backends,
    solve,
    supports_cone,
)
from platoon_opt.solvers.dual.allocator import DualAllocator
from platoon_opt.solvers.options import Choice, Choices, Option, Table, check_options, options_of
from platoon_opt.solvers.programs import (
    ANCHOR_WEIGHT,
    EPS,
    GEARS,
    PRECEDENCE,
    PRIORITY,
    RATE_AWARE,
    READING,
    RHO,
    SIDES,
    SPEED,
    achievable_part_excess,
    default_precedence,
    name_parts,
    posed,
    program_promise,
)
from platoon_opt.solvers.safety import SafetyOptions, loose_padding, safe_handout, slack_info

# Largest accepted violation of a constraint row (m/s); units whose rows do not hold exactly
# are then moved into their sets. Equality rows are checked to EQUALITY_TOLERANCE relative to
# 1 + their largest right-hand side.
FEASIBILITY_TOLERANCE = 1e-7
EQUALITY_TOLERANCE = 1e-6


# A solution: velocities handed out and their achievable parts (n, 2), m/s; what answered
# (backends, "dual", "stage1"); iterations; extra info; and the program solved
# (``info["program"]``: "as asked", "polygon", "stage 1").
Solution = tuple[np.ndarray, np.ndarray, str, int, dict[str, Any], str]

# The backends depend on what is installed; ``platoon-opt allocators qp`` lists them.
BACKEND_NAMES = Choice(known_backends, "a backend: clarabel, osqp, qpsolvers:<solver> or casadi:<plugin>")
# "dual": the same program solved by the dual allocator, which the compiled engine runs.
DUAL = "dual"
BACKEND = Option(
    "backend",
    "clarabel",
    "the backend tried first (platoon_opt.solvers.convex.backends), or dual: the dual allocator "
    "solves the same program, compiled in the engine",
    Choice(
        lambda: (*known_backends(), DUAL),
        "a backend: clarabel, osqp, qpsolvers:<solver>, casadi:<plugin> or dual",
    ),
)
FALLBACKS = Option(
    "fallbacks",
    None,
    "backends tried next, in order; None: OSQP after Clarabel, Clarabel after any other",
    Choices(BACKEND_NAMES),
)
SOLVER_OPTIONS = Option("solver_options", None, "extra settings of the first backend", Table())


@dataclass(frozen=True)
class ConvexAllocator(SafetyOptions):
    """One convex program per step (see the module docstring), solved by a backend.

    Attributes (the options, declared once in ``platoon_opt.solvers.programs`` and here):
        label: the registered name, used in ``name``.
        reading: "achievable-first" (qp, cone) or "task-exact" (qp-projection, cone-projection).
        speed: "polygon" (inscribed regular polygon, ``sides``) or "cone" (exact, Clarabel).
        rho: weight of ``||J q' - u||^2`` (achievable-first, ``priority="weighted"``). The
            effective weight of task direction k is rho times the k-th eigenvalue of J J^T
            (1/n for a mean, 4 var/(n-1) for a variance).
        eps: weight of ``||a - q'_d||^2`` (task-exact): picks, among the velocities that meet
            the task and are equally close to achievable, the nearest to the nominal one. It
            also pulls the answer toward q'_d by about 2 eps (relative) when the task is out
            of reach; below about 1e-6 the program is ill-conditioned (Clarabel reported
            infeasibility on most random problems at 1e-8).
        priority: "weighted" or "strict" (achievable-first only).
        sides: polygon sides for the speed disk.
        rate_aware: narrow each sector to what the steering reaches within dt (the safe sets
            of barriers are always narrowed: docs/safety.md, section 6) and pose the program on
            the nominal velocities as the units drive them (``programs.posed``).
        gears: "model" (each unit's sector in the gear its gear rule chose), "either" (in the
            gear whose sector lies nearer its nominal velocity) or "catching-up" (the nearer gear
            while the platoon catches up, the gear rule's otherwise): ``programs.posed``.
        backend, fallbacks, solver_options: which backends solve the program, in which order
            (a backend without cones solves the polygon program instead), and extra settings
            of the first (e.g. {"max_iter": 200}).
        safety, barrier_rate, safety_distance, obstacle_margin, neighbour_cutoff, turning_room: barrier
            constraints in every unit's set (``SafetyOptions``; docs/safety.md). With them the
            task-exact reading hands out c, the safe achievable velocity nearest to a, instead of a.
        precedence, anchor_weight: how units under the paper's precedence rule keep their
            avoidance velocity p_i (their nominal velocity projected onto their achievable set):
            "pin" fixes them at p_i; "anchor" keeps them in the program, drawn to p_i with
            ``anchor_weight`` (see ``formulation.Setup``); None is the reading's default
            (``programs.default_precedence``).
    """

    label: str = "qp"
    reading: str = READING.field()
    speed: str = SPEED.field()
    rho: float = RHO.field()
    eps: float = EPS.field()
    priority: str = PRIORITY.field()
    sides: int = SIDES.field()
    rate_aware: bool = RATE_AWARE.field()
    gears: str = GEARS.field()
    backend: str = BACKEND.field()
    fallbacks: tuple[str, ...] | None = FALLBACKS.field()
    solver_options: Mapping[str, Any] | None = SOLVER_OPTIONS.field(hash=False)
    precedence: str | None = PRECEDENCE.field()
    anchor_weight: float = ANCHOR_WEIGHT.field()
    _workspaces: Workspaces = dataclasses.field(
        default_factory=Workspaces, init=False, repr=False, compare=False
    )
    # The backends in the order tried: ``backend``, then ``fallbacks`` (None resolved), split into
    # those that solve the program asked for and those that solve the polygon instead of the cone.
    _backends: tuple[str, ...] = dataclasses.field(init=False, repr=False, compare=False)
    _same: tuple[str, ...] = dataclasses.field(init=False, repr=False, compare=False)
    _other: tuple[str, ...] = dataclasses.field(init=False, repr=False, compare=False)
    # The dual allocator posing the same program: the exact fallback before another program.
    _exact: DualAllocator | None = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_options(self, self.label)
        if self.precedence is None:
            object.__setattr__(self, "precedence", default_precedence(self.reading))
        if self.priority == "strict" and self.reading == "task-exact":
            raise ValueError("priority='strict' applies to the achievable-first reading (qp, cone)")
        if self.priority == "strict" and self.precedence == "anchor":
            # Stage 1 has no deviation term, so anchored units would take the task freely.
            raise ValueError("priority='strict' needs precedence='pin'")
        if self.speed == "cone" and not (supports_cone(self.backend) or self.backend == DUAL):
            raise ValueError(f"the speed cone needs backend 'clarabel' or 'dual', got {self.backend!r}")
        fallbacks = self.fallbacks
        if fallbacks is None:
            fallbacks = ("osqp",) if self.backend.endswith("clarabel") else ("clarabel",)
        object.__setattr__(self, "fallbacks", fallbacks)
        backends = (self.backend, *fallbacks)
        same = tuple(b for b in backends if self.speed != "cone" or supports_cone(b))
        object.__setattr__(self, "_backends", backends)
        object.__setattr__(self, "_same", same)
        object.__setattr__(self, "_other", tuple(b for b in backends if b not in same))
        object.__setattr__(
            self,
            "_exact",
            DualAllocator(
                reading=self.reading,
                speed=self.speed,
                rho=self.rho,
                eps=self.eps,
                sides=self.sides,
                rate_aware=self.rate_aware,
                gears=self.gears,
                precedence=self.precedence,
                anchor_weight=self.anchor_weight,
                priority=self.priority,
                **{option.name: getattr(self, option.name) for option in options_of(SafetyOptions)},
            )
            if self.rho > 0
            else None,
        )

    @property
    def name(self) -> str:
        """E.g. "qp(rho=1000, osqp)", "qp(strict, osqp)", "cone-projection(eps=0.0001, clarabel)"."""
        if self.reading == "task-exact":
            parts = [f"eps={self.eps:g}"]
        else:
            parts = ["strict" if self.priority == "strict" else f"rho={self.rho:g}"]
        parts.append(self.backend)
        if self.speed == "polygon" and self.sides != SIDES.default:
            parts.append(f"sides={self.sides}")
        parts += name_parts(self.reading, self.rate_aware, self.gears, self.precedence, self.anchor_weight)
        parts += self.safety_name()
        return f"{self.label}({', '.join(parts)})"

    @property
    def promise(self) -> str:
        return program_promise(self.reading, self.rate_aware, self.gears)

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        return achievable_part_excess(problem, allocation, self.rate_aware, self.gears)

    @property
    def exact(self) -> DualAllocator | None:
        """The dual allocator posing the same program (None when rho = 0)."""
        return self._exact

    def compiled(self, scenario: Scenario) -> CompiledStep | None:
        """With ``backend="dual"``, the dual allocator's kernel for this program (the engine runs
        it); else None: the backends are host libraries."""
        if self.backend != DUAL or self._exact is None:
            return None
        return self._exact.compiled(scenario)

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """Velocities (n, 2) for one step; see the module docstring for the status."""
        if self.backend == DUAL and self._exact is not None:
            return dataclasses.replace(self._exact.allocate(problem), allocator=self.name)
        problem = posed(problem, self.rate_aware, self.gears)
        start = time.perf_counter()
        failures: list[str] = []
        setup = solution = None
        try:
            setup = self.setup(problem)
            setup, solution = self._optimal(problem, setup, failures, self._same)
            if solution is None or solution[5] != "as asked":  # failed, or strict's stage 1 alone
                solution = self._dual(problem, failures) or solution
            if solution is None and self._other:
                # The setup of the speed model solved: a backend without cones solves the polygon.
                setup, solution = self._optimal(problem, setup, failures, self._other)
        except ConfigurationError:
            raise
        except Exception as error:  # a formulation error must not end a run either
            failures.append(f"error:{type(error).__name__}")
        if solution is not None:
            velocities, achievable, used, iterations, extra, program = solution
        else:  # every backend failed, or the formulation raised
            velocities = achievable = self._projection(problem, setup)
            used, iterations, extra, program = "projection", 0, {}, "projection"
        status = "optimal" if not failures else f"fallback:{'; '.join(failures)}->{used}"
        stage = "deviation" if self.priority == "strict" else "joint"
        safety: dict[str, Any] = {}
        handed = velocities
        if setup is not None and setup.safe is not None:
            safety.update(slack_info(setup.safe))
            if self.reading == "task-exact":
                handout = safe_handout(problem, self.safety_for(problem), setup.safe, velocities, achievable)
                handed = handout.velocities
                safety.update(
                    task_exact_velocity=velocities, held_units=handout.held, escaping_units=handout.escaping
                )
            else:
                handed = achievable
        return Allocation.of(
            problem,
            handed,
            allocator=self.name,
            status=status,
            iterations=iterations,
            solve_time=time.perf_counter() - start,
            fell_back=bool(failures),
            program_changed=program != "as asked",
            backend=used,
            program=program,
            objective=None if setup is None else fm.objective(problem, setup, velocities, achievable, stage),
            achievable=achievable,
            failures=tuple(failures),
            **extra,
            **safety,
        )

    def program(
        self, problem: AllocationProblem, stage: str = "joint", target: np.ndarray | None = None
    ) -> fm.Program:
        """The program this allocator poses for ``problem``, in its own speed model: what its first
        backend is given at ``stage`` ("joint"; under ``priority="strict"`` "task", then
        "deviation" toward the stage-1 task velocity ``target``, ``info["stage1_task_velocity"]``).

        Raises:
            ValueError: a stage this allocator's reading does not have.
        """
        problem = posed(problem, self.rate_aware, self.gears)
        return fm.build(problem, self.setup(problem), stage, target)

    def setup(self, problem: AllocationProblem, speed: str | None = None) -> fm.Setup:
        """The fixed data of this step: unit rows (with barrier rows when safety is on), the
        precedence velocities and which units are pinned or anchored."""
        speed = speed or self.speed
        max_speed = problem.limits.max_speed
        sets = problem.achievable(rate_aware=self.rate_aware)
        interior = 0.5 * max_speed * sets.unit_vectors((sets.lower + sets.upper) / 2)
        params, safe = self.safety_for(problem), None
        if params.enabled:
            safe = problem.safe_sets(params, speed=speed, sides=self.sides)
            normals, offsets = loose_padding(sets, safe, max_speed)
            precedence, interior = safe.project(problem.nominal), safe.project(interior)
        else:
            normals, offsets = unit_rows(sets, speed, self.sides, max_speed)
            precedence = inner_projection(problem.nominal, sets, speed, self.sides)
        none = np.zeros(problem.n, dtype=bool)
        return fm.Setup(
            reading=self.reading,
            speed=speed,
            normals=normals,
            offsets=offsets,
            precedence=precedence,
            interior=interior,
            pinned=problem.exempt.copy() if self.precedence == "pin" else none,
            anchored=problem.exempt.copy() if self.precedence == "anchor" else none,
            rho=float(self.rho),
            eps=float(self.eps),
            anchor_weight=float(self.anchor_weight),
            safe=safe,
        )

    def _projection(self, problem: AllocationProblem, setup: fm.Setup | None) -> np.ndarray:
        """The last resort (n, 2): each unit's precedence velocity p_i, its nominal velocity
        projected onto its (safe) set; without the setup, which raised, onto its achievable set."""
        if setup is not None:
            return setup.precedence
        sets = problem.achievable(rate_aware=self.rate_aware)
        return inner_projection(problem.nominal, sets, self.speed, self.sides)

    def _optimal(
        self, problem: AllocationProblem, setup: fm.Setup, failures: list[str], backends: tuple[str, ...]
    ) -> tuple[fm.Setup, Solution | None]:
        """The setup of the speed model solved and the solution by the first of ``backends`` that
        succeeds (see ``Solution``); None if every one failed."""
        setups = {self.speed: setup}
        if np.all(setup.pinned):
            return setup, (setup.precedence, setup.precedence, "pinned", 0, {}, "as asked")
        if self.priority == "weighted":
            solved = self._solve(problem, setups, "joint", None, failures, backends=backends)
            if solved is None:
                return setup, None
            program, x, used, iterations = solved
            used_setup, velocities, achievable = self._unpack(problem, program, x, setups)
            return used_setup, (velocities, achievable, used, iterations, {}, self._program(program))
        first = self._solve(problem, setups, "task", None, failures, backends=backends)
        if first is None:
            return setup, None
        program, x, used, iterations = first
        used_setup, stage1, _ = self._unpack(problem, program, x, setups)
        target = problem.jacobian.apply(stage1)
        # Stage 2 keeps stage 1's speed model: a cone stage 2 toward a polygon's best task velocity
        # would serve less of the task than the cone can.
        second = self._solve(
            problem,
            setups,
            "deviation",
            target,
            failures,
            "polygon" if program.cone_columns is None else None,
            # On stage 1's polygon every backend solves stage 2 (Clarabel too).
            backends if self._program(program) == "as asked" else None,
        )
        extra = {"stage1": stage1, "stage1_task_velocity": target}
        if second is None:
            return used_setup, (stage1, stage1, "stage1", iterations, extra, "stage 1")
        program, x, used2, iterations2 = second
        used_setup, velocities, achievable = self._unpack(problem, program, x, setups)
        return used_setup, (
            velocities,
            achievable,
            used if used == used2 else f"{used}+{used2}",
            iterations + iterations2,
            extra,
            self._program(program),
        )

    def _program(self, program: fm.Program) -> str:
        """What ``info["program"]`` says of a solution of ``program``: "as asked", or "polygon"
        (a cone variant's program solved on the inscribed polygon)."""
        return "polygon" if self.speed == "cone" and program.cone_columns is None else "as asked"

    def _dual(self, problem: AllocationProblem, failures: list[str]) -> Solution | None:
        """The program asked for, solved by the ``dual`` allocator (the same program, exactly:
        docs/dual.md); None, with the reason in ``failures``, if it fell back."""
        if self._exact is None:
            return None
        allocation = self._exact.allocate(problem)
        if allocation.fell_back:
            failures.append(f"dual:{allocation.status}")
            return None
        extra = {}
        if "stage1_task_velocity" in allocation.info:
            extra["stage1_task_velocity"] = np.asarray(allocation.info["stage1_task_velocity"])
        used = "dual" if allocation.status == "optimal" else f"dual({allocation.status})"
        achievable = np.asarray(allocation.info["achievable"])
        velocities = np.asarray(allocation.info.get("task_exact_velocity", allocation.velocities))
        return velocities, achievable, used, allocation.iterations, extra, "as asked"

    def _unpack(
        self, problem: AllocationProblem, program: fm.Program, x: np.ndarray, setups: dict[str, fm.Setup]
    ) -> tuple[fm.Setup, np.ndarray, np.ndarray]:
        """The setup of the speed model the backend solved, the velocities handed to the units and
        their achievable parts (n, 2). The achievable parts are moved into their sets: an
        accepted x meets each row to FEASIBILITY_TOLERANCE, which at a corner of a set leaves it up
        to that over sin(half the corner's angle) outside (1.5e-7 m/s seen)."""
        setup = setups["polygon" if program.cone_columns is None else "cone"]
        velocities, achievable = program.unpack(x)
        if self.reading == "task-exact":  # an anchored unit's achievable part is p_i
            achievable = np.where(setup.anchored[:, None], setup.precedence, achievable)
        outside = np.any(np.einsum("ikj,ij->ik", setup.normals, achievable) > setup.offsets, axis=1)
        if program.cone_columns is not None:
            outside |= np.einsum("ij,ij->i", achievable, achievable) > problem.limits.max_speed**2
        # Pinned units sit at their precedence velocity, already inside.
        outside &= ~setup.pinned
        if outside.any():
            if setup.safe is not None:
                inside = setup.safe.project(achievable)
            else:
                inside = inner_projection(
                    achievable, problem.achievable(rate_aware=self.rate_aware), setup.speed, self.sides
                )
            achievable = np.where(outside[:, None], inside, achievable)
        return setup, (achievable if self.reading == "achievable-first" else velocities), achievable

    def _solve(
        self,
        problem: AllocationProblem,
        setups: dict[str, fm.Setup],
        stage: str,
        target: np.ndarray | None,
        failures: list[str],
        speed_model: str | None = None,
        backends: tuple[str, ...] | None = None,
    ) -> tuple[fm.Program, np.ndarray, str, int] | None:
        """Try ``backends`` (None: all of them) in order; return (program, x, backend, iterations)
        or None. The speed model is ``speed_model`` if given, else the allocator's where the
        backend has cones."""
        for backend in self._backends if backends is None else backends:
            speed = speed_model or (self.speed if supports_cone(backend) else "polygon")
            label = backend if speed == self.speed else f"{backend}(polygon)"
            try:
                if speed not in setups:
                    setups[speed] = self.setup(problem, speed)
                program = fm.build(problem, setups[speed], stage, target)
                options = (self.solver_options or {}) if backend == self.backend else {}
                solved = solve(program, backend, self._workspaces, options)
                reason = self._reject(program, solved.x)
                if reason is not None and solved.reused:
                    # State kept from unrelated programs must not change the answer.
                    solved = solve(program, backend, self._workspaces, options, fresh=True)
                    reason = self._reject(program, solved.x)
            except BackendFailure as error:
                reason = str(error)
            except Exception as error:  # a backend or binding error: record its type, go on
                reason = type(error).__name__
            if reason is None:
                return program, solved.x, label, solved.iterations
            failures.append(f"{label}:{reason}" if stage == "joint" else f"{label}[{stage}]:{reason}")
        return None

    @staticmethod
    def _reject(program: fm.Program, x: np.ndarray) -> str | None:
        """Why a backend's x is unusable, or None."""
        if x.shape != (program.variables,) or not np.all(np.isfinite(x)):
            return "non-finite solution"
        equality, inside = program.violation(x)
        if equality > EQUALITY_TOLERANCE * program.equality_scale:
            return f"equality violated by {equality:.1e}"
        if inside > FEASIBILITY_TOLERANCE:
            return f"inequalities violated by {inside:.1e}"
        return None
