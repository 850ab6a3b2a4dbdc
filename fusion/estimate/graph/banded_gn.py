"""Gauss-Newton over a whole trace in vectorised numpy, with a banded Cholesky: the batch solver of
:mod:`fusion.estimate.graph.vector_graph`'s copy of the fused graph (``GraphConfig.batch_solver = "banded"``).

GTSAM's Gauss-Newton spends ~110 ms an iteration on the Pixel5 graph linearising 57k factors one
C++ object at a time and eliminating 11k variables through its Bayes tree
(``benchmarks/graph_iteration_cost.py``). Here every factor kind is a :class:`Blocks` of identical
factors evaluated at once, and the normal equations of a trace in time order are a band (each epoch
links only to its neighbours) plus a few trace-wide columns (inter-system biases), which LAPACK's
banded Cholesky and a Schur complement solve directly.

The iteration is GTSAM's, step for step: each factor whitened by its sigma, a robust loss applied to
the norm of its whitened error as iteratively reweighted least squares (weight ``w(|e|)`` on the
whitened rows, as GTSAM's ``noiseModel.Robust`` linearises), the cost ``sum rho(|e|)`` GTSAM's
``graph.error`` reports, and the same stopping rule (:func:`fusion.estimate.graph.optimiser.converged`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
import scipy.linalg

from fusion.errors import GnssfuseError
from fusion.estimate.graph.optimiser import at_optimum, converged

#: a nonlinear kind's model: (x (N,), whether to compute Jacobians) -> (whitened residuals (M,d), whitened
#: Jacobians (M,d,n) or None) at x
Model = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]


@dataclass
class Blocks:
    """M factors of one kind, each ``d`` whitened rows over ``n`` scalar variables.

    cols (M,n) int: each factor's variables (indices into the state vector); linear kinds give A (M,d,n)
    and b (M,d), the whitened residual being ``A @ x[cols] - b``; nonlinear kinds give ``model`` instead.
    robust: "none", "huber", "cauchy" or "gm" on the norm of each factor's whitened residual, at ``k``. A factor
    names each of its variables once (the normal equations' pair products assume distinct columns)."""

    cols: np.ndarray
    A: np.ndarray | None = None
    b: np.ndarray | None = None
    robust: str = "none"
    k: float = 1.0
    model: Model | None = None
    _pairs: "_Pairs | None" = field(default=None, repr=False)
    _h: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        c = np.sort(self.cols, axis=1)
        if (c[:, :1] < 0).any() or (c[:, 1:] == c[:, :-1]).any():
            raise ValueError("Blocks: a factor's variables must be distinct state indices >= 0")

    def __len__(self) -> int:
        return len(self.cols)

    def residual(self, x: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals (M,d) at ``x`` (N,), and the whitened Jacobians (M,d,n) (None without ``jacobian``)."""
        if self.model is not None:
            return self.model(x, jacobian)
        return np.einsum("mdn,mn->md", self.A, x[self.cols]) - self.b, self.A


@dataclass
class System:
    """A least-squares problem over ``n`` scalar variables: the first ``n_local`` belong to epochs, in
    time order (so each factor spans a short stretch of them), the rest are trace-wide."""

    blocks: list[Blocks]
    n: int
    n_local: int
    _static: "Normal | None" = field(default=None, repr=False)    # the information of the constant factors

    @cached_property
    def band(self) -> int:
        """Largest distance between two local variables of one factor, at least 1 (the normal equations'
        bandwidth; the blocks are fixed once the system is made)."""
        bw = 1
        for blk in self.blocks:
            c = np.where(blk.cols < self.n_local, blk.cols, -1)
            lo = np.where(c >= 0, c, np.iinfo(np.int64).max).min(axis=1, initial=np.iinfo(np.int64).max)
            hi = c.max(axis=1, initial=-1)
            some = hi >= 0
            if some.any():
                bw = max(bw, int((hi[some] - lo[some]).max()))
        return bw


def robust_loss(kind: str, k: float, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's M-estimators on whitened error norms e (M,) >= 0: the loss rho(e) (M,) (0.5 e^2 unrobust)
    and the IRLS weight w(e) (M,)."""
    if kind == "none":
        return 0.5 * e * e, np.ones_like(e)
    if kind == "cauchy":
        q = (e / k) ** 2
        return 0.5 * k * k * np.log1p(q), 1.0 / (1.0 + q)
    if kind == "huber":
        big = e > k
        return np.where(big, k * e - 0.5 * k * k, 0.5 * e * e), np.where(big, k / np.where(big, e, 1.0), 1.0)
    if kind == "gm":
        d = k * k + e * e
        return 0.5 * k * k * e * e / d, (k * k / d) ** 2
    raise GnssfuseError(f"unknown robust loss {kind!r}; choose huber, cauchy, gm or none")


def cost(system: System, x: np.ndarray) -> float:
    """The total cost at ``x`` (N,): what GTSAM's ``graph.error`` gives for the same graph."""
    total = 0.0
    for blk in system.blocks:
        r, _ = blk.residual(x, jacobian=False)
        total += float(robust_loss(blk.robust, blk.k, np.sqrt(np.einsum("md,md->m", r, r)))[0].sum())
    return total


@dataclass
class Normal:
    """The reweighted normal equations H dx = -g, split as H = [[B, C], [C^T, D]]: B the banded local part
    in LAPACK's lower form (band+1, n_local), C (n_local, G), D (G,G), and g (N,)."""

    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    g: np.ndarray


@dataclass
class _Pairs:
    """Where each product of two of a factor's Jacobian columns lands: the (i, j) column pairs (P,) of
    its lower triangle, and per factor and pair (M,P) a mask and a flat index into B, C or D (D: row,
    column)."""

    ii: np.ndarray
    jj: np.ndarray
    in_b: np.ndarray
    at_b: np.ndarray
    in_c: np.ndarray
    at_c: np.ndarray
    in_d: np.ndarray
    d_row: np.ndarray
    d_col: np.ndarray


def _pair_targets(blk: Blocks, n_local: int, n_global: int) -> _Pairs:
    """:class:`_Pairs` of ``blk`` (cached on it: its variables never change)."""
    if blk._pairs is None:
        ii, jj = np.tril_indices(blk.cols.shape[1])
        a, b = blk.cols[:, ii], blk.cols[:, jj]
        hi, lo = np.maximum(a, b), np.minimum(a, b)
        in_b, in_d = hi < n_local, lo >= n_local
        in_c = ~in_b & ~in_d
        blk._pairs = _Pairs(ii, jj, in_b, ((hi - lo) * n_local + lo)[in_b], in_c,
                            (lo * n_global + hi - n_local)[in_c], in_d, (hi - n_local)[in_d], (lo - n_local)[in_d])
    return blk._pairs


def _pair_products(blk: Blocks, Aw: np.ndarray, pr: _Pairs) -> np.ndarray:
    """(M,P) the products of each factor's Jacobian columns at its pairs (cached on a linear kind as they
    are: a robust weight only scales them)."""
    if blk.model is not None:
        return np.einsum("mdp,mdp->mp", Aw[:, :, pr.ii], Aw[:, :, pr.jj])
    if blk._h is None:
        blk._h = np.einsum("mdp,mdp->mp", blk.A[:, :, pr.ii], blk.A[:, :, pr.jj])
    return blk._h


def _add_information(eq: Normal, blk: Blocks, Aw: np.ndarray, w: np.ndarray | None, nl: int, G: int) -> None:
    """Add the information of ``blk``'s factors with reweighted Jacobians Aw (M,d,n) (robust weights w (M,),
    None for unit weights) into eq's B, C and D (flat B and C)."""
    pr = _pair_targets(blk, nl, G)
    h = _pair_products(blk, Aw, pr)
    if w is not None and blk.model is None:
        h = h * w[:, None]
    eq.B += np.bincount(pr.at_b, weights=h[pr.in_b], minlength=eq.B.size)
    if G:
        eq.C += np.bincount(pr.at_c, weights=h[pr.in_c], minlength=eq.C.size)
        np.add.at(eq.D, (pr.d_row, pr.d_col), h[pr.in_d])


def _static_information(system: System) -> Normal:
    """The information of the linear factors without a robust loss (constant: computed once per system),
    flat B and C, lower D; g zero."""
    if system._static is None:
        nl, G = system.n_local, system.n - system.n_local
        eq = Normal(np.zeros((system.band + 1) * nl), np.zeros(nl * G), np.zeros((G, G)), np.zeros(system.n))
        for blk in system.blocks:
            if len(blk) and _static(blk):
                _add_information(eq, blk, blk.A, None, nl, G)
        system._static = eq
    eq = system._static
    return Normal(eq.B.copy(), eq.C.copy(), eq.D.copy(), np.zeros(system.n))


def _static(blk: Blocks) -> bool:
    """Whether ``blk``'s information never changes (linear, no robust loss)."""
    return blk.model is None and blk.robust == "none"


def normal_equations(system: System, x: np.ndarray) -> Normal:
    """The Gauss-Newton normal equations at ``x`` (N,), robust losses reweighted there."""
    nl, G = system.n_local, system.n - system.n_local
    eq = _static_information(system)
    for blk in system.blocks:
        if not len(blk):
            continue
        r, A = blk.residual(x)
        _, w = robust_loss(blk.robust, blk.k, np.sqrt(np.einsum("md,md->m", r, r)))
        sw = np.sqrt(w)
        Aw, rw = A * sw[:, None, None], r * sw[:, None]
        eq.g += np.bincount(blk.cols.ravel(), weights=np.einsum("mdn,md->mn", Aw, rw).ravel(), minlength=system.n)
        if not _static(blk):
            _add_information(eq, blk, Aw, w, nl, G)
    D = eq.D + np.tril(eq.D, -1).T
    return Normal(eq.B.reshape(system.band + 1, nl), eq.C.reshape(nl, G), D, eq.g)


def solve_normal(eq: Normal) -> np.ndarray:
    """dx (N,) solving H dx = -g by a banded Cholesky of B and the Schur complement of the trace-wide
    variables; numpy's LinAlgError where H is not positive definite."""
    nl = eq.B.shape[1]
    chol = scipy.linalg.cholesky_banded(eq.B, lower=True, check_finite=False)
    gl, gg = -eq.g[:nl], -eq.g[nl:]
    y = scipy.linalg.cho_solve_banded((chol, True), gl, check_finite=False)
    if not gg.size:
        return y
    Y = scipy.linalg.cho_solve_banded((chol, True), eq.C, check_finite=False)      # (nl, G)
    S = eq.D - eq.C.T @ Y
    dg = np.linalg.solve(np.linalg.cholesky(S).T, np.linalg.solve(np.linalg.cholesky(S), gg - eq.C.T @ y))
    return np.concatenate([y - Y @ dg, dg])


@dataclass
class Solved:
    """x (N,) the solution, the iterations taken, its cost, and ``ok`` False where a step raised the cost
    (beyond round-off at the optimum), met a singular system or left the finite numbers (the caller then hands
    over to another solver from ``x``, the best values so far)."""

    x: np.ndarray
    iterations: int
    error: float
    ok: bool


def gauss_newton(system: System, x0: np.ndarray, rel_tol: float, max_iter: int) -> Solved:
    """Gauss-Newton from ``x0`` (N,) until the cost falls by less than ``rel_tol`` of itself (GTSAM's
    rule) or after ``max_iter`` iterations."""
    x, err = x0, cost(system, x0)
    for n in range(max_iter):
        eq = normal_equations(system, x)
        try:
            dx = solve_normal(eq)
        except np.linalg.LinAlgError:
            return Solved(x, n, err, False)
        new_x = x + dx
        new = cost(system, new_x)
        if not np.isfinite(new) or new > err:
            return Solved(x, n + 1, err, at_optimum(err, new, rel_tol))
        x, done = new_x, converged(err, new, rel_tol)
        err = new
        if done:
            return Solved(x, n + 1, err, True)
    return Solved(x, max_iter, err, True)


def information_triplets(system: System, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lower triangle of the information matrix H at ``x`` (robust losses reweighted there, as
    ``gtsam.Marginals`` linearises): rows (P,), cols (P,), values (P,), row >= col."""
    eq = normal_equations(system, x)
    nl = system.n_local
    d, j = np.nonzero(eq.B)
    rows, cols, vals = [j + d], [j], [eq.B[d, j]]
    li, gi = np.nonzero(eq.C)
    rows.append(gi + nl), cols.append(li), vals.append(eq.C[li, gi])
    a, b = np.nonzero(np.tril(eq.D))
    rows.append(a + nl), cols.append(b + nl), vals.append(eq.D[a, b])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
