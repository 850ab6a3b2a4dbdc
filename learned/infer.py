"""Inference: the trained network as a position corrector, a position-prior provider and a pipeline mode.

Honest protocol: the initial guess comes from WLS (or any estimate that never saw the truth); the receiver
clock is re-estimated from the measurements at every guess (:mod:`learned.features`).

Runs without torch: the network is evaluated in numpy (:mod:`learned.npnet`) from the checkpoint's ``.npz``
twin (:mod:`learned.npz_weights`). :meth:`Corrector.graph_inputs` is one network pass of the ``fused`` mode:
the prior, the per-satellite sigmas and biases and the guard's counts together (the mode takes the sigmas of a
second pass, :func:`learned.modes.sigmas_again`).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.errors import CheckpointError, GeometryError
from fusion.estimate.graph.priors import LearnedGraphInputs
from fusion.geometry import ned_rotation
from fusion.trace import SIGNALS, Trace
from learned.context import context_wls, slot_context
from learned.doppler_head import DopplerNoise, check_head
from learned.features import FeatureConfig, context_channels, elevation_mask, features_numpy
from learned.guard import feature_guard, slot_out_of_range, trust
from learned.heads import LOGSIG_RANGE, OUTPUTS, base_sigma, report_sigma, sat_sigma_bias, weighted_ls_step
from learned.npnet import KINDS, NpNet, as_net
from learned.npz_weights import check_config, load_for_inference


#: Weights shipped with the package: an ensemble's manifest (:mod:`learned.ensemble`; learned/weights/TRAINING.md).
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "gnssfuse_dnn.json"
#: Training signal set assumed for checkpoints that do not record one (all were GPS L1 only).
DEFAULT_SIGNALS = ("GPS_L1",)
#: Epochs per forward pass at inference: bounded memory, and epochs of like satellite counts together, so that
#: each chunk pads its sets only to its own largest (benchmarks/bench_infer.py).
INFER_CHUNK = 512
#: The chunk outputs with a slot axis, (N,S).
SLOT_OUTPUTS = ("sigma", "bias", "oor", "base")


def chunks_by_size(n_real: np.ndarray):
    """Row indices of chunks of at most ``INFER_CHUNK`` epochs, epochs sorted by their count of real slots
    ``n_real`` (N,) (stable): yields (n,) int arrays covering 0..N-1 once."""
    order = np.argsort(n_real, kind="stable")
    for a in range(0, len(order), INFER_CHUNK):
        yield order[a:a + INFER_CHUNK]


def pad_slots(a: np.ndarray, n_slots: int) -> np.ndarray:
    """(N,s) chunk output padded with zeros (False) to (N,n_slots)."""
    return np.pad(a, ((0, 0), (0, n_slots - a.shape[1])))


@dataclass
class Correction:
    """Network output for every epoch of a trace (NaN rows where ``valid`` is False).

    mean_ecef: (E,3) corrected position [m].  cov_ecef: (E,3,3) its covariance [m^2].
    corr_ned:  (E,3) correction in the NED frame of the initial guess [m].  cov_ned: (E,3,3) [m^2].
    valid:     (E,) bool: initial guess valid and >= 4 satellites above the elevation mask at it.
    n_too_few: epochs with a valid guess but < 4 satellites above the mask.
    sigma, bias: (E,S) learned pseudorange sigma and bias [m] per trace slot, NaN where the network was
               not asked or the slot's inputs are out of the training range (:mod:`learned.guard`).
    base:      (E,S) the head's own physical sigma model, which its sigma multiplies [m] (the reported sigma or
               the C/N0 model, and elevation: :func:`learned.heads.base_sigma`; not the graph's default sigma),
               NaN where not asked.
    trust:     (E,) the guard's trust in [0, 1] (NaN where not valid); the correction is shrunk by it.
    info:      what the guard did: counts by reason (:meth:`Corrector.guard_counts`).
    """

    mean_ecef: np.ndarray
    cov_ecef: np.ndarray
    corr_ned: np.ndarray
    cov_ned: np.ndarray
    valid: np.ndarray
    n_too_few: int = 0
    sigma: np.ndarray | None = None
    bias: np.ndarray | None = None
    trust: np.ndarray | None = None
    info: dict | None = None
    base: np.ndarray | None = None


def _calibration_scales(config: dict, path, calibrated: bool) -> dict[str, np.ndarray]:
    """Variance scales (name -> (3,) NED), ones where absent or not ``calibrated``: per output (fitted on the
    validation split) and ``unseen_dnn`` / ``unseen_fused`` (fitted on unseen drives by
    ``experiments/crossval.py``; applied on top of the checkpoint's own output's scale only, the one
    they were fitted on)."""
    out = {}
    for name in (*OUTPUTS, "unseen_dnn", "unseen_fused"):
        scale = ((config.get("calibration") or {}).get(name) or {}).get("scale_ned")
        if scale is None or not calibrated:
            out[name] = np.ones(3)
            continue
        scale = np.asarray(scale, float)
        if scale.shape != (3,) or not (np.isfinite(scale).all() and (scale > 0).all()):
            raise CheckpointError(f"{path}: calibration {name} scale_ned must be 3 positive numbers, got {scale.tolist()}")
        out[name] = scale ** 2
    return out


def _input_ranges(config: dict, n_inputs: int, path) -> dict | None:
    """The guard's training ranges ({"lo", "hi"}: n_inputs numbers each, lo <= hi) or None."""
    ranges = config.get("input_ranges")
    if ranges is None:
        return None
    try:
        lo, hi = (np.asarray(ranges[k], float) for k in ("lo", "hi"))
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: input_ranges must be {{'lo': [...], 'hi': [...]}} of numbers") from exc
    if lo.shape != (n_inputs,) or hi.shape != (n_inputs,) or not (np.isfinite(lo) & np.isfinite(hi) & (lo <= hi)).all():
        raise CheckpointError(f"{path}: input_ranges must hold {n_inputs} finite lo <= hi pairs, got lo {lo.shape} "
                              f"and hi {hi.shape}")
    return {"lo": lo.tolist(), "hi": hi.tolist()}


class Corrector:
    """A loaded checkpoint: the learned position (``predict``), prior provider (``provider``) and
    per-satellite noise provider (``slot_noise``).

    Output (``config["output"]``, or the ``output`` argument): ``"wls"``, the least-squares position with the
    per-satellite head's sigmas and biases, iterated from the guess; ``"correction"``, the paper's
    correction head. Covariances are scaled by the checkpoint's calibration (``calibrated=False``: raw).
    The guard (:mod:`learned.guard`) shrinks the correction toward the guess where inputs leave the
    training range. Only the signals the network was trained on are used (``config["signals"]``).
    """

    def __init__(self, model, config: dict, device: str = "cpu", path: Path | None = None,
                 calibrated: bool = True):
        """model: an :class:`learned.npnet.NpNet` (what :meth:`load` builds) or a torch module (tests,
        experiments); device: kept for callers of the torch era, inference runs on the CPU in numpy."""
        self.net, self.config, self.path = as_net(model), config, path
        self.model = model
        try:
            self.features = FeatureConfig.from_dict(config["features"])
        except (TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: bad feature config {config['features']!r}: {exc}") from exc
        # refused here, not at the first forward pass
        d_in = ((config.get("model") or {}).get("hparams") or {}).get("d_in", 4)
        if d_in != self.features.n_inputs:
            raise CheckpointError(f"{path}: the network reads {d_in} channels per satellite but the feature "
                                  f"config {list(self.features.inputs)} makes {self.features.n_inputs}")
        if self.features.clock != "median":
            # Paper-leak reproduction (true receiver clock as an input): never allowed to run in the product.
            raise CheckpointError(f"{path}: trained with features.clock={self.features.clock!r} (the paper's "
                                  "true-clock leak, experiment only); refusing to use it for inference")
        signals = tuple(config.get("signals") or DEFAULT_SIGNALS)
        unknown = [s for s in signals if s not in SIGNALS]
        if unknown:
            raise CheckpointError(f"{path}: unknown training signal(s) {unknown} (known: {', '.join(SIGNALS)})")
        self.signals = signals
        self._signal_idx = np.array([SIGNALS.index(s) for s in signals], np.int8)
        self.output = config.get("output", "correction")
        self.device = device
        self.var_scale = _calibration_scales(config, path, calibrated)
        self.ranges = _input_ranges(config, self.features.n_inputs, path)
        head = config.get("doppler_head")
        self.doppler = None if head is None else DopplerNoise(check_head(head, path))
        self._ctx_cache: tuple[Trace, np.ndarray | None, dict] | None = None

    @classmethod
    def load(cls, path: str | Path | None = None, device: str = "cpu", calibrated: bool = True) -> "Corrector":
        """The checkpoint at ``path`` (.pt or its .npz twin, or an ensemble's .json manifest,
        :mod:`learned.ensemble`; None: the shipped weights), without torch when the .npz is there."""
        path = SHIPPED_WEIGHTS if path is None else Path(path)
        from learned import ensemble             # here: it builds on this module
        if ensemble.is_manifest(path):
            return ensemble.Ensemble.load(path, device=device, calibrated=calibrated)
        if path.is_dir():
            raise CheckpointError(f"{path}: a folder, not a checkpoint file (e.g. {path / SHIPPED_WEIGHTS.name})")
        if not path.is_file():
            raise CheckpointError(f"{path}: checkpoint not found"
                                  + (" (shipped weights missing from learned/weights/)" if path == SHIPPED_WEIGHTS else ""))
        weights, config, read = load_for_inference(path)
        check_config(config, path, KINDS)
        mcfg = config["model"]
        try:
            net = NpNet(mcfg["kind"], mcfg.get("hparams") or {}, weights)
        except (TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: model hyper-parameters do not fit this code: "
                                  f"{type(exc).__name__}: {str(exc)[:200]}") from exc
        try:
            net.check()
        except (KeyError, ValueError) as exc:
            raise CheckpointError(f"{path}: weights do not fit a {mcfg['kind']!r} model with hyper-parameters "
                                  f"{mcfg.get('hparams')}: {type(exc).__name__}: {str(exc)[:200]}") from exc
        return cls(net, config, device=device, path=path, calibrated=calibrated)

    def _context(self, trace: Trace, drop: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The trace's per-slot context (E,S) from its own plain WLS (as in training), cached for the last
        trace and ``drop`` asked (held, so that a new trace can never reuse its identity). ``drop`` (E,S)
        bool: measurements left out of that WLS (faults the robust WLS excluded: a +200 m fault would
        otherwise move the plain fit and so every residual change of its epoch and the next); the slot
        after a dropped one reads as having no previous residual."""
        drop = None if drop is None or not np.any(drop) else np.array(drop, bool)   # a copy: the cache keeps it
        c = self._ctx_cache
        same_drop = c is not None and (c[1] is None if drop is None else c[1] is not None and np.array_equal(c[1], drop))
        if c is None or c[0] is not trace or not same_drop:
            screened = trace if drop is None else dataclasses.replace(trace, mask=trace.mask & ~drop)
            wls = context_wls(screened, self.features.elev_mask_deg)
            if drop is not None:
                wls.resid = np.where(drop, np.nan, wls.resid)
            ctx = slot_context(trace, wls, self.features.elev_mask_deg, heading="heading" in self.features.inputs)
            self._ctx_cache = (trace, drop, ctx.as_dict())
        return self._ctx_cache[2]

    def _asked(self, trace: Trace, init_pos: np.ndarray, valid: np.ndarray, elev: float,
               drop: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Epochs asked (N,), their slot masks (N,S) (valid guess, readable signals, not in ``drop`` (E,S),
        >= 4 above ``elev``), the number of other satellites above ``elev`` (N,) (signals a version-2
        network cannot read), and the number of epochs with too few."""
        E = trace.n_epochs
        if init_pos.shape != (E, 3) or np.shape(valid) != (E,):
            raise GeometryError(f"{trace.name}: init_pos must be ({E}, 3) and valid ({E},), "
                                f"got {init_pos.shape} and {np.shape(valid)}")
        idx = np.flatnonzero(np.asarray(valid, bool) & np.isfinite(init_pos).all(1))
        kept = trace.mask[idx]
        if drop is not None:
            if np.shape(drop) != (E, trace.n_slots):
                raise GeometryError(f"{trace.name}: drop must be ({E}, {trace.n_slots}), got {np.shape(drop)}")
            kept = kept & ~np.asarray(drop, bool)[idx]
        own = kept
        if self.features.version == 2:
            # a GPS-L1 network fed other constellations' slots would see their inter-system clock offsets as
            # residuals it has never met; version 3 reads every signal (its clock offset removed)
            own = own & np.isin(trace.signal[idx], self._signal_idx)
        mask = elevation_mask(trace.sat_pos[idx], own, init_pos[idx], elev)
        # screened faults are counted by the screen, not as signals the network cannot read
        unseen = elevation_mask(trace.sat_pos[idx], kept & ~own, init_pos[idx], elev).sum(1)
        enough = mask.sum(1) >= 4
        return idx[enough], mask[enough], unseen[enough], int((~enough).sum())

    def _forward(self, trace: Trace, idx: np.ndarray, mask: np.ndarray, guess: np.ndarray,
                 drop: np.ndarray | None = None) -> dict:
        """Network outputs for epochs ``idx`` (N,) with slot mask (N,S) at ``guess`` (N,3), in trace slots
        (``drop``: (E,S) measurements left out of the context's WLS too, :meth:`_context`)."""
        ctx = {k: v[idx] for k, v in self._context(trace, drop).items()}
        order = np.argsort(~mask, axis=1, kind="stable")[:, :max(int(mask.sum(1).max(initial=0)), 1)]

        def take(a: np.ndarray) -> np.ndarray:
            return np.take_along_axis(a, order.reshape(order.shape + (1,) * (a.ndim - 2)), axis=1)
        sat_pos, pr, m = take(trace.sat_pos[idx]), take(trace.pr[idx] - ctx["isb"]), take(mask)
        ctx = {k: take(v) for k, v in ctx.items()}
        n_real = m.sum(1)
        parts, chunks = [], list(chunks_by_size(n_real))
        for rows in chunks:
            n = max(int(n_real[rows[-1]]), 1)               # this chunk's largest set (sorted): attention costs n^2
            part = self._chunk(sat_pos[rows, :n], pr[rows, :n], m[rows, :n],
                               {k: v[rows, :n] for k, v in ctx.items()}, guess[rows])
            parts.append({k: pad_slots(v, m.shape[1]) if k in SLOT_OUTPUTS else v for k, v in part.items()})
        counts = {}
        for p in parts:
            for k, v in p.pop("counts").items():
                counts[k] = counts.get(k, 0) + v
        back = np.argsort(np.concatenate(chunks))
        out = {k: np.concatenate([p[k] for p in parts])[back] for k in parts[0]}
        out["counts"] = counts
        for k in SLOT_OUTPUTS:                          # back from compacted to trace slots
            full = np.zeros(mask.shape, out[k].dtype)
            np.put_along_axis(full, order, out[k], axis=1)
            out[k] = np.where(mask, full, False if k == "oor" else np.nan)
        return out

    def _inputs(self, sat_pos, pr, mask, ctx: dict, guess) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
        """Network inputs x (N,S,F), the slots handed to the physical model (N,S), the physical model's
        sigma (N,S) [m] and the guard's counts. Version 3: the guard reads the inputs, then the groups
        it marks read as missing / unknown."""
        fc = self.features
        sin_el = -features_numpy(sat_pos, pr, mask, guess, FeatureConfig(version=fc.version))[0][..., 3]
        if fc.version == 2:
            x, _ = features_numpy(sat_pos, pr, mask, guess, fc, extra=context_channels(ctx, mask, fc))
            return x, slot_out_of_range(x, mask, self.ranges), base_sigma(ctx["pr_sigma"], sin_el), {}
        base = base_sigma(report_sigma(ctx["pr_sigma"], ctx["pr_sigma_ok"], ctx["cn0"]), sin_el)
        x, _ = features_numpy(sat_pos, pr, mask, guess, fc, extra=context_channels(ctx, mask, fc))
        missing, core, counts = feature_guard(x, mask, self.ranges, fc)
        if missing:
            x[..., 4:] = context_channels(ctx, mask, fc, missing)
        return x, core, base, counts

    def _chunk(self, sat_pos, pr, mask, ctx: dict, guess) -> dict:
        """One chunk (N epochs, S slots: sat_pos (N,S,3), pr, mask (N,S), ctx (N,S) arrays, guess (N,3))
        through the network; the learned-weight solution iterated twice from the guess. Slots the guard
        hands to the physical model keep its sigma and no bias."""
        sat_pos = np.where(mask[..., None], sat_pos, 0.0)
        pr = np.where(mask, pr, 0.0)
        x, oor, base, counts = self._inputs(sat_pos, pr, mask, ctx, guess)
        mean, logvar, sat = self.net(x, mask)
        sigma, bias = sat_sigma_bias(sat, self.features.res_scale, base)
        if self.features.version > 2:
            sigma, bias = np.where(oor, base, sigma), np.where(oor, 0.0, bias)
        pos, _ = weighted_ls_step(sat_pos, pr, mask, guess, sigma, bias)
        # the weights come from the guess's features; a second step removes the linearisation error
        pos, cov = weighted_ls_step(sat_pos, pr, mask, pos, sigma, bias)
        s = self.features.out_scale
        R = ned_rotation(guess)
        corr_ned = {"wls": np.einsum("nij,nj->ni", R, pos - guess), "correction": np.asarray(mean, float) * s}
        var_ned = {"wls": np.einsum("nij,njk,nlk->nil", R, cov, R),
                   "correction": np.apply_along_axis(np.diag, 1, np.exp(np.asarray(logvar, float)) * s * s)}
        return {"sigma": sigma, "bias": bias, "oor": oor, "base": base, "R": R, "counts": counts,
                **{f"corr_{k}": v for k, v in corr_ned.items()}, **{f"cov_{k}": v for k, v in var_ned.items()}}

    def predict(self, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                elev_mask_deg: float | None = None, output: str | None = None,
                drop: np.ndarray | None = None) -> Correction:
        """Correct ``init_pos`` (E,3) ECEF at epochs where ``valid`` (E,) and >= 4 satellites of the
        checkpoint's signals clear the elevation mask (checkpoint's, unless given) seen from the guess.
        ``drop``: optional (E,S) bool, measurements the network must not see (e.g. those the robust WLS
        excluded as faults, :attr:`fusion.estimate.wls.WlsResult.excluded`): read as absent slots."""
        E, S = trace.mask.shape
        init_pos = np.asarray(init_pos, float)
        output = output or self.output
        if output not in OUTPUTS:
            raise CheckpointError(f"{self.path}: unknown output {output!r} (known: {', '.join(OUTPUTS)})")
        elev = self.features.elev_mask_deg if elev_mask_deg is None else elev_mask_deg
        idx, mask, unseen, n_too_few = self._asked(trace, init_pos, valid, elev, drop)
        res = Correction(np.full((E, 3), np.nan), np.full((E, 3, 3), np.nan), np.full((E, 3), np.nan),
                         np.full((E, 3, 3), np.nan), np.zeros(E, bool), n_too_few, np.full((E, S), np.nan),
                         np.full((E, S), np.nan), np.full(E, np.nan), base=np.full((E, S), np.nan))
        oor, counts = np.zeros(mask.shape, bool), {}
        if len(idx):
            out = self._forward(trace, idx, mask, init_pos[idx], drop)
            out["trust"] = trust(out["oor"], mask, unseen)
            self._fill(res, out, idx, init_pos[idx], output)
            oor, counts = out["oor"], out["counts"]
        res.info = dict(self.guard_counts(res, mask, oor, unseen), **counts)
        return res

    @staticmethod
    def guard_counts(res: Correction, mask: np.ndarray, oor: np.ndarray, unseen: np.ndarray) -> dict:
        """What the guard did, for the report: epochs asked, epochs with too few satellites, epochs whose
        correction it shrank / switched off, measurements outside the training range (given the physical
        model) and measurements of signals the network cannot read (version 2; version 3 reads them all)."""
        t = res.trust[res.valid]
        return {"epochs_asked": int(res.valid.sum()), "epochs_too_few_sats": int(res.n_too_few),
                "epochs_guard_shrunk": int((t < 1).sum()), "epochs_guard_off": int((t == 0).sum()),
                "meas_asked": int(mask.sum()), "meas_out_of_range": int(oor.sum()),
                "meas_unseen_signal": int(np.sum(unseen))}

    def graph_inputs(self, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                     elev_mask_deg: float | None = None, sigma_power: float | np.ndarray = 1.0) -> LearnedGraphInputs:
        """Everything the graph takes from the network, from ONE pass at ``init_pos`` (E,3) ECEF for the
        epochs in ``valid`` (E,): the position prior (mean (E,3), covariance (E,3,3), ok (E,)), the
        per-slot pseudorange sigma and bias (E,S) [m] (NaN: no opinion; the head's multiplier on its
        physical model raised to ``sigma_power``, see :func:`graph_sigma`: 1 is the head as trained, the
        ``fused`` mode passes ``GraphConfig.learned_sigma_power``), the Doppler head where the
        checkpoint has one (:mod:`learned.doppler_head`; None: the graph's physical model), and the guard's counts."""
        c = self.predict(trace, init_pos, valid, elev_mask_deg=elev_mask_deg)
        # an epoch the guard switched off has its guess as the "prior": information the graph already has
        ok = c.valid & (np.nan_to_num(c.trust) > 0)
        return LearnedGraphInputs(prior_mean=c.mean_ecef, prior_cov=c.cov_ecef, prior_ok=ok,
                                  pr_sigma=graph_sigma(c.sigma, c.base, sigma_power), pr_bias=c.bias,
                                  doppler_noise=self.doppler,
                                  info=dict(c.info or {}, pr_sigma_learned=int(np.isfinite(c.sigma).sum())))

    def _fill(self, res: Correction, out: dict, idx, guess, output: str) -> None:
        """Shrink by the guard's trust, scale the covariance, rotate to ECEF, write rows ``idx``."""
        a = out["trust"]
        corr = out[f"corr_{output}"] * a[:, None]
        # the unseen-drive scale was fitted on the checkpoint's own output (crossval's dnn mode); the fused
        # prior is that same estimate, another output is not
        v = self.var_scale[output] * (self.var_scale["unseen_dnn"] if output == self.output else 1.0)
        # what the shrink left out is uncertainty the covariance must carry
        cov = out[f"cov_{output}"] * np.sqrt(np.outer(v, v))
        cov = cov + np.apply_along_axis(np.diag, 1, ((1 - a)[:, None] * out[f"corr_{output}"]) ** 2)
        R = out["R"]
        res.corr_ned[idx], res.cov_ned[idx], res.trust[idx], res.valid[idx] = corr, cov, a, True
        res.mean_ecef[idx] = guess + np.einsum("nji,nj->ni", R, corr)
        res.cov_ecef[idx] = np.einsum("nji,njk,nkl->nil", R, cov, R)
        # version 2: no opinion on out-of-range slots; version 3 gives them the physical model
        off = out["oor"] & (self.features.version == 2)
        res.sigma[idx] = np.where(off, np.nan, out["sigma"])
        res.bias[idx] = np.where(off, np.nan, out["bias"])
        res.base[idx] = np.where(off, np.nan, out["base"])

    def __call__(self, trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
        return self.provider()(trace, init_pos, valid)

    def provider(self, elev_mask_deg: float | None = None):
        """This corrector as a graph prior provider ``(trace, init_pos, valid) -> (mean_ecef, cov_ecef,
        valid)`` with the elevation mask fixed (None: the checkpoint's), so that the ``fused`` mode
        feeds the network what ``dnn`` does under the same ``--elev-mask``."""
        def ask(trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
            c = self.predict(trace, init_pos, valid, elev_mask_deg=elev_mask_deg)
            return c.mean_ecef, c.cov_ecef, c.valid
        return ask

    def slot_noise(self, elev_mask_deg: float | None = None, sigma_power: float = 1.0):
        """This corrector as a graph slot-noise provider ``(trace, init_pos, valid) -> (sigma (E,S),
        bias (E,S))`` [m], NaN where it has no opinion (the graph then keeps its default sigma); the sigma
        as :func:`graph_sigma` makes it for ``sigma_power`` (1: the head as trained)."""
        def ask(trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
            c = self.predict(trace, init_pos, valid, elev_mask_deg=elev_mask_deg)
            return graph_sigma(c.sigma, c.base, sigma_power), c.bias
        return ask


def graph_sigma(sigma: np.ndarray, base: np.ndarray, power: float | np.ndarray) -> np.ndarray:
    """The head's pseudorange sigma for a smoother: ``base * (sigma / base) ** power``, all (E,S) [m]; ``power``
    a number or per epoch (E,1).

    The head is trained on one epoch's error, and a smoother averages epochs: a pseudorange the head
    finds worse than the physical model is mostly multipath or a reflection, whose error lasts for many
    epochs and does not average away, so the graph needs it down-weighted more than one epoch's
    variance says (and the clean ones up-weighted). ``power`` 1 is the head as trained. The raised
    log-multiplier keeps the head's own clamp (:data:`learned.heads.LOGSIG_RANGE`, 1/55 to 55 x the model):
    one satellite at millimetres would make the graph's normal equations ill-conditioned.
    """
    if np.all(np.asarray(power) == 1.0):
        return sigma
    with np.errstate(invalid="ignore", divide="ignore"):
        return base * np.exp(np.clip(power * np.log(sigma / base), *LOGSIG_RANGE))


def calibration(err_ned: np.ndarray, cov_ned: np.ndarray) -> dict:
    """Fraction of |error| within 1 and 2 predicted sigma per NED axis (ideal Gaussian: 0.683 / 0.954).

    err_ned (N,3) [m], cov_ned (N,3,3) [m^2]; rows with NaN are ignored.
    """
    ok = np.isfinite(err_ned).all(1) & np.isfinite(cov_ned).all((1, 2))
    sig = np.sqrt(np.diagonal(cov_ned[ok], axis1=1, axis2=2))
    z = np.abs(err_ned[ok]) / sig
    return {"n": int(ok.sum()), "within_1sigma": (z <= 1).mean(0).tolist() if ok.any() else [np.nan] * 3,
            "within_2sigma": (z <= 2).mean(0).tolist() if ok.any() else [np.nan] * 3}


