"""Inference, the pipeline mode, calibration and checkpoint loading errors."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from fusion.errors import CheckpointError
from fusion.geometry import ned2ecef_vec, ned_rotation
from learned.checkpoint import load_model, read_checkpoint, save_checkpoint
from learned.features import FeatureConfig
from learned.infer import SHIPPED_WEIGHTS, Corrector, calibration
from learned.modes import estimate_dnn
from learned.model import DeepSets, SetTransformer
from learned.toy import toy_trace
from learned.train import TrainConfig


class ConstantNet(nn.Module):
    """Stub network: always predicts the NED correction (1, 2, 3) * out_scale with log-variance (0, ln 4, 0),
    and per satellite the log-scale ``log_k`` of the physical sigma model and bias 0."""

    def __init__(self, log_k: float = 0.0):
        super().__init__()
        self.log_k = log_k

    def forward(self, x, mask):
        B, S = x.shape[:2]
        sat = torch.zeros(B, S, 2)
        sat[..., 0] = self.log_k
        return (torch.tensor([1.0, 2.0, 3.0]).expand(B, 3), torch.tensor([0.0, np.log(4.0), 0.0]).expand(B, 3), sat)


def _config(kind="set", output="correction", **feat):
    return TrainConfig(model=kind, features=FeatureConfig(**feat), output=output).to_checkpoint_config()


def test_predict_applies_ned_correction_and_covariance_in_frame_of_guess():
    tr = toy_trace(30, seed=1)
    init = tr.truth + 5.0
    valid = np.ones(30, bool)
    valid[3] = False
    init[4] = np.nan
    c = Corrector(ConstantNet(), _config(out_scale=2.0)).predict(tr, init, valid)
    assert not c.valid[3] and not c.valid[4] and c.valid[[0, 5, 29]].all()
    assert np.isnan(c.mean_ecef[3]).all()
    ok = c.valid
    np.testing.assert_allclose(c.corr_ned[ok], np.broadcast_to([2.0, 4.0, 6.0], (ok.sum(), 3)), atol=1e-9)
    expect = init[ok] + ned2ecef_vec(np.array([2.0, 4.0, 6.0]), init[ok])
    np.testing.assert_allclose(c.mean_ecef[ok], expect, atol=1e-6)
    np.testing.assert_allclose(c.cov_ned[ok][0], np.diag([4.0, 16.0, 4.0]), atol=1e-9)
    R = ned_rotation(init[0])
    np.testing.assert_allclose(c.cov_ecef[0], R.T @ np.diag([4.0, 16.0, 4.0]) @ R, atol=1e-9)
    mean, cov, v = Corrector(ConstantNet(), _config(out_scale=2.0))(tr, init, valid)
    np.testing.assert_array_equal(v, c.valid)
    np.testing.assert_allclose(mean, c.mean_ecef)
    # no guard ranges in the config: full trust everywhere asked
    np.testing.assert_array_equal(c.trust[ok], 1.0)
    assert np.isnan(c.trust[~ok]).all()


def _noise_free(E=12, seed=1, n_sats=(6, 9)):
    """A toy trace whose pseudoranges are the exact (Sagnac) ranges plus a clock: WLS lands on the truth."""
    from fusion.geometry import line_of_sight
    tr = toy_trace(E, seed=seed, n_sats=n_sats)
    rng, _ = line_of_sight(tr.sat_pos, tr.truth)
    tr.pr = np.where(tr.mask, rng + 1234.5, 0.0)
    return tr


def test_wls_output_is_least_squares_with_the_heads_sigmas_and_slot_noise_matches():
    """Output "wls": the position of least squares weighted by the per-satellite head, iterated from the
    guess; on noise-free ranges it is the truth whatever the weights."""
    tr = _noise_free()
    init = tr.truth + np.array([6.0, -4.0, 3.0])
    valid = np.ones(tr.n_epochs, bool)
    corr = Corrector(ConstantNet(), _config(output="wls"))
    assert corr.output == "wls" and set(corr.var_scale) >= {"wls", "correction"}
    c = corr.predict(tr, init, valid)
    assert c.valid.all()
    np.testing.assert_allclose(c.mean_ecef, tr.truth, atol=1e-3)
    assert np.abs(c.corr_ned).max() > 3.0                   # it moved, and not by the correction head's (1,2,3)
    assert np.allclose(c.cov_ecef, np.swapaxes(c.cov_ecef, 1, 2)) and (np.linalg.eigvalsh(c.cov_ecef) > 0).all()
    # the per-slot sigma: positive on real slots, NaN on padding; the bias 0 (the stub's)
    assert (c.sigma[tr.mask] > 0).all() and np.isnan(c.sigma[~tr.mask]).all()
    np.testing.assert_array_equal(c.bias[tr.mask], 0.0)
    # the head scales the sigmas: 2x everywhere -> the same position, covariance x4
    c2 = Corrector(ConstantNet(np.log(2.0)), _config(output="wls")).predict(tr, init, valid)
    np.testing.assert_allclose(c2.sigma[tr.mask], 2.0 * c.sigma[tr.mask], rtol=1e-6)
    np.testing.assert_allclose(c2.mean_ecef, c.mean_ecef, atol=1e-6)
    np.testing.assert_allclose(c2.cov_ecef, 4.0 * c.cov_ecef, rtol=1e-6)
    # ... and a larger reported pseudorange sigma gives a larger learned sigma (the physical model under it)
    loud = _noise_free()
    loud.pr_sigma = loud.pr_sigma * 3.0
    c3 = corr.predict(loud, init, valid)
    assert (c3.sigma[tr.mask] > c.sigma[tr.mask]).all()
    sigma, bias = corr.slot_noise()(tr, init, valid)
    np.testing.assert_array_equal(sigma, c.sigma)
    np.testing.assert_array_equal(bias, c.bias)
    # the output argument overrides the checkpoint's; an unknown one is refused
    cc = corr.predict(tr, init, valid, output="correction")
    np.testing.assert_allclose(cc.corr_ned[0], [10.0, 20.0, 30.0])       # (1, 2, 3) * out_scale 10
    with pytest.raises(CheckpointError, match="unknown output 'direct'"):
        corr.predict(tr, init, valid, output="direct")


def test_checkpoints_without_output_default_to_the_correction_head():
    tr = toy_trace(8, seed=3)
    cfg = _config(output="wls")
    cfg.pop("output")
    c = Corrector(ConstantNet(), cfg)
    assert c.output == "correction"
    np.testing.assert_allclose(c.predict(tr, tr.truth, np.ones(8, bool)).corr_ned, np.tile([10.0, 20.0, 30.0], (8, 1)))


def test_epochs_with_too_few_satellites_not_solved_and_counted():
    tr = toy_trace(10, seed=2, n_sats=(6, 6))
    tr.mask[2, 3:] = False                      # 3 satellites left
    c = Corrector(ConstantNet(), _config()).predict(tr, tr.truth, np.ones(10, bool))
    assert not c.valid[2] and c.valid.sum() == 9 and c.n_too_few == 1


def test_calibration_of_gaussian_errors():
    rng = np.random.default_rng(0)
    sig = np.array([1.0, 2.0, 5.0])
    err = rng.normal(size=(20000, 3)) * sig
    cov = np.broadcast_to(np.diag(sig ** 2), (20000, 3, 3))
    cal = calibration(err, cov)
    np.testing.assert_allclose(cal["within_1sigma"], 0.683, atol=0.015)
    np.testing.assert_allclose(cal["within_2sigma"], 0.954, atol=0.01)
    half = calibration(err, cov / 4)            # overconfident sigma -> low coverage
    assert max(half["within_1sigma"]) < 0.45


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    from learned.data import build_samples, split_random
    from learned.toy import toy_dataset
    from learned.train import train
    torch.set_num_threads(1)
    s = build_samples(toy_dataset(2, 60, seed=3))
    tr, va = split_random(s, 0.2, np.random.default_rng(0))
    out = tmp_path_factory.mktemp("ck") / "m.pt"
    train(tr, va, TrainConfig(epochs=1), out, progress=False)
    return out


def test_estimate_dnn_from_wls_with_passes(tiny_ckpt):
    from fusion.run_types import RunOptions
    from fusion.estimate.wls import solve_wls
    tr = toy_trace(40, seed=9)
    wls = solve_wls(tr)
    wls.valid[5] = False
    r1 = estimate_dnn(tr, wls, RunOptions(weights=tiny_ckpt, dnn_passes=1))
    r2 = estimate_dnn(tr, wls, RunOptions(weights=tiny_ckpt, dnn_passes=2))
    assert not r1.valid[5] and np.isnan(r1.pos[5]).all() and r1.info["unsolved_wls"] >= 1
    assert r1.cov.shape == (40, 3, 3) and r2.info["passes"] == 2
    ok = r1.valid
    assert np.abs(r1.pos[ok] - r2.pos[ok]).max() > 1e-3   # second pass recomputed features
    # A 1-epoch network is not accurate, but its corrections are bounded (output scale x few).
    assert np.nanmax(np.linalg.norm(r1.pos[ok] - wls.pos[ok], axis=1)) < 100.0


def test_checkpoint_errors(tmp_path, tiny_ckpt):
    with pytest.raises(CheckpointError, match="not found"):
        Corrector.load(tmp_path / "missing.pt")
    txt = tmp_path / "notes.pt"
    txt.write_text("hello, not a checkpoint\n")
    with pytest.raises(CheckpointError, match=r"not a checkpoint .*starts with b'hell'"):
        read_checkpoint(txt)
    with pytest.raises(CheckpointError, match=r"not a checkpoint .*starts with b'hell'"):
        Corrector.load(txt)                       # named before torch is imported to read it
    with pytest.raises(CheckpointError, match="a folder, not a checkpoint file"):
        Corrector.load(tmp_path)
    with pytest.raises(CheckpointError, match="a folder, not a checkpoint file"):
        read_checkpoint(tmp_path)
    data = tiny_ckpt.read_bytes()
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="corrupt or truncated"):
        Corrector.load(trunc)
    tensor_only = tmp_path / "tensor.pt"
    torch.save({"weights": torch.zeros(3)}, tensor_only)
    with pytest.raises(CheckpointError, match="not a gnssfuse checkpoint"):
        read_checkpoint(tensor_only)
    evil = tmp_path / "evil.pt"
    torch.save({"format": "gnssfuse-checkpoint", "obj": TrainConfig()}, evil)   # arbitrary pickled object
    with pytest.raises(CheckpointError, match="refused to load"):
        read_checkpoint(evil)
    old = tmp_path / "old.pt"
    save_checkpoint(old, SetTransformer(), dict(_config(), features={**FeatureConfig().to_dict(), "version": 0}))
    with pytest.raises(CheckpointError, match="feature version 0"):
        Corrector.load(old)
    arch = tmp_path / "arch.pt"
    save_checkpoint(arch, DeepSets(), _config("set"))
    with pytest.raises(CheckpointError, match="architecture mismatch"):
        load_model(arch)
    hp = tmp_path / "hp.pt"
    save_checkpoint(hp, SetTransformer(), dict(_config(), model={"kind": "set", "hparams": {"d_model": 32}}))
    with pytest.raises(CheckpointError, match="architecture mismatch"):
        load_model(hp)


def test_checkpoints_that_do_not_fit_their_own_config_are_refused_at_load(tmp_path):
    """Each of these used to pass the load and fail later inside numpy or torch."""
    def bad(name: str, net: nn.Module, **config) -> Corrector:
        path = tmp_path / f"{name}.pt"
        save_checkpoint(path, net, dict(_config(), **config))
        return Corrector.load(path)

    wide = FeatureConfig(inputs=("res", "los", "pr_sigma"))
    with pytest.raises(CheckpointError, match=r"width\.pt: the network reads 4 channels per satellite but the "
                                              r"feature config \['res', 'los', 'pr_sigma'\] makes 6"):
        bad("width", SetTransformer(), features=wide.to_dict())
    with pytest.raises(CheckpointError, match=r"listfeat\.pt: checkpoint has no model/feature config"):
        bad("listfeat", SetTransformer(), features=["res", "los"])
    with pytest.raises(CheckpointError, match=r"ranges\.pt: input_ranges must hold 4 finite lo <= hi pairs"):
        bad("ranges", SetTransformer(), input_ranges={"lo": [0.0] * 3, "hi": [1.0] * 3})
    with pytest.raises(CheckpointError, match=r"ranges2\.pt: input_ranges must be"):
        bad("ranges2", SetTransformer(), input_ranges={"low": [0.0] * 4})
    with pytest.raises(CheckpointError, match=r"heads\.pt: model hyper-parameters do not fit this code: "
                                              r"ValueError"):
        bad("heads", SetTransformer(), model={"kind": "set", "hparams": {"d_model": 30, "n_heads": 4}})


def test_nan_in_padded_slots_changes_nothing(tmp_path):
    """The Trace contract checks only real slots; a padding slot holding NaN must give what zeros give
    (NaN times a zero mask is NaN, so every masked sum must keep it out)."""
    from dataclasses import replace

    from learned.features import CHANNELS

    features = FeatureConfig(inputs=tuple(CHANNELS))
    torch.manual_seed(2)
    path = tmp_path / "ctx.pt"
    hp = dict(d_model=16, n_heads=2, dim_feedforward=16, n_encoder=1, n_decoder=1, d_in=features.n_inputs)
    save_checkpoint(path, SetTransformer(**hp), dict(_config(output="wls", inputs=tuple(CHANNELS)),
                                                     model={"kind": "set", "hparams": hp}))
    tr = toy_trace(6, seed=3, n_sats=(6, 9))
    tr = replace(tr, cn0=np.where(tr.mask, 35.0, 0.0))
    assert (~tr.mask).any()
    pad = ~tr.mask
    nan_tr = replace(tr, sat_pos=np.where(pad[..., None], np.nan, tr.sat_pos), pr=np.where(pad, np.nan, tr.pr),
                     pr_sigma=np.where(pad, np.nan, tr.pr_sigma), cn0=np.where(pad, np.nan, tr.cn0))
    guess, valid = tr.truth + 5.0, np.ones(tr.n_epochs, bool)
    corr = Corrector.load(path)
    ref, got = corr.predict(tr, guess, valid), corr.predict(nan_tr, guess, valid)
    assert ref.valid.all() and np.isfinite(ref.mean_ecef).all()
    for name in ("mean_ecef", "cov_ecef", "sigma", "bias", "trust"):
        np.testing.assert_allclose(getattr(got, name), getattr(ref, name), rtol=1e-9, atol=1e-9, err_msg=name)


def test_shipped_weights_on_held_out_trace(shared_data):
    """The shipped network, from WLS, on the held-out real trace: runs, solves every usable epoch."""
    if not SHIPPED_WEIGHTS.is_file():
        pytest.skip("no shipped weights yet")
    from fusion.prepare.load import load_trace
    from fusion.run_types import RunOptions
    from fusion.estimate.wls import solve_wls
    tr = load_trace(shared_data / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel4")
    wls = solve_wls(tr)
    r = estimate_dnn(tr, wls, RunOptions())
    assert r.valid.sum() >= 0.98 * wls.valid.sum()
    step = np.linalg.norm(r.pos[r.valid] - wls.pos[r.valid], axis=1)
    assert np.median(step) < 30.0                # corrections are metre-level, not wild
    assert Corrector.load().config["features"]["version"] >= 1


def test_predict_rejects_bad_shapes_with_our_error():
    from fusion.errors import GeometryError

    tr = toy_trace(5, seed=3)
    with pytest.raises(GeometryError, match=r"init_pos must be \(5, 3\)"):
        Corrector(ConstantNet(), _config()).predict(tr, tr.truth[:4], np.ones(5, bool))


def test_shipped_weights_load_run_and_match_training_md(shipped_trace_dir):
    """The shipped ensemble loads without /work/shared; each member is a product (median-clock) model whose
    stored config is the recipe learned/weights/TRAINING.md states, seed, best epoch and data included; the
    ensemble carries its own unseen-drive calibration and corrects the shipped trace from WLS."""
    from fusion.prepare.load import load_trace
    from fusion.estimate.wls import solve_wls
    from learned.ensemble import Ensemble

    corr = Corrector.load()
    assert isinstance(corr, Ensemble) and len(corr.members) >= 2
    doc = (SHIPPED_WEIGHTS.parent / "TRAINING.md").read_text()
    command = " ".join(doc.replace("\\\n", " ").split())
    seeds = [m.config["seed"] for m in corr.members]
    assert len(set(seeds)) == len(seeds) and f"for SEED in {' '.join(map(str, seeds))};" in command
    for m in corr.members:
        _check_member_recipe(m, doc, command)
    cal = json.loads(SHIPPED_WEIGHTS.read_text())["calibration"]
    assert set(cal) == {"unseen_dnn", "unseen_fused"}
    for k, v in cal.items():
        assert f"{' / '.join(f'{x:.2f}' for x in v['scale_ned'])}" in command, k
    tr = load_trace(shipped_trace_dir).select(np.arange(60))
    wls = solve_wls(tr)
    c = corr.predict(tr, wls.pos, wls.valid)
    assert c.valid.sum() >= 0.9 * wls.valid.sum() and c.info["members"] == len(corr.members)
    assert np.median(np.linalg.norm(c.corr_ned[c.valid], axis=1)) < 30.0


def _check_member_recipe(corr: Corrector, doc: str, command: str) -> None:
    from learned.model import count_parameters
    from learned.train_command import default_inputs

    cfg = corr.config
    assert corr.features.clock == "median" and corr.signals[0] == "GPS_L1"
    if corr.signals != ("GPS_L1",):                       # trained on more signals: the recipe names them
        assert f" SIGNALS={','.join(corr.signals)} " in command and " --signals $SIGNALS " in command
    model, blob = load_model(corr.path)
    assert f"{count_parameters(model):,} parameters" in doc
    mix = ",".join(f"{k}={v:g}" for k, v in cfg["guess_mix"].items())
    for flag in (f"--epochs {cfg['epochs']}", f"--eta {cfg['eta']:g}", f"--guess-mix {mix}",
                 f"--wls-jitter {cfg['wls_jitter']:g}", f"--val-split {cfg['data']['val_split']}", "--seed $SEED"):
        assert f" {flag} " in command, flag
    if "sim" in cfg["data"]:            # simulated traces in the data: their count and length too
        for flag in (f"--sim-traces {cfg['data']['sim']['traces']}",
                     f"--sim-epochs {cfg['data']['sim']['epochs_per_trace']}"):
            assert f" {flag} " in command, flag
    # the new options appear when they differ from the CLI defaults
    if ",".join(cfg["features"]["inputs"]) != default_inputs(corr.features.version):
        assert f" --inputs {','.join(cfg['features']['inputs'])} " in command
    if cfg["output"] != "wls":
        assert f" --output {cfg['output']} " in command
    assert corr.features.inputs == tuple(cfg["features"]["inputs"]) and cfg["input_ranges"] is not None
    assert set(cfg["calibration"]) >= {"wls", "correction"}
    assert f"seed {cfg['seed']}: best validation epoch **{blob['epoch']} of {cfg['epochs']}**" in command
    assert f"{cfg['data']['n_train']:,} train / {cfg['data']['n_val']:,} validation" in command


def test_shipped_weights_beat_their_baselines_on_the_held_out_shipped_trace(shipped_trace_dir):
    """The issue's held-out target, kept as a regression check of the shipped weights: on the shipped
    trace (never trained or tuned on) dnn beats wls and fused beats fused-nodnn in GSDC score."""
    from fusion.eval.metrics import mode_metrics
    from fusion.prepare.load import load_trace
    from fusion.modes import run_modes

    tr = load_trace(shipped_trace_dir)
    res = run_modes(tr, ["wls", "dnn", "fused-nodnn", "fused"])
    score = {m: mode_metrics(tr, r)["gsdc_score"] for m, r in res.items()}
    assert score["dnn"] < score["wls"] and score["fused"] < score["fused-nodnn"], score



def _with_copies_as(tr, signal: str):
    """The trace with every slot repeated as ``signal`` (same satellite and pseudorange): a
    multi-constellation trace whose extra satellites agree with the GPS ones. Shapes (E, 2S, ...)."""
    from dataclasses import replace
    from fusion.trace import SIGNALS

    two = lambda a: np.concatenate([a, a], axis=1)  # noqa: E731
    sig = np.concatenate([tr.signal, np.full_like(tr.signal, SIGNALS.index(signal))], axis=1)
    return replace(tr, sat_pos=two(tr.sat_pos), sat_vel=two(tr.sat_vel), pr=two(tr.pr),
                   pr_sigma=two(tr.pr_sigma), sat_id=np.concatenate([tr.sat_id, tr.sat_id + 5000], axis=1),
                   signal=sig, mask=two(tr.mask))


def test_other_constellations_lower_the_trust_of_a_version_2_network():
    """A GPS-L1 (feature version 2) network on a multi-constellation trace: the satellites it cannot read
    count against its trust (here half of every epoch's: none left), so that a GPS-only correction does
    not override a guess from every constellation."""
    from fusion.estimate.wls import solve_wls

    corr = Corrector(ConstantNet(), _config(version=2))
    gps = toy_trace(20, seed=4)
    multi = _with_copies_as(gps, "GAL_E1")
    w = solve_wls(gps)
    t_gps = corr.predict(gps, w.pos, w.valid).trust
    c_multi = corr.predict(multi, w.pos, w.valid)
    ok = np.isfinite(t_gps)
    assert ok.mean() > 0.9 and np.median(t_gps[ok]) == 1.0
    np.testing.assert_array_equal(c_multi.trust[ok], 0.0)
    np.testing.assert_allclose(c_multi.corr_ned[ok], 0.0, atol=1e-9)
    assert c_multi.info["meas_unseen_signal"] == multi.mask[ok].sum() // 2


def test_the_shipped_network_reads_other_constellations(shipped_trace_dir):
    """The shipped (feature version 3) network reads every signal: on the shipped GPS trace with each
    slot repeated as Galileo E1 (agreeing measurements), no satellite is unseen, the trust stays and the
    correction stays close to the GPS-only one (the copies add no information)."""
    from fusion.estimate.wls import solve_wls
    from fusion.prepare.load import load_trace

    corr = Corrector.load()
    gps = load_trace(shipped_trace_dir).select(np.arange(200))
    w = solve_wls(gps)
    c_gps = corr.predict(gps, w.pos, w.valid)
    c_multi = corr.predict(_with_copies_as(gps, "GAL_E1"), w.pos, w.valid)
    ok = np.isfinite(c_gps.trust) & np.isfinite(c_multi.trust)
    assert corr.features.version == 3 and ok.mean() > 0.9
    assert c_multi.info["meas_unseen_signal"] == 0 and np.median(c_multi.trust[ok]) > 0.5
    step = np.linalg.norm(c_multi.corr_ned[ok] - c_gps.corr_ned[ok], axis=1)
    assert np.median(step) < 3.0


def test_chunks_of_like_satellite_counts_give_what_one_chunk_gives(monkeypatch):
    """learned.infer.chunks_by_size: epochs sorted by their satellite count into chunks, each padded to its own
    largest set, and put back in their order; a chunk of 7 epochs over a toy trace of 5-11 satellites gives what
    one chunk of all gives (float32 sums over fewer padded slots: to 1e-5)."""
    import learned.infer as infer
    tr = toy_trace(40, seed=4, n_sats=(5, 11))
    assert len(np.unique(tr.mask.sum(1))) > 3
    corr = Corrector.load(SHIPPED_WEIGHTS)
    guess, valid = tr.truth + 4.0, np.ones(tr.n_epochs, bool)
    monkeypatch.setattr(infer, "INFER_CHUNK", 4096)
    whole = corr.predict(tr, guess, valid)
    monkeypatch.setattr(infer, "INFER_CHUNK", 7)
    chunked = corr.predict(tr, guess, valid)
    for name in ("mean_ecef", "cov_ecef", "sigma", "bias"):
        np.testing.assert_allclose(getattr(chunked, name), getattr(whole, name), rtol=1e-4, atol=1e-5, err_msg=name)
    rows = list(infer.chunks_by_size(tr.mask.sum(1)))
    assert sorted(np.concatenate(rows).tolist()) == list(range(tr.n_epochs)) and max(map(len, rows)) == 7
    assert (np.diff(tr.mask.sum(1)[np.concatenate(rows)]) >= 0).all()          # sorted by count
