"""The GTSAM factor graph: factor conventions, batch and incremental solves, robustness."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fusion.errors import GeometryError, GnssfuseError
from fusion.geometry import C_LIGHT, geodetic2ecef, line_of_sight, ned2ecef_vec
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import pseudorange_factor_xc
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.keys import clock_key, isb_key, pos_key
from fusion.eval.metrics import ned_errors
from fusion.run_types import RunOptions
from fusion.trace import SIGNALS, Trace, empty_trace
from fusion.estimate.wls import solve_wls

R_ORBIT = 26_560e3


def synth_trace(E: int = 120, S: int = 8, seed: int = 0, pr_noise_m: float = 3.0,
                speed_mps: float = 12.0, clock_drift_mps: float = 40.0) -> Trace:
    """A vehicle driving a gentle curve in Mountain View seen by S GPS-like satellites.

    Pseudoranges are built with the exact Sagnac rotation of ``fusion.geometry`` so the graph is
    tested against our own measurement model; the clock drifts like a phone's.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(E, dtype=float)
    heading = np.radians(30.0 + 0.3 * t)                     # slowly turning
    north = np.cumsum(speed_mps * np.cos(heading))
    east = np.cumsum(speed_mps * np.sin(heading))
    origin = geodetic2ecef(np.array([37.42, -122.08, -20.0]))
    truth = origin + ned2ecef_vec(np.stack([north, east, np.zeros(E)], axis=1), origin)
    az = np.radians(np.linspace(0, 360, S, endpoint=False) + 17.0)
    el = np.radians(np.array([15, 25, 40, 55, 70, 35, 20, 80][:S] + [45] * max(0, S - 8)))
    los_ned = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)], axis=1)
    los = ned2ecef_vec(los_ned, origin)                      # (S,3) unit, fixed over the short drive
    # distance d along los so that |origin + d los| = R_ORBIT
    b = los @ origin
    d = -b + np.sqrt(b ** 2 - (origin @ origin - R_ORBIT ** 2))
    sats = origin + d[:, None] * los
    sat_pos = np.broadcast_to(sats, (E, S, 3)).copy()
    sat_pos += np.arange(E)[:, None, None] * np.array([0.0, 0.0, 300.0])  # satellites move
    clock = 3000.0 + clock_drift_mps * t
    rng_true, _ = line_of_sight(sat_pos, truth)
    kw = empty_trace(E, S, name="synth", with_truth=True)
    kw.update(t_ms=(1_300_000_000_000 + 1000 * np.arange(E)).astype(np.int64), sat_pos=sat_pos,
              pr=rng_true + clock[:, None] + rng.normal(0, pr_noise_m, (E, S)),
              pr_sigma=np.full((E, S), 3.0), sat_id=np.broadcast_to(1001 + np.arange(S), (E, S)).astype(np.int32),
              mask=np.ones((E, S), bool), truth=truth)
    return Trace(**kw)


def assert_centimetres_apart(a: np.ndarray, b: np.ndarray) -> None:
    """Two solves of one graph from different starts, both stopped at lm_rel_tol: positions (E,3) a median
    1 cm and at most 5 cm apart."""
    gap = np.linalg.norm(a - b, axis=1)
    assert np.nanmedian(gap) < 0.01 and np.nanmax(gap) < 0.05


def h_err(trace: Trace, pos: np.ndarray, valid: np.ndarray) -> np.ndarray:
    e = ned_errors(np.where(valid[:, None], pos, np.nan), trace.truth)
    return np.hypot(e[:, 0], e[:, 1])


def truth_prior(sigma_m: float, seed: int = 1):
    """Test-only position prior provider: truth + Gaussian noise of known sigma (a stand-in for the DNN)."""
    def provider(trace, init_pos, valid):
        r = np.random.default_rng(seed)
        mean = trace.truth + r.normal(0, sigma_m, trace.truth.shape)
        cov = np.tile(np.eye(3) * sigma_m ** 2, (trace.n_epochs, 1, 1))
        return mean, cov, np.asarray(valid, bool).copy()
    return provider


# ---------------------------------------------------------------------------- factor convention
def test_pseudorange_factor_matches_our_model_including_sagnac():
    tr = synth_trace(E=2, pr_noise_m=0.0)
    rx = tr.truth[0] + np.array([30.0, -20.0, 10.0])
    clock_m = 1234.5
    rng, _ = line_of_sight(tr.sat_pos[0], rx)
    for s in range(tr.n_slots):
        f = pseudorange_factor_xc(0, tr.pr[0, s], tr.sat_pos[0, s], gtsam.noiseModel.Isotropic.Sigma(1, 1.0))
        got = f.evaluateError(rx, clock_m / C_LIGHT)[0]
        ours = rng[s] + clock_m - tr.pr[0, s]                    # predicted - measured
        assert got == pytest.approx(ours, abs=5e-3)
    # without Sagnac the plain geometric range would be off by metres for at least one satellite
    plain = np.linalg.norm(tr.sat_pos[0] - rx, axis=1) + clock_m - tr.pr[0]
    assert np.max(np.abs(plain - (rng + clock_m - tr.pr[0]))) > 1.0


def test_single_epoch_graph_equals_wls():
    tr = synth_trace(E=1, pr_noise_m=2.0)
    wls = solve_wls(tr, weighting="elevation")
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for s in range(tr.n_slots):
        g.add(pseudorange_factor_xc(0, tr.pr[0, s], tr.sat_pos[0, s], gtsam.noiseModel.Isotropic.Sigma(1, 1.0)))
    v.insert(pos_key(0), wls.pos[0] + 50.0)
    v.insert(clock_key(0), 0.0)
    res = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
    # unweighted graph vs elevation-weighted WLS differ slightly; both near truth, clock in seconds works
    assert np.linalg.norm(res.atPoint3(pos_key(0)) - tr.truth[0]) < 15.0
    assert res.atDouble(clock_key(0)) * C_LIGHT == pytest.approx(wls.clock_m[0], abs=15.0)


# ---------------------------------------------------------------------------- batch and incremental
@pytest.fixture(scope="module")
def trace():
    return synth_trace()


@pytest.fixture(scope="module")
def wls(trace):
    return solve_wls(trace)


def test_fused_nodnn_beats_wls(trace, wls):
    res = fuse(trace, wls, RunOptions())
    e_wls, e_g = h_err(trace, wls.pos, wls.valid), h_err(trace, res.pos, res.valid)
    assert res.valid.all()
    assert np.median(e_g) < 0.7 * np.median(e_wls)
    assert res.cov is not None and np.all(np.linalg.eigvalsh(res.cov)[:, 0] > 0)


def test_learned_prior_helps_and_incremental_matches_batch(trace, wls):
    batch = fuse(trace, wls, RunOptions(), provider=truth_prior(1.0))
    nodnn = fuse(trace, wls, RunOptions())
    assert np.median(h_err(trace, batch.pos, batch.valid)) < np.median(h_err(trace, nodnn.pos, nodnn.valid))
    inc = fuse(trace, wls, RunOptions(graph=GraphConfig(incremental=True)), provider=truth_prior(1.0))
    assert inc.valid.all()
    assert np.max(np.linalg.norm(inc.pos - batch.pos, axis=1)) < 0.5
    assert inc.info["online_pos"].shape == (trace.n_epochs, 3)
    # the same graph's marginals at ISAM2's estimate: close to the batch solution's, where the two nearly agree
    np.testing.assert_allclose(inc.cov, batch.cov, rtol=0.05, atol=0.01)          # m^2, against ~2 m^2
    assert fuse(trace, wls, RunOptions(graph=GraphConfig(incremental=True)), provider=truth_prior(1.0),
                want_cov=False).cov is None


@pytest.mark.parametrize("motion", ["rw", "cv"])
@pytest.mark.parametrize("incremental", [False, True])
def test_a_trace_of_three_epochs_solves(trace, motion, incremental):
    """Three epochs' motion variances (3,3) were once read as one covariance matrix (fusion.geometry)."""
    short = trace.select(np.arange(3))
    res = fuse(short, solve_wls(short), RunOptions(), cfg=GraphConfig(motion=motion, incremental=incremental))
    assert res.valid.all() and np.all(np.linalg.eigvalsh(res.cov)[:, 0] > 0)
    assert np.max(h_err(short, res.pos, res.valid)) < 10.0


@pytest.mark.parametrize("motion", ["rw", "cv"])
def test_both_motion_models_solve(trace, wls, motion):
    res = fuse(trace, wls, RunOptions(), cfg=GraphConfig(motion=motion), want_cov=False)
    assert res.valid.all()
    assert np.median(h_err(trace, res.pos, res.valid)) < np.median(h_err(trace, wls.pos, wls.valid))


# ---------------------------------------------------------------------------- robustness
def test_epochs_with_few_satellites_are_carried(trace):
    mask = trace.mask.copy()
    mask[40:50, 2:] = False                 # 2 satellites for 10 s: WLS cannot solve these
    mask[60:63, :] = False                  # no satellite at all for 3 s
    tr = Trace(**{**trace.__dict__, "mask": mask})
    w = solve_wls(tr)
    assert not w.valid[40:50].any()
    res = fuse(tr, w, RunOptions(), provider=truth_prior(2.0))
    assert res.valid.all()
    e = h_err(tr, res.pos, res.valid)
    assert np.max(e[40:63]) < 10.0
    res0 = fuse(tr, w, RunOptions())        # no prior: motion alone carries them, less well
    assert res0.valid.all() and np.max(h_err(tr, res0.pos, res0.valid)[40:63]) < 60.0


def test_gross_outliers_do_not_pull_the_solution(trace, wls):
    rng = np.random.default_rng(7)
    pr = trace.pr.copy()
    hit = rng.random(pr.shape) < 0.08
    pr[hit] += 200.0
    bad = Trace(**{**trace.__dict__, "pr": pr})
    wb = solve_wls(bad)
    clean = fuse(trace, wls, RunOptions(), want_cov=False)
    robust = fuse(bad, wb, RunOptions(), want_cov=False)
    plain = fuse(bad, wb, RunOptions(), cfg=GraphConfig(unlearned_robust="none"), want_cov=False)
    e_c, e_r, e_p = (np.percentile(h_err(trace, r.pos, r.valid), 95) for r in (clean, robust, plain))
    assert e_r < e_p                        # the robust loss matters
    assert e_r < e_c + 3.0                  # and nearly undoes the damage


def test_clock_jump_breaks_only_the_clock_chain(trace):
    pr = trace.pr.copy()
    pr[70:] += 150_000.0                    # a 0.5 ms receiver clock step
    tr = Trace(**{**trace.__dict__, "pr": pr})
    w = solve_wls(tr)
    res = fuse(tr, w, RunOptions(), want_cov=False)
    assert res.info["clock_resets"] >= 1
    e = h_err(tr, res.pos, res.valid)
    assert res.valid.all() and np.max(e[65:75]) < 15.0


def test_undetermined_epoch_raises_or_is_dropped(trace):
    keep = np.r_[0:50, 80:81, 110:120]      # epoch 80 isolated by 30 s gaps on both sides
    tr = trace.select(keep)
    mask = tr.mask.copy()
    mask[50, 3:] = False                    # ...and only 3 satellites there
    tr = Trace(**{**tr.__dict__, "mask": mask})
    w = solve_wls(tr)
    with pytest.raises(GeometryError, match=r"epoch 50 .*undetermined"):
        fuse(tr, w, RunOptions(), on_undetermined="raise")
    res = fuse(tr, w, RunOptions())
    assert not res.valid[50] and res.valid[np.arange(tr.n_epochs) != 50].all()
    assert res.info["epochs_undetermined"] == 1
    # with a prior the same epoch is determined
    res = fuse(tr, w, RunOptions(), provider=truth_prior(2.0), on_undetermined="raise")
    assert res.valid.all()


def test_bad_provider_shapes_are_reported(trace, wls):
    def broken(tr, init_pos, valid):
        return init_pos[:5], np.zeros((5, 3, 3)), valid[:5]
    with pytest.raises(GeometryError, match="prior provider returned shapes"):
        fuse(trace, wls, RunOptions(), provider=broken)


def test_non_spd_prior_covariances_are_skipped_and_counted(trace, wls):
    def sloppy(tr, init_pos, valid):
        mean, cov, ok = truth_prior(1.0)(tr, init_pos, valid)
        cov[::10] = 0.0                     # singular covariance on every tenth epoch
        mean[5] = np.nan
        return mean, cov, ok
    res = fuse(trace, wls, RunOptions(), provider=sloppy, want_cov=False)
    assert res.valid.all()
    assert res.info["prior_rejected"] == 12 + 1
    assert res.info["priors_used"] == trace.n_epochs - 13


# ---------------------------------------------------------------------------- pipeline wiring
def test_fused_modes_run_through_the_pipeline_registry(trace, wls, tmp_path):
    torch = pytest.importorskip("torch")
    from learned.checkpoint import save_checkpoint
    from learned.features import FeatureConfig
    from learned.model import build_model
    from fusion.modes import run_modes

    torch.manual_seed(0)
    hp = dict(d_model=16, n_heads=2, dim_feedforward=16, n_encoder=1, n_decoder=1)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model("set", **hp),
                           {"model": {"kind": "set", "hparams": hp}, "features": FeatureConfig().to_dict()})
    out = run_modes(trace, ["fused", "fused-nodnn"], RunOptions(weights=ckpt, dnn_passes=2), wls=wls)
    assert out["fused"].valid.all() and out["fused-nodnn"].valid.all()
    assert out["fused"].info["priors_used"] > 0 and out["fused-nodnn"].info["priors_used"] == 0
    assert out["fused"].cov.shape == (trace.n_epochs, 3, 3)
    # the prior's widening by the residuals' variance factor (GraphConfig.prior_factor_*) is wired in and counted
    info = out["fused"].info
    assert 0 <= info["learned_prior_widened"] <= info["priors_used"] and info["learned_prior_factor_p50"] > 0
    off = RunOptions(weights=ckpt, graph=GraphConfig(prior_factor_power=0.0))
    assert "learned_prior_widened" not in run_modes(trace, ["fused"], off, wls=wls)["fused"].info
    # the sigmas' power ramp (GraphConfig.learned_sigma_power_high) reaches the graph: on the trace with 40 m of
    # extra noise in its second half (variance factor far above 1 there) the high power moves the answer
    from dataclasses import replace as _replace
    from learned.modes import residual_factor
    rng = np.random.default_rng(1)
    half = np.arange(trace.n_epochs)[:, None] >= trace.n_epochs // 2
    noisy = _replace(trace, pr=trace.pr + np.where(half, rng.normal(0.0, 40.0, trace.pr.shape), 0.0))
    noisy_wls = solve_wls(noisy)
    plain = run_modes(noisy, ["fused"], RunOptions(weights=ckpt), wls=noisy_wls)["fused"]
    assert np.sum(residual_factor(noisy, plain.info["unlearned_pos"], RunOptions()) > 1.01) > 0
    ramp = RunOptions(weights=ckpt, graph=GraphConfig(learned_sigma_power_high=12.0,
                                                      learned_sigma_power_f_high=1.01))
    moved = run_modes(noisy, ["fused"], ramp, wls=noisy_wls)["fused"].pos - plain.pos
    assert np.nanmax(np.abs(moved)) > 1e-3


def test_iterated_provider_feeds_each_pass_the_previous_mean(trace):
    from learned.modes import iterated

    calls = []

    def step(tr, init_pos, valid):           # moves every guess 1 m north-ish in ECEF z
        calls.append(init_pos.copy())
        return init_pos + np.array([0, 0, 1.0]), np.tile(np.eye(3), (tr.n_epochs, 1, 1)), valid.copy()
    init = trace.truth.copy()
    mean, _, ok = iterated(step, 3)(trace, init, np.ones(trace.n_epochs, bool))
    assert len(calls) == 3 and ok.all()
    np.testing.assert_allclose(mean - init, np.tile([0, 0, 3.0], (trace.n_epochs, 1)))
    np.testing.assert_allclose(calls[2] - init, np.tile([0, 0, 2.0], (trace.n_epochs, 1)))


def test_loader_flagged_clock_reset_breaks_the_clock_chain(trace):
    pr = trace.pr.copy()
    pr[70:] += 60.0                          # a small step, below the WLS jump detector's threshold
    reset = np.zeros(trace.n_epochs, bool)
    reset[70] = True
    flagged = Trace(**{**trace.__dict__, "pr": pr, "clock_reset": reset})
    w = solve_wls(flagged)
    res = fuse(flagged, w, RunOptions(), want_cov=False)
    assert res.info["clock_resets"] == 1
    assert np.max(h_err(flagged, res.pos, res.valid)[66:75]) < 8.0


def test_real_trace_graph_beats_wls(shipped_trace_dir):
    if not shipped_trace_dir.is_dir():
        pytest.skip("shipped trace not present")
    from fusion.prepare.load import load_trace

    tr = load_trace(shipped_trace_dir).select(np.arange(300, 700))
    w = solve_wls(tr)
    for opts in (RunOptions(), RunOptions(graph=GraphConfig(incremental=True))):
        res = fuse(tr, w, opts, want_cov=False)
        assert res.valid.all()
        e_g, e_w = h_err(tr, res.pos, res.valid), h_err(tr, w.pos, w.valid)
        assert np.median(e_g) < 0.8 * np.median(e_w) and np.percentile(e_g, 95) < np.percentile(e_w, 95)


def test_provider_is_asked_once_at_the_initial_positions(trace, wls):
    """One question per run: the provider sees the WLS track (the graph is built and solved once)."""
    seen = []

    def spy(tr, init_pos, valid):
        seen.append(init_pos.copy())
        return truth_prior(1.0)(tr, init_pos, valid)
    res = fuse(trace, wls, RunOptions(), provider=spy, want_cov=False, cfg=GraphConfig(prior_robust="huber"))
    assert res.valid.all() and len(seen) == 1
    np.testing.assert_allclose(seen[0], wls.pos)


def test_learned_inputs_and_providers_give_the_same_graph(trace, wls):
    from fusion.estimate.graph.priors import LearnedGraphInputs

    prov = truth_prior(1.0)
    mean, cov, ok = prov(trace, wls.pos, wls.valid)
    a = fuse(trace, wls, RunOptions(), provider=prov, want_cov=False)
    b = fuse(trace, wls, RunOptions(), learned=LearnedGraphInputs(prior_mean=mean, prior_cov=cov, prior_ok=ok,
                                                                  info={"guard_off": 0}), want_cov=False)
    np.testing.assert_allclose(a.pos, b.pos, atol=1e-9)
    assert b.info["guard_off"] == 0 and b.info["priors_used"] == trace.n_epochs
    with pytest.raises(GnssfuseError, match="not both"):
        fuse(trace, wls, RunOptions(), provider=prov, learned=LearnedGraphInputs())


# ---------------------------------------------------------------------------- < 4 satellites, real data
def _thinned_trace_dir(src, dst, n_epochs: int = 240, thin=(100, 106), keep_sats: int = 2):
    """Copy the first ``n_epochs`` epochs of a real GSDC 2021 trace folder, keeping only
    ``keep_sats`` satellites in the epochs ``thin[0]:thin[1]`` (an urban-canyon outage)."""
    import pandas as pd

    df = pd.read_csv(next(src.glob("*_derived.csv*")))
    t = np.sort(df["millisSinceGpsEpoch"].unique())[:n_epochs]
    df = df[df["millisSinceGpsEpoch"].isin(t)]
    thin_t = t[thin[0]:thin[1]]
    rank = df.groupby("millisSinceGpsEpoch").cumcount()
    df = df[~df["millisSinceGpsEpoch"].isin(thin_t) | (rank < keep_sats)]
    dst.mkdir(parents=True)
    df.to_csv(dst / f"{src.name}_derived.csv", index=False)
    (dst / "ground_truth.csv").write_bytes((src / "ground_truth.csv").read_bytes())
    return thin_t


def test_cli_keeps_and_fused_solves_two_satellite_epochs(shipped_trace_dir, tmp_path):
    """``gnssfuse run`` loads with min_sats=1: WLS leaves 2-satellite epochs unsolved and counts them,
    the graph carries them with motion + their two pseudoranges (fused-nodnn) and with the learned
    prior where the network has one (fused: the corrector declines < 4 satellites, so motion too)."""
    import json

    import pandas as pd

    from fusion.cli.run import main

    if not shipped_trace_dir.is_dir():
        pytest.skip("shipped trace not present")
    d = tmp_path / "2021-04-28-US-MTV-1" / "Pixel4"
    thin_t = _thinned_trace_dir(shipped_trace_dir, d)
    out = {}
    for mode in ("wls", "fused-nodnn", "fused"):
        assert main([str(d), "--mode", mode, "--out", str(tmp_path / mode)]) == 0
        est = pd.read_csv(tmp_path / mode / "estimates.csv")
        rec = json.loads((tmp_path / mode / "metrics.json").read_text())
        assert rec["epochs_total"] == 240 and "epochs_lt4_sats" not in rec["skipped"]
        out[mode] = (est, rec)
    est_w, rec_w = out["wls"]
    assert rec_w["epochs_solved"] == 240 - len(thin_t) and rec_w["info"]["lt4_sats"] == len(thin_t)
    from fusion.prepare.load import load_trace

    tr = load_trace(d, min_sats=1)
    few = np.flatnonzero(tr.n_sats == 2)
    assert few.size == len(thin_t)
    for mode in ("fused-nodnn", "fused"):
        est, rec = out[mode]
        assert rec["epochs_solved"] == 240
        pos = est[["x_m", "y_m", "z_m"]].to_numpy()
        assert np.isin(tr.t_ms[few], est["gps_millis"]).all()
        e = h_err(tr, pos, np.ones(len(pos), bool))
        # the 6-s outage stays within a few metres of the solution around it
        assert np.max(e[few]) < max(15.0, 3 * np.median(e)), (mode, e[few])


# ---------------------------------------------------------------------------- a safe learned prior
def test_prior_robust_loss_acts_on_the_mahalanobis_distance():
    from fusion.estimate.graph.factors import robust_model

    model = robust_model("huber", 1.0, gtsam.noiseModel.Gaussian.Covariance(np.diag([100.0, 1.0, 1.0])))
    f = gtsam.PriorFactorPoint3(pos_key(0), np.zeros(3), model)

    def err(off):
        v = gtsam.Values()
        v.insert(pos_key(0), np.asarray(off, float))
        return f.error(v)
    assert err([5, 0, 0]) == pytest.approx(0.5 * 0.5 ** 2)      # 0.5 sigma: quadratic
    assert err([0, 5, 0]) == pytest.approx(1.0 * 5 - 0.5)       # 5 sigma: Huber's linear branch
    with pytest.raises(GeometryError, match="robust loss"):
        robust_model("tukey", 1.0, model)


def test_a_wrong_overconfident_prior_cannot_drag_the_solution(trace, wls):
    """The network is sometimes confidently wrong: 60 m off with a claimed 1 m sigma for 10 s."""
    def bad(tr, init_pos, valid):
        mean, cov, ok = truth_prior(1.0)(tr, init_pos, valid)
        mean = mean.copy()
        mean[30:40] += ned2ecef_vec(np.array([60.0, 0.0, 0.0]), tr.truth[30])
        return mean, cov, ok
    safe = fuse(trace, wls, RunOptions(), provider=bad, want_cov=False)          # the defaults
    naive = fuse(trace, wls, RunOptions(), provider=bad, want_cov=False,
                 cfg=GraphConfig(prior_robust="none", prior_cov_scale=1.0, prior_sigma_floor_m=0.0))
    nodnn = fuse(trace, wls, RunOptions(), want_cov=False)
    e_safe, e_naive = h_err(trace, safe.pos, safe.valid), h_err(trace, naive.pos, naive.valid)
    e_nodnn = h_err(trace, nodnn.pos, nodnn.valid)
    assert np.max(e_naive[30:40]) > 20.0                      # an unprotected prior is dragged
    assert np.max(e_safe[30:40]) < np.max(e_nodnn[30:40]) + 3.0
    # and the good part of the prior still helps elsewhere
    assert np.median(e_safe[50:]) < np.median(e_nodnn[50:])
    with pytest.raises(GeometryError, match="prior_cov_scale"):
        fuse(trace, wls, RunOptions(), provider=bad, cfg=GraphConfig(prior_cov_scale=0.0))


# ---------------------------------------------------------------------------- inter-system biases
def _two_system_trace(isb_m: float, seed: int = 0, E: int = 120, gap_at: int | None = None) -> Trace:
    """synth_trace with its last 4 of 10 satellites relabelled GLONASS G1 and offset by ``isb_m``."""
    tr = synth_trace(E=E, S=10, seed=seed, pr_noise_m=1.0)
    glo = np.zeros(tr.n_slots, bool)
    glo[6:] = True
    tr.signal[:, glo] = SIGNALS.index("GLO_G1")
    tr.sat_id[:, glo] = 3001 + np.arange(glo.sum())
    tr.pr[:, glo] += isb_m
    if gap_at is not None:                      # a 60 s gap: two motion components
        tr.t_ms[gap_at:] += 60_000
    return tr


def test_differential_factor_carries_minus_the_bias():
    tr = synth_trace(E=2, pr_noise_m=0.0)
    rx, clock_m, isb = tr.truth[0] + np.array([5.0, -3.0, 2.0]), 800.0, 4.25
    rng, _ = line_of_sight(tr.sat_pos[0], rx)
    f = gtsam.DifferentialPseudorangeFactor(pos_key(0), clock_key(0), isb_key(0, 0), float(tr.pr[0, 0]), tr.sat_pos[0, 0], 0.0,
                                            gtsam.noiseModel.Isotropic.Sigma(1, 1.0))
    v = gtsam.Values()
    v.insert(pos_key(0), rx)
    v.insert(clock_key(0), clock_m / C_LIGHT)
    v.insert(isb_key(0, 0), -isb)
    assert f.unwhitenedError(v)[0] == pytest.approx(rng[0] + clock_m + isb - tr.pr[0, 0], abs=5e-3)


@pytest.mark.parametrize("incremental", [False, True])
def test_inter_system_bias_is_estimated_and_removes_the_error(incremental):
    biased = _two_system_trace(isb_m=12.0, gap_at=70)
    clean = _two_system_trace(isb_m=0.0, gap_at=70)
    opts = RunOptions(graph=GraphConfig(incremental=incremental))
    wls = solve_wls(biased)
    on = fuse(biased, wls, opts, cfg=GraphConfig(isb="window"), want_cov=False)
    off = fuse(biased, wls, opts, cfg=GraphConfig(isb="none"), want_cov=False)
    ref = fuse(clean, solve_wls(clean), opts, cfg=GraphConfig(isb="window"), want_cov=False)
    # one bias per component, each close to the simulated 12 m
    assert sorted(on.info["isb_m"]) == ["GLO_G1@0", "GLO_G1@1"]
    assert np.allclose(list(on.info["isb_m"].values()), 12.0, atol=1.0)
    e_on, e_off, e_ref = (np.median(h_err(biased, r.pos, r.valid)) for r in (on, off, ref))
    assert e_on < 0.5 * e_off
    assert e_on == pytest.approx(e_ref, abs=0.3)   # as good as the trace without a bias


def test_bias_states_start_where_a_group_first_appears_in_each_component():
    tr = _two_system_trace(isb_m=5.0, gap_at=70)
    tr.mask[:20, 6:] = False                    # GLONASS only from epoch 20 on in component 0
    wls = solve_wls(tr)
    inp = prepare_inputs(tr, wls, GraphConfig())
    assert inp.isb.groups == (SIGNALS.index("GLO_G1"),)
    assert np.flatnonzero(inp.isb.new[:, 0]).tolist() == [20, 70]
    assert np.isfinite(inp.isb.init_m).all()   # a starting value only: WLS has absorbed part of the bias
    assert (inp.isb.group[inp.sel & (tr.signal == 0)] == -1).all()


def test_single_signal_traces_get_no_bias_state(trace, wls):
    on = fuse(trace, wls, RunOptions(), cfg=GraphConfig(isb="window"), want_cov=False)
    off = fuse(trace, wls, RunOptions(), cfg=GraphConfig(isb="none"), want_cov=False)
    assert on.info["isb_m"] == {} and on.info["factors"] == off.info["factors"]
    np.testing.assert_array_equal(on.pos, off.pos)


def test_unknown_isb_model_is_rejected(trace, wls):
    tr = _two_system_trace(isb_m=0.0)
    with pytest.raises(GeometryError, match="isb"):
        fuse(tr, solve_wls(tr), RunOptions(), cfg=GraphConfig(isb="perepoch"), want_cov=False)


@pytest.mark.parametrize("incremental", [False, True])
def test_prior_alone_solves_when_the_no_prior_graph_determines_nothing(trace, wls, incremental):
    """WLS solved but none of its satellites is usable: the no-prior graph (the default guess for the
    provider) solves nothing, so the provider is asked at the initial positions. Incremental mode used
    to crash with KeyError('online_pos') here."""
    import dataclasses

    nothing = dataclasses.replace(wls, used=np.zeros_like(wls.used))
    res = fuse(trace, nothing, RunOptions(graph=GraphConfig(incremental=incremental)), provider=truth_prior(1.0), want_cov=False)
    assert res.valid.all() and res.info["priors_used"] == trace.n_epochs
    assert np.median(h_err(trace, res.pos, res.valid)) < 2.0


def test_clock_jump_at_an_epoch_wls_cannot_solve_still_breaks_the_chain(trace):
    pr = trace.pr.copy()
    pr[70:] += 150_000.0                    # the step lands on an epoch with 3 satellites...
    mask = trace.mask.copy()
    mask[70:72, 3:] = False                 # ...so WLS has no clock there to see it by
    tr = Trace(**{**trace.__dict__, "pr": pr, "mask": mask})
    w = solve_wls(tr)
    assert not w.valid[70:72].any() and w.valid[69] and w.valid[72]
    res = fuse(tr, w, RunOptions(), want_cov=False)
    assert res.info["clock_resets"] == 1     # one jump, though two epochs are marked
    e = h_err(tr, res.pos, res.valid)
    assert res.valid.all() and np.max(e[65:75]) < 15.0


def test_fused_feeds_the_network_the_runs_elevation_mask(trace, wls, tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from learned.checkpoint import save_checkpoint
    from learned.features import FeatureConfig
    from learned.infer import Corrector
    from learned.model import build_model
    from fusion.modes import run_modes

    hp = dict(d_model=16, n_heads=2, dim_feedforward=16, n_encoder=1, n_decoder=1)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model("set", **hp),
                           {"model": {"kind": "set", "hparams": hp}, "features": FeatureConfig().to_dict()})
    seen = []
    real = Corrector.predict

    def spy(self, trace, init_pos, valid, elev_mask_deg=None, **kw):
        seen.append(elev_mask_deg)
        return real(self, trace, init_pos, valid, elev_mask_deg=elev_mask_deg, **kw)
    monkeypatch.setattr(Corrector, "predict", spy)
    run_modes(trace, ["dnn", "fused"], RunOptions(weights=ckpt, elev_mask_deg=17.0), wls=wls)
    # dnn once, fused once for its prior and its slot noise and once more for its sigmas
    # (GraphConfig.learned_sigma_passes): all with the run's mask
    assert seen == [17.0, 17.0, 17.0]


def test_an_outage_is_flagged_as_bridged_with_its_length(trace, wls):
    """Epochs with < 4 satellites carried by the motion model are counted, timed and flagged per epoch,
    and their sigmas grow through the outage (at the motion model's own velocity walk: with
    bridged_accel_scale 0.5 they grow 1.6x here)."""
    import dataclasses

    tr = _outage(trace)                                        # 10 epochs with 2 satellites
    opts = RunOptions()
    res = fuse(tr, solve_wls(tr), dataclasses.replace(opts, graph=dataclasses.replace(opts.graph,
                                                                                       bridged_accel_scale=1.0)))
    assert res.info["epochs_bridged"] == 10 and res.info["bridged"][40:50].all()
    assert not res.info["bridged"][:40].any() and not res.info["bridged"][50:].any()
    dt = np.diff(tr.t_ms[[39, 50]]).item() / 1000.0
    assert res.info["longest_bridge_s"] == pytest.approx(dt)
    sd = np.sqrt(np.trace(res.cov, axis1=1, axis2=2))
    assert sd[45] > 2 * sd[20]
    from fusion.io.estimates import estimates_frame
    assert estimates_frame(tr, res)["bridged"].sum() == 10


def test_satellites_are_counted_once_whatever_their_signals():
    """satellite_counts: two frequencies of one satellite are one satellite; unselected slots none; slots without
    a satellite number (0) one each."""
    from fusion.trace import satellite_counts

    sat_id = np.array([[5, 5, 7, 9, 0], [3, 4, 3, 4, 3], [1, 2, 3, 4, 5], [0, 8, 9, 10, 11], [0, 0, 0, 6, 6]])
    sel = np.array([[1, 1, 1, 0, 0], [1, 1, 1, 1, 0], [0, 0, 0, 0, 0], [1, 1, 1, 1, 0], [1, 1, 1, 1, 1]], bool)
    np.testing.assert_array_equal(satellite_counts(sat_id, sel), [2, 2, 0, 4, 4])


def test_four_pseudoranges_of_three_satellites_are_a_bridge():
    """Four pseudoranges of three satellites, one of them on two frequencies, fix no position: the epochs are
    bridged (flagged, counted, the motion model's) as three single-frequency satellites are."""
    import dataclasses

    from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
    from fusion.sim.simulate import SimConfig, simulate

    tr = simulate(n_epochs=80, nav=read_rinex_nav(default_nav_path()), seed=12,
                  config=SimConfig(doppler=False, carrier=False, dual_frequency=True)).trace
    mask = tr.mask.copy()
    for k in range(40, 50):                    # one satellite's two signals and two other satellites' one each
        ids, n = np.unique(tr.sat_id[k][tr.mask[k]], return_counts=True)
        assert (n == 2).any() and (n == 1).sum() >= 2
        mask[k] &= np.isin(tr.sat_id[k], np.r_[ids[n == 2][:1], ids[n == 1][:2]])
    tr = dataclasses.replace(tr, mask=mask)
    assert (tr.mask[40:50].sum(axis=1) == 4).all()
    res = _fused_nodnn(tr)
    assert res.info["epochs_bridged"] == 10 and res.info["bridged"][40:50].all()
    assert res.info["bridged_without_doppler"][40:50].all() and not res.info["bridged"][:40].any()


def _outage(tr: Trace) -> Trace:
    """The trace with 2 satellites at epochs 40-49."""
    import dataclasses

    mask = tr.mask.copy()
    mask[40:50] &= np.cumsum(mask[40:50], axis=1) <= 2
    return dataclasses.replace(tr, mask=mask)


@pytest.fixture(scope="module")
def doppler_outage():
    """A simulated trace with Doppler (no carrier) and the same outage."""
    from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
    from fusion.sim.simulate import SimConfig, simulate

    return _outage(simulate(n_epochs=80, nav=read_rinex_nav(default_nav_path()), seed=12,
                            config=SimConfig(doppler=True, carrier=False)).trace)


def _fused_nodnn(tr: Trace, **change):
    import dataclasses

    from fusion.estimate.graph.fuse import estimate_fused_nodnn

    opts = RunOptions()
    return estimate_fused_nodnn(tr, solve_wls(tr), dataclasses.replace(opts, graph=dataclasses.replace(
        opts.graph, **change)))


def test_bridged_sigmas_are_widened_where_nothing_measures_the_velocity(trace, doppler_outage):
    """GraphConfig.bridged_sigma_scale multiplies the calibrated sigmas of bridged epochs without Doppler, and
    of those alone; where Doppler measures the velocity through the outage they stay the graph's own."""
    from fusion.geometry import ecef2ned_cov

    tr = _outage(trace)
    one = _fused_nodnn(tr, bridged_sigma_scale=1.0, bridged_sigma_scale_down=1.0)
    wide = _fused_nodnn(tr, bridged_sigma_scale=1.5, bridged_sigma_scale_down=1.5)
    np.testing.assert_array_equal(one.pos, wide.pos)
    np.testing.assert_allclose(wide.cov[40:50], 2.25 * one.cov[40:50], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(wide.cov[:40], one.cov[:40])
    np.testing.assert_array_equal(wide.cov[50:], one.cov[50:])
    # each axis its own scale: north-east variances x 1.5^2, down x 2^2, the cross terms in between
    axes = _fused_nodnn(tr, bridged_sigma_scale=1.5, bridged_sigma_scale_down=2.0)
    ned_one, ned_axes = (ecef2ned_cov(r.cov[40:50], r.pos[40:50]) for r in (one, axes))
    d = np.array([1.5, 1.5, 2.0])
    np.testing.assert_allclose(ned_axes, ned_one * d[:, None] * d[None, :], rtol=1e-9, atol=1e-9)
    one, wide = (_fused_nodnn(doppler_outage, bridged_sigma_scale=s, bridged_sigma_scale_down=s) for s in (1.0, 1.5))
    assert one.info["bridged"][40:50].all() and not one.info["bridged_without_doppler"].any()
    np.testing.assert_array_equal(wide.cov, one.cov)


def test_a_tighter_velocity_walk_only_where_the_motion_model_alone_places_the_epoch(trace, doppler_outage):
    """GraphConfig.bridged_accel_scale changes the motion noise into epochs with fewer than 4 satellites, no
    prior and no Doppler, the same in GTSAM's graph and in the banded solver's copy; a trace whose outage has
    Doppler keeps its solution."""
    from fusion.estimate.graph.inputs import motion_only

    tr = _outage(trace)
    only = motion_only(prepare_inputs(tr, solve_wls(tr), GraphConfig()))
    assert only[40:50].all() and not only[:40].any() and not only[50:].any()
    tight, loose = _fused_nodnn(tr, bridged_accel_scale=0.5), _fused_nodnn(tr, bridged_accel_scale=1.0)
    gtsam_tight = _fused_nodnn(tr, bridged_accel_scale=0.5, batch_solver="gauss-newton")
    assert np.linalg.norm(tight.pos[40:50] - loose.pos[40:50], axis=1).max() > 1e-3
    np.testing.assert_allclose(tight.pos, gtsam_tight.pos, rtol=0, atol=5e-5)
    np.testing.assert_array_equal(_fused_nodnn(doppler_outage, bridged_accel_scale=0.5).pos,
                                  _fused_nodnn(doppler_outage, bridged_accel_scale=1.0).pos)


def test_pseudorange_losses_redescend_only_with_satellites_to_spare_and_nothing_learned():
    """Geman-McClure where the graph has no learned sigma and the epoch at least robust_min_sats
    satellites; learned_robust at those epochs of a graph with learned sigmas; robust / robust_k at the others."""
    from fusion.estimate.graph.inputs import pseudorange_losses
    n_sats = np.array([3, 5, 6, 9])
    (kind, k, at), (other, k_other, rest) = pseudorange_losses(GraphConfig(), False, n_sats)
    assert (kind, k, other, k_other) == ("gm", 2.0, "cauchy", 1.5)
    assert at.tolist() == [False, False, True, True] and rest.tolist() == [True, True, False, False]
    cfg = GraphConfig(learned_robust="huber", learned_robust_k=3.0, robust="none", robust_k=1.0)
    (kind, k, at), (other, k_other, rest) = pseudorange_losses(cfg, True, n_sats)
    assert (kind, k, other, k_other) == ("huber", 3.0, "none", 1.0)
    assert at.tolist() == [False, False, True, True] and rest.tolist() == [True, True, False, False]


def test_geman_mcclure_drops_a_gross_outlier_that_cauchy_still_feels(trace, wls):
    """One satellite 60 m off for the whole trace: the redescending loss gives it next to no weight, so the
    solution stays nearer the clean one than under Cauchy at the same scale."""
    pr = trace.pr.copy()
    pr[:, 0] = np.where(trace.mask[:, 0], pr[:, 0] + 60.0, pr[:, 0])
    bad = Trace(**{**trace.__dict__, "pr": pr})
    clean = fuse(trace, wls, RunOptions(), want_cov=False)
    runs = {kind: fuse(bad, wls, RunOptions(), cfg=GraphConfig(unlearned_robust=kind, unlearned_robust_k=2.0,
                                                                robust_min_sats=1), want_cov=False)
            for kind in ("gm", "cauchy")}
    shift = {kind: np.nanmedian(np.linalg.norm(r.pos - clean.pos, axis=1)) for kind, r in runs.items()}
    assert shift["gm"] < 0.5 * shift["cauchy"]
