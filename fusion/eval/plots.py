"""Figures for ``gnssfuse evaluate``: error CDFs, quantile box plots, trajectories, error vs time.

Every function takes plain arrays keyed by mode name, writes one PNG and returns its path, so
adding a mode never needs a change here. Errors are NED metres (north, east, down) as returned by
:func:`fusion.eval.metrics.ned_errors`; NaN rows (unsolved epochs or epochs without truth) are ignored.
Matplotlib runs headless (Agg); figures are closed after saving so long runs do not leak memory.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fusion.geometry import ecef2ned_vec  # noqa: E402
from fusion.eval.metrics import cdf, horizontal  # noqa: E402

AXES = ("north", "east", "down")
#: Upper percentile shown on CDF x-axes; a few extreme outliers would otherwise squash the curves.
CDF_CLIP_PCT = 99.0


def _finite_rows(a: np.ndarray) -> np.ndarray:
    return a[np.isfinite(a).all(axis=-1)] if a.ndim == 2 else a[np.isfinite(a)]


def _break_gaps(t: np.ndarray | None, y: np.ndarray, max_gap: float) -> tuple[np.ndarray | None, np.ndarray]:
    """Insert a NaN row wherever consecutive times differ by more than ``max_gap``, so lines are
    not drawn across data gaps (e.g. the separate windows of one drive). y: (E,) or (E, k)."""
    if t is None or len(t) < 2:
        return t, y
    cut = np.flatnonzero(np.diff(t) > max_gap) + 1
    return np.insert(t.astype(float), cut, np.nan), np.insert(y.astype(float), cut, np.nan, axis=0)


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a figure with a layout engine is laid out already; "tight" would draw it a second time
    fig.savefig(path, dpi=110, bbox_inches=None if fig.get_layout_engine() else "tight")
    plt.close(fig)
    return path


def _no_data(ax, text: str = "no epochs with truth") -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")


def plot_error_cdfs(errors: dict[str, np.ndarray], path: Path, title: str = "",
                    clip_pct: float = CDF_CLIP_PCT) -> Path:
    """CDFs of |north|, |east|, |down| and horizontal error, one curve per mode.

    errors: mode -> (E, 3) NED error [m]. The x-range of each panel stops at the ``clip_pct``
    percentile over all modes (the curves themselves use every epoch); the panel says so.
    """
    fig, axs = plt.subplots(1, 4, figsize=(16, 3.8), layout="constrained")
    panels = [(f"|{a}| error [m]", lambda e, i=i: np.abs(e[:, i])) for i, a in enumerate(AXES)]
    panels.append(("horizontal error [m]", horizontal))
    for ax, (label, fn) in zip(axs, panels):
        vals = {m: fn(_finite_rows(e)) for m, e in errors.items()}
        pooled = np.concatenate([v for v in vals.values()] + [np.zeros(0)])
        if pooled.size == 0:
            _no_data(ax)
        for mode, v in vals.items():
            if v.size:
                x, p = cdf(v)
                ax.step(x, p, where="post", label=f"{mode} (n={v.size})")
        if pooled.size:
            hi = float(np.percentile(pooled, clip_pct))
            ax.set_xlim(0, hi * 1.02 if hi > 0 else 1.0)
            n_out = int((pooled > hi).sum())
            ax.set_title(f"x clipped at p{clip_pct:g} ({n_out} pts beyond)", fontsize=9)
        ax.set_xlabel(label)
        ax.set_ylim(0, 1.0)
        ax.grid(alpha=0.3)
    axs[0].set_ylabel("fraction of epochs")
    if axs[-1].get_legend_handles_labels()[0]:
        axs[-1].legend(loc="lower right", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_error_boxes(errors: dict[str, np.ndarray], path: Path, title: str = "") -> Path:
    """Quantile box plots of signed N/E/D errors per mode (as in Kanhere et al., Fig. 5).

    Box Q1-Q3 with the median; whiskers at the furthest point within 1.5*IQR; points beyond
    them drawn as outliers. The y-range covers every whisker with a margin; outliers outside it
    are counted in the panel title rather than allowed to flatten the boxes.
    """
    modes = list(errors)
    fig, axs = plt.subplots(1, 3, figsize=(4.2 * 3, 4.2), layout="constrained")
    for i, (ax, axis) in enumerate(zip(axs, AXES)):
        data = [_finite_rows(errors[m])[:, i] for m in modes]
        keep = [(m, d) for m, d in zip(modes, data) if d.size]
        if not keep:
            _no_data(ax)
            ax.set_title(f"{axis} error")
            continue
        labels, arrays = zip(*keep)
        ax.boxplot(arrays, whis=1.5, showfliers=True, tick_labels=labels,
                   flierprops=dict(marker=".", markersize=3, alpha=0.5))
        lo, hi = box_limits(arrays)
        n_out = sum(int(((d < lo) | (d > hi)).sum()) for d in arrays)
        ax.set_ylim(lo, hi)
        ax.axhline(0.0, color="0.5", lw=0.8, ls=":")
        ax.set_title(f"{axis} error" + (f" ({n_out} outlier{'s' if n_out > 1 else ''} off-scale)" if n_out else ""), fontsize=10)
        ax.set_ylabel(f"{axis} error [m]")
        ax.grid(axis="y", alpha=0.3)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def box_limits(arrays, whis: float = 1.5, pad: float = 0.5) -> tuple[float, float]:
    """y-range covering every box's whiskers (furthest points within ``whis``*IQR), plus
    ``pad`` times that span on each side, so a few huge outliers cannot flatten the boxes."""
    lo, hi = np.inf, -np.inf
    for d in arrays:
        q1, q3 = np.percentile(d, [25, 75])
        iqr = q3 - q1
        inside = d[(d >= q1 - whis * iqr) & (d <= q3 + whis * iqr)]
        lo, hi = min(lo, inside.min()), max(hi, inside.max())
    margin = pad * max(hi - lo, 1e-3)
    return float(lo - margin), float(hi + margin)


def local_east_north(pos_ecef: np.ndarray, origin_ecef: np.ndarray) -> np.ndarray:
    """(E, 3) ECEF -> (E, 2) east, north [m] from ``origin_ecef`` in the NED frame at the origin."""
    ned = ecef2ned_vec(pos_ecef - origin_ecef, np.broadcast_to(origin_ecef, pos_ecef.shape))
    return ned[:, [1, 0]]


def mode_colours(modes) -> dict[str, str]:
    """One fixed colour per mode (tab10 in the order given), the same in every panel of a figure."""
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {m: cycle[i % len(cycle)] for i, m in enumerate(modes)}


def worst_stretches(t_s: np.ndarray, score: np.ndarray, n: int = 3, half_s: float = 15.0) -> list[int]:
    """Epoch indices of up to ``n`` separate worst moments: the largest finite ``score`` (E,), then the
    largest more than ``3 * half_s`` seconds from every one already taken (zooms of ``half_s`` either
    side then neither overlap nor touch)."""
    picked: list[int] = []
    s = np.where(np.isfinite(score), score, -np.inf)
    for _ in range(n):
        k = int(np.argmax(s))
        if not np.isfinite(s[k]) or s[k] <= 0:
            break
        picked.append(k)
        s[np.abs(t_s - t_s[k]) <= 3 * half_s] = -np.inf
    return picked


def _stretch_score(positions: dict[str, np.ndarray], truth: np.ndarray | None) -> np.ndarray | None:
    """(E,) what makes an epoch worth a zoom: the largest horizontal error of any mode against the
    truth, or without truth the largest distance of a mode from the modes' median (modes disagree)."""
    stack = np.stack(list(positions.values()))                              # (M, E, 3)
    ref = truth if truth is not None else (np.nanmedian(stack, axis=0) if len(stack) > 1 else None)
    if ref is None:
        return None
    ok = np.isfinite(ref).all(axis=1)
    d = np.full(stack.shape[:2], np.nan)
    for i, pos in enumerate(stack):
        good = ok & np.isfinite(pos).all(axis=1)
        d[i, good] = np.hypot(*ecef2ned_vec(pos[good] - ref[good], ref[good])[:, :2].T)
    with np.errstate(all="ignore"):
        return np.where(np.isfinite(d).any(axis=0), np.nanmax(np.where(np.isfinite(d), d, -np.inf), axis=0), np.nan)


def _draw_tracks(ax, tracks: dict[str, np.ndarray], colours: dict[str, str], truth_en: np.ndarray | None,
                 ms: float, zoom: bool = False) -> None:
    for mode, en in tracks.items():
        ax.plot(en[:, 0], en[:, 1], ".-", ms=ms, lw=0.7, alpha=0.85, color=colours[mode], label=mode, zorder=2)
    if truth_en is not None and zoom:     # on top, so a stopped car's truth (one point) is not hidden
        ax.plot(truth_en[:, 0], truth_en[:, 1], "o-", color="k", ms=ms * 0.6, lw=1.6, label="truth", zorder=3,
                alpha=0.8)
    elif truth_en is not None:            # underneath, wide: the overview's reference
        ax.plot(truth_en[:, 0], truth_en[:, 1], color="k", lw=2.0, label="truth", zorder=1)


def plot_trajectories(positions: dict[str, np.ndarray], truth: np.ndarray | None, path: Path,
                      title: str = "", t_s: np.ndarray | None = None, max_gap_s: float = 5.0,
                      n_zoom: int = 3, zoom_half_s: float = 15.0) -> Path:
    """Every mode's track over the truth in a local east/north frame, with zoomed panels (A, B, C) on
    the worst stretches, where the tracks' differences are visible at street scale.

    positions: mode -> (E, 3) ECEF with NaN rows where unsolved; truth: (E, 3) ECEF or None;
    t_s: (E,) epoch times [s]: lines break across gaps longer than ``max_gap_s``, and a zoom shows
    ``zoom_half_s`` seconds either side of its worst epoch (the largest horizontal error of any mode,
    or without truth the largest disagreement between modes). Origin: the first finite truth point,
    else the first solved estimate of any mode.
    """
    has_truth = truth is not None and len(_finite_rows(truth)) > 0
    candidates = ([truth] if has_truth else []) + list(positions.values())
    origin = next((_finite_rows(c)[0] for c in candidates if len(_finite_rows(c))), None)
    score = _stretch_score(positions, truth if has_truth else None) if origin is not None and positions else None
    t = np.arange(len(next(iter(candidates)))) * 1.0 if t_s is None else np.asarray(t_s, float)
    zooms = worst_stretches(t, score, n_zoom, zoom_half_s) if score is not None else []
    fig = plt.figure(figsize=(13 if zooms else 7, 7.5), layout="constrained")
    grid = fig.add_gridspec(max(len(zooms), 1), 2 if zooms else 1, width_ratios=[2, 1] if zooms else [1])
    ax = fig.add_subplot(grid[:, 0])
    what = "first truth point" if has_truth else "first estimate"
    if origin is None:
        _no_data(ax, "no solved epochs")
    else:
        _trajectory_panels(fig, grid, ax, positions, truth if has_truth else None, origin, t, max_gap_s,
                           [(k, score[k]) for k in zooms], zoom_half_s)
    ax.set_xlabel(f"east [m] from {what}")
    ax.set_ylabel(f"north [m] from {what}")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def _trajectory_panels(fig, grid, ax, positions, truth, origin, t, max_gap_s, zooms, zoom_half_s) -> None:
    """The overview on ``ax`` and one zoom panel per (epoch, its score) in ``zooms`` (see
    :func:`plot_trajectories`)."""
    colours = mode_colours(positions)

    def en_of(pos: np.ndarray, sel: np.ndarray) -> np.ndarray:
        ok = sel & np.isfinite(pos).all(axis=1)     # skip unsolved epochs; break only at time gaps
        return _break_gaps(t[ok], local_east_north(pos[ok], origin), max_gap_s)[1]

    everywhere = np.ones(len(t), bool)
    tracks = {m: en_of(p, everywhere) for m, p in positions.items() if len(_finite_rows(p))}
    _draw_tracks(ax, tracks, colours, None if truth is None else en_of(truth, everywhere), ms=2)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    for i, (k, worst_m) in enumerate(zooms):
        near = np.abs(t - t[k]) <= zoom_half_s
        z_tracks = {m: en_of(p, near) for m, p in positions.items()}
        z_tracks = {m: v for m, v in z_tracks.items() if np.isfinite(v).any()}
        z_truth = None if truth is None else en_of(truth, near)
        zax = fig.add_subplot(grid[i, 1])
        _draw_tracks(zax, z_tracks, colours, z_truth, ms=4, zoom=True)
        pts = np.concatenate([v for v in z_tracks.values()] + ([z_truth] if z_truth is not None else []))
        lo, hi = np.nanmin(pts, axis=0), np.nanmax(pts, axis=0)
        pad = 0.08 * max(float(np.max(hi - lo)), 1.0)
        ax.add_patch(plt.Rectangle(lo - pad, *(hi - lo + 2 * pad), fill=False, ec="crimson", lw=1.0, zorder=3))
        ax.annotate("ABCDEFGH"[i], hi + pad, color="crimson", fontsize=11, fontweight="bold")
        zax.set_aspect("equal", adjustable="datalim")
        zax.grid(alpha=0.3)
        zax.tick_params(labelsize=7)
        worst = "horizontal error" if truth is not None else "distance from the modes' median"
        zax.set_title(f"{'ABCDEFGH'[i]}: t = {t[k] - zoom_half_s:.0f}..{t[k] + zoom_half_s:.0f} s, largest "
                      f"{worst} {worst_m:.0f} m", fontsize=9)


def plot_error_vs_time(t_s: np.ndarray, errors: dict[str, np.ndarray], path: Path, title: str = "",
                       clip_pct: float = CDF_CLIP_PCT, max_gap_s: float = 5.0) -> Path:
    """Horizontal and vertical (down) error against time since the first epoch, as small multiples:
    one row per mode, in its colour, over the other modes in light grey, so no mode hides another.

    t_s: (E,) seconds since the trace start; errors: mode -> (E, 3) NED [m]. Rows share their axes;
    the y-range stops at the ``clip_pct`` percentile of |error| over all modes, as in the CDFs. Lines
    break across time gaps longer than ``max_gap_s`` (unsolved single epochs are bridged).
    """
    modes = list(errors)
    colours = mode_colours(modes)
    fig, axs = plt.subplots(max(len(modes), 1), 2, figsize=(13, 1.1 + 1.7 * max(len(modes), 1)), sharex=True,
                            sharey="col", squeeze=False, layout="constrained")
    series = [("horizontal error [m]", horizontal), ("down error [m]", lambda e: e[:, 2])]
    for col, (label, fn) in enumerate(series):
        lines = {}
        for mode, e in errors.items():
            v = fn(e)
            ok = np.isfinite(v)
            lines[mode] = _break_gaps(t_s[ok], v[ok], max_gap_s) if ok.any() else None
        pooled = np.concatenate([np.abs(fn(e)[np.isfinite(fn(e))]) for e in errors.values()] + [np.zeros(0)])
        hi = float(np.percentile(pooled, clip_pct)) * 1.05 or 1.0 if pooled.size else 1.0
        for row, mode in enumerate(modes):
            ax = axs[row, col]
            for other, tv in lines.items():
                if tv is not None and other != mode:
                    ax.plot(*tv, lw=0.5, color="0.8", zorder=1)
            if lines[mode] is None:
                _no_data(ax)
            else:
                ax.plot(*lines[mode], lw=0.8, color=colours[mode], zorder=2)
            ax.set_ylim((0, hi) if col == 0 else (-hi, hi))
            ax.grid(alpha=0.3)
            ax.set_ylabel(mode, color=colours[mode], fontweight="bold")
        axs[0, col].set_title(f"{label} (y clipped at p{clip_pct:g} of |error|: {int((pooled > hi).sum())} "
                              "pts beyond)", fontsize=9)
        axs[-1, col].set_xlabel("time since first epoch [s]")
    fig.suptitle((f"{title}: " if title else "") + "each mode in colour, the others in grey behind it")
    return _save(fig, path)
