"""Several networks of one recipe (trained with different seeds) asked as one corrector.

Each seed's network makes its own errors where the data say little (a drive unlike the training drives, a
signal seen only in simulation); their average makes fewer, and their disagreement is uncertainty one
network's covariance cannot show (``experiments/results/ensemble.md``: three seeds' fold networks together
beat every one of them on the unseen GSDC drives, and their mean on smartLoc and the Pixel5).

On disk an ensemble is a small JSON manifest beside ordinary checkpoints (each usable on its own)::

    {"format": "gnssfuse-ensemble", "members": ["gnssfuse_dnn_m0.pt", ...],
     "calibration": {"unseen_dnn": {"scale_ned": [...]}, "unseen_fused": {"scale_ned": [...]}}}

Member paths are relative to the manifest's folder. An optional ``"few_satellites": {"below": N, "members":
[...]}`` names networks of another recipe (e.g. trained with satellite dropout) that answer instead at the epochs
where fewer than N distinct satellites are above the mask (``experiments/results/few_satellite_sigmas.md``).
``calibration`` holds the per-axis variance scales
fitted on unseen drives for the ensemble as a whole (``experiments/crossval.py --store-calibration``); the
members' own unseen-drive scales, if any, are ignored (they were fitted on one network's covariance). The
members must read the same features and signals; the Doppler head is the first member's.
"""
from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import numpy as np

from fusion.errors import CheckpointError, DataError
from fusion.geometry import ned2ecef_cov, ned2ecef_vec
from fusion.trace import satellite_counts
from learned.infer import Corrector, Correction, _calibration_scales

FORMAT = "gnssfuse-ensemble"
#: What a manifest's name ends with (``Corrector.load`` reads such a file as an ensemble).
SUFFIX = ".json"
#: Unseen-drive scales belong to the ensemble, not to a member (see the module docstring).
UNSEEN = ("unseen_dnn", "unseen_fused")


def is_manifest(path: str | Path) -> bool:
    return Path(path).suffix == SUFFIX


def read_manifest(path: str | Path) -> tuple[list[Path], dict]:
    """(member checkpoint paths, ensemble calibration) of the manifest at ``path``; CheckpointError naming
    the file when it is not one (:func:`read_few_satellites` reads its optional few-satellite members)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: ensemble manifest not found")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable JSON ensemble manifest: {type(exc).__name__}") from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a gnssfuse ensemble manifest (missing format tag {FORMAT!r})")
    members = doc.get("members")
    if not isinstance(members, list) or not members or not all(isinstance(m, str) and m for m in members):
        raise CheckpointError(f"{path}: 'members' must be a non-empty list of checkpoint file names")
    cal = doc.get("calibration") or {}
    if not isinstance(cal, dict):
        raise CheckpointError(f"{path}: 'calibration' must be a mapping")
    return [path.parent / m for m in members], cal


def read_few_satellites(path: str | Path) -> tuple[int, list[Path]]:
    """(below, member paths) of the manifest's ``few_satellites`` entry; (0, []) where it has none."""
    path = Path(path)
    read_manifest(path)                                   # a file that is no manifest: its one-line error
    few = json.loads(path.read_text()).get("few_satellites")
    if few is None:
        return 0, []
    below, members = (few.get(k) if isinstance(few, dict) else None for k in ("below", "members"))
    if not isinstance(below, int) or below < 5 or not isinstance(members, list) or not members \
            or not all(isinstance(m, str) and m for m in members):
        raise CheckpointError(f"{path}: 'few_satellites' must be {{\"below\": an integer >= 5, \"members\": "
                              "[checkpoint file names]}")
    return below, [path.parent / m for m in members]


def _relative(members: list[str | Path], path: Path) -> list[str]:
    missing = [str(m) for m in members if not Path(m).is_file()]
    if not members or missing:
        raise CheckpointError(f"{path}: an ensemble needs existing member checkpoints; missing {missing or 'all'}")
    return [Path(os.path.relpath(Path(m).resolve(), path.parent.resolve())).as_posix() for m in members]


def write_manifest(path: str | Path, members: list[str | Path], calibration: dict | None = None,
                   few: tuple[int, list[str | Path]] | None = None) -> Path:
    """Write the manifest atomically, ``members`` (and ``few``: below, members) stored relative to its folder
    (kept beside it, the folder moves whole)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"format": FORMAT, "members": _relative(members, path), "calibration": dict(calibration or {})}
    if few is not None:
        doc["few_satellites"] = {"below": int(few[0]), "members": _relative(few[1], path)}
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(tmp, path)
    return path


def store_ensemble_calibration(path: str | Path, scales: dict) -> None:
    """Merge ``scales`` (name -> :func:`learned.calibrate.sigma_scale` dict, e.g. ``unseen_fused``) into the
    manifest's calibration."""
    paths, cal = read_manifest(path)
    below, few = read_few_satellites(path)
    write_manifest(path, paths, {**cal, **scales}, (below, few) if few else None)


def member_paths(weights: Path, out: Path) -> tuple[list[Path], list[Path]]:
    """For a command that writes a changed copy of ``weights`` to ``out`` (adapt, train-doppler): the
    checkpoints to change and where each goes. ``weights`` and ``out`` themselves, or an ensemble's members
    and ``<out stem>_m<i>.pt`` beside the manifest ``out`` (which the command writes last)."""
    if not is_manifest(weights):
        if is_manifest(out):
            raise DataError(f"{out}: a .json names an ensemble manifest, and {weights.name} is one network; "
                            "give --out a .pt")
        return [weights], [out]
    if not is_manifest(out):
        raise DataError(f"{out}: {weights.name} is an ensemble, and so is what is made from it: give --out a "
                        ".json (the manifest; its members are written beside it)")
    bases = read_manifest(weights)[0]
    return bases, [out.with_name(f"{out.stem}_m{i}.pt") for i in range(len(bases))]


def write_derived_manifest(weights: Path, out: Path, members: list[Path]) -> None:
    """After a command wrote its changed copies of ``weights``' networks to ``members`` (:func:`member_paths`):
    for an ensemble, its manifest ``out`` naming them, with the base ensemble's calibration; nothing for one
    network."""
    if is_manifest(weights):
        below, few = read_few_satellites(weights)      # kept as they are: the command changed the members only
        write_manifest(out, members, read_manifest(weights)[1], (below, few) if few else None)


class Ensemble(Corrector):
    """The members' answers combined (:func:`combine`); everything built on :meth:`predict` (the ``fused``
    mode's :meth:`graph_inputs`, the providers) then works as for one network."""

    def __init__(self, members: list[Corrector], calibration: dict | None = None, path: Path | None = None,
                 calibrated: bool = True, few: "Ensemble | None" = None, few_below: int = 0):
        first = members[0]
        for m in members[1:]:
            if m.features != first.features or m.signals != first.signals or m.output != first.output:
                raise CheckpointError(f"{path}: member {m.path} reads other features, signals or output than "
                                      f"{first.path}; an ensemble's members share one recipe")
        members = [copy.copy(m) for m in members]          # the caller's correctors keep their own scales
        for m in members:
            m.var_scale = dict(m.var_scale, **{k: np.ones(3) for k in UNSEEN})
        self.members, self.path, self.model = members, path, None
        # what any member was trained on (so that no table presents an in-sample trace as held out)
        traces = sorted({t for m in members for t in (m.config.get("data") or {}).get("traces", [])})
        self.config = dict(first.config, data=dict(first.config.get("data") or {}, traces=traces),
                           ensemble={"members": [str(m.path) for m in members]})
        self.features, self.signals, self.output = first.features, first.signals, first.output
        self.device, self.ranges, self.doppler = first.device, first.ranges, first.doppler
        # the members applied their validation scales already; the ensemble's unseen-drive ones go on top
        scales = _calibration_scales({"calibration": calibration or {}}, path, calibrated)
        self.var_scale = {k: (scales[k] if k in UNSEEN else np.ones(3)) for k in scales}
        if few is not None and (few.features != first.features or few.signals != first.signals):
            raise CheckpointError(f"{path}: the few-satellite members read other features or signals")
        self.few, self.few_below = few, few_below

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu", calibrated: bool = True) -> "Ensemble":
        paths, cal = read_manifest(path)
        below, few = read_few_satellites(path)
        few_ens = cls([Corrector.load(p, device=device, calibrated=calibrated) for p in few], cal, Path(path),
                      calibrated) if few else None
        return cls([Corrector.load(p, device=device, calibrated=calibrated) for p in paths], cal, Path(path),
                   calibrated, few_ens, below)

    def predict(self, trace, init_pos: np.ndarray, valid: np.ndarray, elev_mask_deg: float | None = None,
                output: str | None = None, drop: np.ndarray | None = None) -> Correction:
        """Each member asked as :meth:`Corrector.predict` is, the answers combined (:func:`combine`) and the
        ensemble's unseen-drive scale applied to the default output's covariance."""
        output = output or self.output
        outs = []
        for i, m in enumerate(self.members):
            outs.append(m.predict(trace, init_pos, valid, elev_mask_deg=elev_mask_deg, output=output, drop=drop))
            if i == 0:
                # the context (a plain WLS of the whole trace) is the same for every member: computed once
                share_context(m, self.members)
        scale = self.var_scale["unseen_dnn"] if output == self.output else np.ones(3)
        res = combine(outs, np.asarray(init_pos, float), scale)
        if self.few is not None:
            rows = res.valid & (satellite_counts(trace.sat_id, np.isfinite(res.base)) < self.few_below)
            few = self.few.predict(trace, init_pos, np.asarray(valid) & rows, elev_mask_deg, output, drop) \
                if rows.any() else None
            res.info["few_satellite_epochs"] = 0 if few is None else int((rows & few.valid).sum())
            if few is not None:
                take_rows(res, few, rows & few.valid)
        return res


def take_rows(res: Correction, other: Correction, rows: np.ndarray) -> None:
    """``other``'s answers in place of ``res``'s at the epochs ``rows`` (E,) bool."""
    for name in ("mean_ecef", "cov_ecef", "corr_ned", "cov_ned", "sigma", "bias", "base", "trust"):
        getattr(res, name)[rows] = getattr(other, name)[rows]


def share_context(first: Corrector, members: list[Corrector]) -> None:
    """Hand ``first``'s cached trace context to the members that would compute the same one."""
    for m in members:
        if m is not first and m.features.elev_mask_deg == first.features.elev_mask_deg \
                and ("heading" in m.features.inputs) == ("heading" in first.features.inputs):
            m._ctx_cache = first._ctx_cache


def combine(outs: list[Correction], guess: np.ndarray, scale_ned: np.ndarray = np.ones(3)) -> Correction:
    """One :class:`Correction` from the members' (E epochs, S slots), at the guess (E,3) ECEF they corrected.

    Correction: the mean; its NED covariance the mean of theirs plus the members' spread around the mean,
    times ``scale_ned`` (3,) (variance scales); valid where every member is. Per slot: the geometric mean of
    the sigmas (a multiplier on one physical model, so averaged as a log), the mean bias, the first member's
    physical model (the same in all); NaN where any member has no opinion. Trust: the least any member
    gave (an epoch one member's guard switched off gives no prior). Guard counts: the most of any member.
    """
    valid = np.logical_and.reduce([o.valid for o in outs])
    corr = np.mean([o.corr_ned for o in outs], axis=0)
    dev = [np.nan_to_num(o.corr_ned - corr) for o in outs]
    spread = np.mean([np.einsum("ei,ej->eij", d, d) for d in dev], axis=0)
    s = np.sqrt(np.asarray(scale_ned, float))
    cov = (np.mean([o.cov_ned for o in outs], axis=0) + spread) * np.outer(s, s)
    E = len(valid)
    res = Correction(np.full((E, 3), np.nan), np.full((E, 3, 3), np.nan), np.full((E, 3), np.nan),
                     np.full((E, 3, 3), np.nan), valid, outs[0].n_too_few)
    if valid.any():
        res.corr_ned[valid], res.cov_ned[valid] = corr[valid], cov[valid]
        res.mean_ecef[valid] = guess[valid] + ned2ecef_vec(corr[valid], guess[valid])
        res.cov_ecef[valid] = ned2ecef_cov(cov[valid], guess[valid])
    with np.errstate(divide="ignore", invalid="ignore"):
        res.sigma = np.exp(np.mean([np.log(o.sigma) for o in outs], axis=0))
    res.bias = np.mean([o.bias for o in outs], axis=0)
    res.base = outs[0].base
    res.trust = np.where(valid, np.min([o.trust for o in outs], axis=0), np.nan)
    keys = dict.fromkeys(k for o in outs for k in (o.info or {}))       # every member's reasons, in order
    res.info = {k: max(int((o.info or {}).get(k, 0)) for o in outs) for k in keys}
    res.info["members"] = len(outs)
    return res


def main(argv: list[str] | None = None) -> int:
    """``python -m learned.ensemble --out W.json M0.pt M1.pt ...``: write the manifest of an ensemble."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m learned.ensemble",
                                description="Write the manifest that makes checkpoints of one recipe an ensemble.")
    p.add_argument("members", type=Path, nargs="+", help="checkpoints (.pt) trained with different seeds")
    p.add_argument("--out", type=Path, required=True, help="the manifest to write (.json), beside or above them")
    p.add_argument("--few", type=Path, nargs="+", default=[], metavar="CKPT",
                   help="networks of another recipe (e.g. --sat-dropout) that answer at epochs of few satellites")
    p.add_argument("--few-below", type=int, default=6, metavar="N",
                   help="with --few: they answer where fewer than N distinct satellites are above the mask (>= 5)")
    args = p.parse_args(argv)
    try:
        if not is_manifest(args.out):
            raise CheckpointError(f"{args.out}: a manifest's name ends in {SUFFIX}")
        if args.few and args.few_below < 5:
            raise CheckpointError(f"--few-below {args.few_below}: the network needs four satellites; give 5 or more")
        few = Ensemble([Corrector.load(m) for m in args.few], path=args.out) if args.few else None
        Ensemble([Corrector.load(m) for m in args.members], path=args.out, few=few)      # one recipe, loadable
        print(write_manifest(args.out, args.members, few=(args.few_below, args.few) if args.few else None))
    except CheckpointError as exc:
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
