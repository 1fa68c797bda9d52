"""The box QP on the split Hessian by an interior point, for where the active-set methods stall.

``min 1/2 x^T (blockdiag(B) + C^T C) x + g^T x`` subject to ``lower <= x <= upper`` is lifted
to a sparse QP with the coupling rows' values w = C x as variables,

    minimize  1/2 x^T blockdiag(B) x + 1/2 w^T w + g^T x   subject to  C x - w = 0,  lower <= x <= upper,

whose KKT matrix holds the blocks and C once (O(n b^2 + c n b) nonzeros), never the dense
(n b)^2 Hessian. Clarabel solves it; its active sets then start the active-set exchange
(``box_qp.active_set_newton``), which ends in one to three exchanges at the exact minimizer
(docs/nmpc.md, section 4.3).
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp

from platoon_opt.solvers.nmpc.box_qp import BlockLowRank, BoxSolution, active_set_newton, wanted_sets


def interior_point(
    hessian: BlockLowRank, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> BoxSolution | None:
    """The minimizer as ``active_set_newton``'s answer from the sets of Clarabel's solution of
    the lifted QP (module docstring); None if Clarabel does not solve it or the exchange from
    its sets does not end."""
    n, b, _ = hessian.blocks.shape
    size, c = n * b, hessian.coupling.shape[0]
    blocks = sp.block_diag(list(hessian.blocks), format="csc")
    P = sp.triu(sp.block_diag((blocks, sp.identity(c)), format="csc"), format="csc")
    identity = sp.identity(size, format="csc")
    A = sp.vstack(
        (
            sp.hstack((sp.csc_matrix(hessian.coupling), -sp.identity(c))),
            sp.hstack((identity, sp.csc_matrix((size, c)))),
            sp.hstack((-identity, sp.csc_matrix((size, c)))),
        ),
        format="csc",
    )
    offsets = np.concatenate((np.zeros(c), upper, -lower))
    cones = [clarabel.ZeroConeT(c), clarabel.NonnegativeConeT(2 * size)]
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    q = np.concatenate((gradient, np.zeros(c)))
    result = clarabel.DefaultSolver(P, q, A, offsets, cones, settings).solve()
    if result.status != clarabel.SolverStatus.Solved:
        return None
    x = np.clip(np.asarray(result.x[:size]), lower, upper)
    at_upper, at_lower = wanted_sets(hessian, gradient, lower, upper, x)
    polished = active_set_newton(
        hessian, gradient, lower, upper, BoxSolution(None, 0, at_upper, at_lower), restarts=0
    )
    return polished if polished.x is not None else None
