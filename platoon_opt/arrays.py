"""The model's arrays: JAX in float64, pytrees, and the seam to numpy.

The model's equations are pure functions of arrays and of frozen dataclasses registered as pytrees
(``pytree``), written once in the operations numpy and ``jax.numpy`` share (``namespace`` picks
the library from the arguments): numpy on the host, traced by ``jax.jit``, batched by
``jax.vmap`` and looped by ``jax.lax.scan`` in the engine (``platoon_opt.engine``). Float64
throughout: the gear rule and the clips decide on ties, and float32 changes trajectories.
Importing ``platoon_opt`` therefore switches JAX to 64-bit floats for the whole process
(``jax_enable_x64``).

Allocators that call host solvers (Clarabel, OSQP, CasADi) work on numpy arrays: ``host`` turns
a kernel into a function that compiles once per shape and answers numpy arrays.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, Literal, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from threadpoolctl import ThreadpoolController

jax.config.update("jax_enable_x64", True)

T = TypeVar("T")

# ``searchsorted`` compares with every entry of tables up to this long.
COMPARE_ALL = 64


def pytree(data: Sequence[str], static: Sequence[str] = ()) -> Callable[[type[T]], type[T]]:
    """Register a frozen dataclass as a pytree: the fields ``data`` are its leaves (arrays or
    numbers, traced under ``jit``), the fields ``static`` part of its structure (hashable: names,
    modes, counts). Rebuilding it skips ``__init__``, so the checks of a public constructor do
    not see traced values."""

    def register(cls: type[T]) -> type[T]:
        def flatten(obj: Any) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
            return tuple(getattr(obj, name) for name in data), tuple(getattr(obj, name) for name in static)

        def unflatten(aux: tuple[Any, ...], leaves: Sequence[Any]) -> T:
            return unchecked(cls, **dict(zip(data, leaves)), **dict(zip(static, aux)))

        names = {field.name for field in dataclasses.fields(cls)}  # type: ignore[arg-type]
        missing = (set(data) | set(static)) ^ {name for name in names if not name.startswith("_")}
        if missing:
            raise TypeError(f"pytree({cls.__name__}): fields not declared data or static: {sorted(missing)}")
        jax.tree_util.register_pytree_node(cls, flatten, unflatten)
        return cls

    return register


def unchecked(cls: type[T], **fields: Any) -> T:
    """An instance of the frozen dataclass ``cls`` with ``fields``, without ``__init__`` (no checks):
    for values the model computed itself, or traced ones."""
    obj = object.__new__(cls)
    for name, value in fields.items():
        object.__setattr__(obj, name, value)
    return obj


def tree_slice(tree: T, part: slice) -> T:
    """``tree`` with every leaf cut to ``leaf[part]``: the units ``part`` of per-unit pytrees."""
    return jax.tree_util.tree_map(lambda leaf: leaf[part], tree)


# The engine's batch axis (``jax.vmap(..., axis_name=BATCH_AXIS)``): see ``any_platoon``.
BATCH_AXIS = "platoons"


def any_platoon(flag: Any) -> Any:
    """``flag`` (a traced bool scalar) or-ed over the platoons of the engine's batch (the axis
    ``BATCH_AXIS``), else ``flag`` itself (one platoon, or a kernel traced alone). Under ``vmap``
    a ``lax.cond`` on a per-platoon flag becomes a select that runs both branches at every step;
    on this flag it stays a branch, taken when some platoon needs it. The branch must then give
    every other platoon what the branch not taken would."""
    try:
        return jax.lax.psum(flag.astype(jnp.int32), BATCH_AXIS) > 0
    except NameError:  # the axis is not bound: no batch
        return flag


def while_loop(keep_going: Callable[[T], Any], body: Callable[[T], T], state: T) -> T:
    """``state = body(state)`` while ``keep_going(state)``: ``jax.lax.while_loop`` when ``state``
    holds JAX arrays (traced), a Python loop on numpy."""
    if namespace(*jax.tree_util.tree_leaves(state)) is jnp:
        return jax.lax.while_loop(keep_going, body, state)
    while keep_going(state):
        state = body(state)
    return state


def host(kernel: Callable[..., Any], *, static: Sequence[str] = ()) -> Callable[..., Any]:
    """``kernel`` compiled (``jax.jit``, once per shape and per value of the ``static`` arguments)
    and answering numpy arrays: for host code that takes numpy (the allocators that call host
    solvers, the safety rows, tests).

    The answer comes back as one buffer, split on the host: fetching each array of a pytree on
    its own costs tens of microseconds apiece, more than the kernel of a small platoon.
    """
    layouts: list[tuple[Any, tuple[tuple[tuple[int, ...], Any], ...]]] = []

    @functools.wraps(kernel)  # its signature: jit finds the static arguments by name
    def flat(*args: Any, **kwargs: Any) -> jax.Array:
        leaves, treedef = jax.tree_util.tree_flatten(kernel(*args, **kwargs))
        layout = (treedef, tuple((jnp.shape(leaf), jnp.result_type(leaf)) for leaf in leaves))
        if layout not in layouts:
            layouts.append(layout)
        # The layout's number travels at the end of the buffer: jit's cache, not this wrapper,
        # knows which trace a call hit. Every value fits a float64 exactly (bools, counts).
        parts = [jnp.ravel(leaf).astype(jnp.float64) for leaf in leaves]
        return jnp.concatenate([*parts, jnp.full(1, float(layouts.index(layout)))])

    compiled = jax.jit(flat, static_argnames=tuple(static))

    @functools.wraps(kernel)
    def call(*args: Any, **kwargs: Any) -> Any:
        buffer = np.asarray(compiled(*args, **kwargs))
        treedef, specs = layouts[int(buffer[-1])]
        leaves, start = [], 0
        for shape, dtype in specs:
            size = math.prod(shape)
            leaves.append(buffer[start : start + size].reshape(shape).astype(dtype))
            start += size
        return jax.tree_util.tree_unflatten(treedef, leaves)

    return call


@functools.cache
def _blas() -> ThreadpoolController:
    # Built at first use, when the BLAS libraries numpy and scipy load are loaded.
    return ThreadpoolController()


def one_blas_thread() -> Any:
    """A context in which BLAS and LAPACK run on one thread: host code on tiny matrices (the host
    loop, ``nmpc``'s Cholesky factors). Beside JAX's threads, OpenBLAS's spinning ones made such
    code up to nine times slower on two cores (measured: ``nmpc``'s property test, 31 s against
    3.5 s)."""
    return _blas().limit(limits=1, user_api="blas")


def searchsorted(sorted_values: Any, value: Any, side: Literal["left", "right"] = "left") -> Any:
    """``numpy.searchsorted`` over a 1-d array, also traced. Under JAX without a loop: a binary
    search compiles to a while loop, and in a compiled step each of its turns costs more than
    comparing ``value`` with the few pieces of a path; long tables (a curve's arc lengths) take
    the binary search unrolled."""
    if namespace(sorted_values, value) is np:
        return np.searchsorted(sorted_values, value, side=side)
    method = "compare_all" if sorted_values.shape[0] <= COMPARE_ALL else "scan_unrolled"
    return jnp.searchsorted(sorted_values, value, side=side, method=method)


def namespace(*arrays: Any) -> Any:
    """``jax.numpy`` if any of ``arrays`` is a JAX array (or traced), else ``numpy``: for the few
    small methods that host code and kernels share (a product with J, a column of positions)."""
    return jnp if any(isinstance(array, jax.Array) for array in arrays) else np
