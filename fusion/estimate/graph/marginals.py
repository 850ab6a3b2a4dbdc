"""Position marginal covariances of the solved graph in one pass over its chain, instead of one
Bayes-tree query per epoch (``gtsam.Marginals.marginalCovariance``: ~0.4 ms an epoch on the Pixel5
trace, and its cost grows with the tree's depth).

The graph is linearised at the solution (robust losses reweighted there, as ``gtsam.Marginals``
does), its information matrix ``H = A^T A`` is put in time order (every per-epoch variable by epoch,
the few trace-wide ones, inter-system biases and the odometry heading state, last), and the diagonal
blocks of ``H^-1`` come from the block-tridiagonal recursion (forward Schur complements, backward
sweep, as a Rauch-Tung-Striebel smoother runs) on the banded part, with the trace-wide variables
added back through their Schur complement. ``H`` is Jacobi-scaled first, so clocks in seconds and
positions in metres meet at unit scale. :func:`marginal_positions` falls back to ``gtsam.Marginals``
where the band is wide (a clock chained across many epochs without one) or the graph has many
trace-wide variables.
"""
from __future__ import annotations

import gtsam
import numpy as np

from fusion.estimate.graph.keys import pos_key

#: symbol characters of per-epoch variables (their index is the epoch), in their order inside an epoch
EPOCH_CHARS = "qudcvx"
#: beyond these the recursion's dense blocks cost more than GTSAM's Bayes tree: fall back to it
MAX_BAND = 96
MAX_GLOBAL = 64


def marginal_positions(graph: gtsam.NonlinearFactorGraph, result: gtsam.Values, epochs: np.ndarray,
                       E: int, dense: list[int] | tuple[int, ...] = ()) -> np.ndarray:
    """(E,3,3) ECEF position marginal covariances at the solution (NaN for epochs not in ``epochs``).
    dense: positions in ``graph`` of factors whose linearisation is a rank-deficient HessianFactor
    (GTSAM cannot turn those into Jacobian rows); their information is added as it is.
    A graph singular at the solution (which LM's damping hides) raises RuntimeError, as
    ``gtsam.Marginals`` does."""
    epochs = np.asarray(epochs, int)
    cov = np.full((E, 3, 3), np.nan)
    if len(epochs) == 0:
        return cov
    try:
        got = chain_marginals(graph, result, epochs, dense)
    except _NoJacobian:
        got = None
    if got is None:
        marg = gtsam.Marginals(graph, result)
        got = np.array([marg.marginalCovariance(pos_key(int(k))) for k in epochs])
    cov[epochs] = got
    return cov


class _NoJacobian(Exception):
    """A factor's linearisation has no Jacobian form (a rank-deficient Hessian not listed as dense)."""


def _column_order(result: gtsam.Values) -> tuple[np.ndarray, np.ndarray, int]:
    """Where each scalar column of ``sparseJacobian_`` (keys in increasing order) goes in time order:
    (n,) new index per old column, (K,) new start column of each key (same key order), and how many
    leading new columns belong to per-epoch variables."""
    dims = result.dims()
    keys = np.array(sorted(dims), dtype=np.uint64)
    dim = np.array([dims[int(k)] for k in keys], int)
    char = (keys >> np.uint64(56)).astype(int)
    index = (keys & np.uint64((1 << 56) - 1)).astype(np.int64)
    rank = np.full(char.shape, len(EPOCH_CHARS))
    for r, ch in enumerate(EPOCH_CHARS):
        rank[char == ord(ch)] = r
    local = rank < len(EPOCH_CHARS)
    order = np.lexsort((index, rank, np.where(local, index, np.iinfo(np.int64).max), ~local))
    new_start = np.empty(len(keys), int)
    new_start[order] = np.r_[0, np.cumsum(dim[order])[:-1]]
    old_start = np.r_[0, np.cumsum(dim)[:-1]]
    col = np.repeat(new_start - old_start, dim) + np.arange(dim.sum())
    return col, new_start, int(dim[local].sum())


def _present_columns(gfg: gtsam.GaussianFactorGraph, result: gtsam.Values, key_start: dict) -> np.ndarray:
    """(m,) the time-ordered column of each column of ``gfg``'s ``sparseJacobian_``, whose columns are the
    keys ``gfg`` holds in increasing order: a variable that only dense factors hold (the last drift state of a
    chain without Doppler) is not among them, and every later column would shift."""
    dims = result.dims()
    held = gfg.keys()               # iterating a temporary KeySet outlives it in GTSAM's binding and hangs
    present = sorted(int(k) for k in list(held))
    return np.concatenate([key_start[k] + np.arange(dims[k]) for k in present])


def _jacobian_pairs(gfg: gtsam.GaussianFactorGraph, col: np.ndarray):
    """Entries of ``A^T A`` (lower triangle of the new column order, duplicates to be summed) of the
    Jacobian factors of ``gfg``: rows (P,), cols (P,), values (P,); col (m,) the new column of each of its
    ``sparseJacobian_`` columns (:func:`_present_columns`)."""
    try:
        i, j, v = gfg.sparseJacobian_()
    except RuntimeError as exc:
        raise _NoJacobian(str(exc)) from None
    n = col.size
    keep = j <= n                                   # a last column, if any, is the right-hand side
    row, c, v = i[keep].astype(np.int64) - 1, col[j[keep].astype(np.int64) - 1], v[keep]
    order = np.argsort(row, kind="stable")
    row, c, v = row[order], c[order], v[order]
    starts = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])
    counts = np.diff(np.r_[starts, row.size])
    per = np.repeat(counts, counts)                  # each entry pairs with every entry of its row
    a = np.repeat(np.arange(row.size), per)
    first = np.repeat(np.repeat(starts, counts), per)
    b = first + (np.arange(a.size) - np.repeat(np.cumsum(per) - per, per))
    lower = c[a] >= c[b]
    a, b = a[lower], b[lower]
    return c[a], c[b], v[a] * v[b]


def _dense_pairs(graph: gtsam.NonlinearFactorGraph, result: gtsam.Values, dense, key_start: dict):
    """The same entries from the information matrices of the factors at positions ``dense``: rows (P,),
    cols (P,), values (P,)."""
    dims = result.dims()
    by_size: dict[int, tuple[list, list]] = {}
    for i in dense:                                  # one per clock link: a few thousand
        hf = graph.at(int(i)).linearize(result)
        idx = np.concatenate([key_start[k] + np.arange(dims[k]) for k in hf.keys()])
        got = by_size.setdefault(idx.size, ([], []))
        got[0].append(idx), got[1].append(hf.information())
    rows, cols, vals = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros(0)]
    for idx, M in by_size.values():
        idx, M = np.array(idx), np.array(M)          # (F,n), (F,n,n)
        r, c = np.broadcast_arrays(idx[:, :, None], idx[:, None, :])
        low = r >= c
        rows.append(r[low]), cols.append(c[low]), vals.append(M[low])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def chain_marginals(graph: gtsam.NonlinearFactorGraph, result: gtsam.Values, epochs: np.ndarray,
                    dense=()) -> np.ndarray | None:
    """(N,3,3) marginal covariances of the positions of ``epochs`` (N,) (see :func:`marginal_positions`),
    or None where the band or the trace-wide part is too wide for the recursion to pay."""
    col, new_start, n_local = _column_order(result)
    keys = np.array(sorted(result.dims()), dtype=np.uint64)
    if len(dense):
        jac = graph.clone()
        for i in dense:
            jac.remove(int(i))
    else:
        jac = graph
    start = dict(zip((int(k) for k in keys), new_start))
    gfg = jac.linearize(result)
    r, c, h = _jacobian_pairs(gfg, _present_columns(gfg, result, start))
    if len(dense):
        r2, c2, h2 = _dense_pairs(graph, result, dense, start)
        r, c, h = np.r_[r, r2], np.r_[c, c2], np.r_[h, h2]
    p0 = new_start[np.searchsorted(keys, np.array([pos_key(int(k)) for k in epochs], dtype=np.uint64))]
    return information_marginals(r, c, h, col.size, n_local, p0)


def information_marginals(r: np.ndarray, c: np.ndarray, h: np.ndarray, n: int, n_local: int,
                          p0: np.ndarray) -> np.ndarray | None:
    """(N,3,3) the diagonal 3x3 blocks of H^-1 starting at the scalar indices p0 (N,), H (n,n) given by
    its lower-triangle entries (rows r (P,) >= cols c (P,), values h (P,), duplicates summed) with the
    first ``n_local`` variables per epoch in time order and the rest trace-wide; None where the band
    or the trace-wide part is too wide for the recursion to pay."""
    diag = np.bincount(r[r == c], weights=h[r == c], minlength=n)
    s = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))     # Jacobi scaling: H' = s H s, unit diagonal
    h = h * s[r] * s[c]
    both = r < n_local                               # c <= r: local-local
    band = int(np.max(r[both] - c[both], initial=0)) + 1
    n_global = n - n_local
    if band > MAX_BAND or n_global > MAX_GLOBAL:
        return None
    nb = -(-n_local // band)
    rl, cl, hl = r[both], c[both], h[both]
    bi, bj = rl // band, cl // band
    same = bi == bj
    D = _accumulate((bi[same], rl[same] % band, cl[same] % band), hl[same], (nb, band, band))
    L = _accumulate((bi[~same], rl[~same] % band, cl[~same] % band), hl[~same], (nb, band, band))  # H[i, i-1]
    D = D + np.swapaxes(D, 1, 2) * (1 - np.eye(band))   # only the lower triangle was summed
    pad = np.arange(n_local, nb * band) - (nb - 1) * band
    D[-1, pad, pad] = 1.0                            # padding: decoupled unit variables
    gg = c >= n_local
    Hgg = _accumulate((r[gg] - n_local, c[gg] - n_local), h[gg], (n_global, n_global))
    Hgg = Hgg + Hgg.T - np.diag(np.diag(Hgg))
    mixed = ~both & ~gg
    Hlg = _accumulate((c[mixed], r[mixed] - n_local), h[mixed], (nb * band, n_global))
    Gd, Gs, Y = _block_tridiagonal_inverse(D, L, Hlg.reshape(nb, band, n_global))
    cov = _gather(Gd, Gs, p0, band)
    if n_global:
        Sg = Hgg - Hlg.T @ Y.reshape(-1, n_global)
        Yp = Y.reshape(-1, n_global)[p0[:, None] + np.arange(3)]          # (N,3,g)
        cov = cov + Yp @ _spd_inverse(Sg) @ np.swapaxes(Yp, 1, 2)
    sp = s[p0[:, None] + np.arange(3)]
    return cov * sp[:, :, None] * sp[:, None, :]


def _accumulate(index: tuple, values: np.ndarray, shape: tuple) -> np.ndarray:
    """A zero array of ``shape`` with ``values`` summed in at ``index`` (np.add.at, ~5x faster)."""
    flat = np.ravel_multi_index(index, shape) if len(values) else np.zeros(0, int)
    return np.bincount(flat, weights=values, minlength=int(np.prod(shape))).astype(float, copy=False).reshape(shape)


def _spd_inverse(M: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix (or a stack); RuntimeError if it is not."""
    try:
        Lc = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        raise RuntimeError("Indeterminant linear system: the graph is singular at the solution") from None
    inv = np.linalg.inv(Lc)
    return np.swapaxes(inv, -1, -2) @ inv


def _block_tridiagonal_inverse(D: np.ndarray, L: np.ndarray, R: np.ndarray):
    """Diagonal blocks Gd (nb,B,B) and sub-diagonal blocks Gs (nb,B,B) (Gs[i] = G[i, i-1]) of G = H^-1
    for the block-tridiagonal SPD H with diagonal blocks D and sub-diagonal blocks L (nb,B,B), and
    Y = H^-1 R for R (nb,B,g)."""
    nb = D.shape[0]
    Sinv = np.empty_like(D)
    Z = R.copy()
    for i in range(nb):                              # forward Schur complements
        S = D[i] if i == 0 else D[i] - L[i] @ Sinv[i - 1] @ L[i].T
        Sinv[i] = _spd_inverse(S)
        if i:
            Z[i] -= L[i] @ (Sinv[i - 1] @ Z[i - 1])
    Gd, Gs, Y = np.empty_like(D), np.zeros_like(D), np.empty_like(R)
    Gd[-1], Y[-1] = Sinv[-1], Sinv[-1] @ Z[-1]
    for i in range(nb - 2, -1, -1):                  # backward sweep
        K = L[i + 1] @ Sinv[i]
        Gs[i + 1] = -Gd[i + 1] @ K
        Gd[i] = Sinv[i] + K.T @ Gd[i + 1] @ K
        Y[i] = Sinv[i] @ (Z[i] - L[i + 1].T @ Y[i + 1])
    return Gd, Gs, Y


def _gather(Gd: np.ndarray, Gs: np.ndarray, p0: np.ndarray, band: int) -> np.ndarray:
    """(N,3,3) blocks G[p:p+3, p:p+3] for starts p0 (N,), from the diagonal and sub-diagonal blocks."""
    idx = p0[:, None] + np.arange(3)
    r, c = np.broadcast_arrays(idx[:, :, None], idx[:, None, :])
    br, bc = r // band, c // band
    out = np.where(br == bc, Gd[br, r % band, c % band], 0.0)
    below = br == bc + 1
    out = np.where(below, Gs[br, r % band, c % band], out)
    above = bc == br + 1
    return np.where(above, Gs[bc, c % band, r % band], out)
