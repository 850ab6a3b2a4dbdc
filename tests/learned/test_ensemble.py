"""Several networks asked as one (learned/ensemble.py): the combination, the manifest and its errors."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from fusion.errors import CheckpointError
from fusion.geometry import ned2ecef_vec
from learned.checkpoint import save_checkpoint
from learned.ensemble import Ensemble, read_manifest, store_ensemble_calibration, write_manifest
from learned.features import FeatureConfig
from learned.infer import Corrector
from learned.model import build_model
from learned.toy import toy_trace
from learned.train import TrainConfig


class ShiftNet(nn.Module):
    """Stub: NED correction ``shift`` (3,) with unit variance; per satellite log-multiplier ``log_k``, bias ``b``."""

    def __init__(self, shift, log_k: float = 0.0, b: float = 0.0):
        super().__init__()
        self.shift, self.log_k, self.b = torch.tensor(shift, dtype=torch.float32), log_k, b

    def forward(self, x, mask):
        B, S = x.shape[:2]
        sat = torch.zeros(B, S, 2)
        sat[..., 0], sat[..., 1] = self.log_k, self.b
        return self.shift.expand(B, 3), torch.zeros(B, 3), sat


def _config(**kw):
    base = TrainConfig(model="set", features=FeatureConfig(out_scale=1.0), output="correction")
    return base.to_checkpoint_config() | kw


def _trace():
    tr = toy_trace(20, seed=3)
    return tr, tr.truth + 4.0, np.ones(20, bool)


def test_ensemble_averages_corrections_and_adds_their_spread_to_the_covariance():
    tr, init, valid = _trace()
    a = Corrector(ShiftNet([1.0, 0.0, 2.0], log_k=0.2, b=0.05), _config())
    b = Corrector(ShiftNet([3.0, 0.0, 2.0], log_k=-0.4, b=-0.15), _config())
    c = Ensemble([a, b]).predict(tr, init, valid)
    ca, cb = a.predict(tr, init, valid), b.predict(tr, init, valid)
    ok = c.valid
    assert ok.all()
    np.testing.assert_allclose(c.corr_ned, np.broadcast_to([2.0, 0.0, 2.0], (20, 3)), atol=1e-6)
    np.testing.assert_allclose(c.mean_ecef, init + ned2ecef_vec(np.array([2.0, 0.0, 2.0]), init), atol=1e-5)
    # each member's variance is 1 per axis; the members disagree by +-1 m north only
    np.testing.assert_allclose(c.cov_ned[0], np.diag([2.0, 1.0, 1.0]), atol=1e-6)
    np.testing.assert_allclose(c.cov_ecef[0], c.cov_ecef[0].T, atol=1e-9)
    np.testing.assert_allclose(np.linalg.eigvalsh(c.cov_ecef[0]), [1.0, 1.0, 2.0], atol=1e-6)
    seen = np.isfinite(ca.sigma)
    assert seen.any()
    np.testing.assert_allclose(c.sigma[seen], np.sqrt(ca.sigma[seen] * cb.sigma[seen]), rtol=1e-6)
    assert not np.allclose(ca.bias[seen], cb.bias[seen])
    np.testing.assert_allclose(c.bias[seen], (ca.bias[seen] + cb.bias[seen]) / 2, atol=1e-6)
    np.testing.assert_array_equal(c.base[seen], ca.base[seen])
    assert c.info["members"] == 2 and c.info["epochs_asked"] == 20


def test_one_network_twice_is_that_network():
    tr, init, valid = _trace()
    a = Corrector(ShiftNet([1.0, -2.0, 0.5], log_k=0.3, b=0.7), _config())
    c, one = Ensemble([a, a]).predict(tr, init, valid), a.predict(tr, init, valid)
    for k in ("mean_ecef", "cov_ecef", "corr_ned", "cov_ned", "sigma", "bias", "trust"):
        np.testing.assert_allclose(getattr(c, k), getattr(one, k), atol=1e-9, err_msg=k)
    g = Ensemble([a, a]).graph_inputs(tr, init, valid, sigma_power=4.0)
    g1 = a.graph_inputs(tr, init, valid, sigma_power=4.0)
    np.testing.assert_allclose(g.pr_sigma, g1.pr_sigma, rtol=1e-9)
    np.testing.assert_array_equal(g.prior_ok, g1.prior_ok)


def test_epoch_is_valid_and_trusted_only_where_every_member_is():
    tr, init, valid = _trace()
    tight = _config(input_ranges={"lo": [-1e-6] * 4, "hi": [1e-6] * 4})   # every residual out of range
    free, guarded = Corrector(ShiftNet([1.0, 0.0, 0.0]), _config()), Corrector(ShiftNet([1.0, 0.0, 0.0]), tight)
    c = Ensemble([free, guarded]).predict(tr, init, valid)
    g = guarded.predict(tr, init, valid)
    np.testing.assert_array_equal(c.trust, np.minimum(g.trust, 1.0))
    assert c.info["meas_out_of_range"] == g.info["meas_out_of_range"] > 0


def test_ensemble_scale_replaces_the_members_unseen_scales():
    tr, init, valid = _trace()
    own = {"unseen_dnn": {"scale_ned": [5.0, 5.0, 5.0]}, "unseen_fused": {"scale_ned": [7.0, 7.0, 7.0]}}
    a = Corrector(ShiftNet([1.0, 0.0, 0.0]), _config(calibration=own))
    ens = Ensemble([a], {"unseen_dnn": {"scale_ned": [2.0, 1.0, 3.0]}, "unseen_fused": {"scale_ned": [1.5, 1.5, 1.5]}})
    c = ens.predict(tr, init, valid)
    np.testing.assert_allclose(c.cov_ned[0], np.diag([4.0, 1.0, 9.0]), atol=1e-6)
    np.testing.assert_allclose(ens.var_scale["unseen_fused"], 2.25)
    # another output than the one the scale was fitted on keeps its own covariance
    np.testing.assert_allclose(ens.predict(tr, init, valid, output="wls").cov_ned,
                               a.predict(tr, init, valid, output="wls").cov_ned)
    with pytest.raises(CheckpointError, match="scale_ned"):
        Ensemble([a], {"unseen_dnn": {"scale_ned": [1.0, -1.0]}})


def _tiny(path, seed: int, **cfg):
    torch.manual_seed(seed)
    hp = dict(d_model=16, n_heads=2, dim_feedforward=16, n_encoder=1, n_decoder=1)
    config = {"model": {"kind": "set", "hparams": hp}, "features": FeatureConfig().to_dict(), **cfg}
    return save_checkpoint(path, build_model("set", **hp), config)


def test_manifest_round_trip_and_corrector_load(tmp_path):
    members = [_tiny(tmp_path / "w" / f"m{i}.pt", i) for i in range(2)]
    m = write_manifest(tmp_path / "w" / "ens.json", members, {"unseen_dnn": {"scale_ned": [1.0, 2.0, 1.0]}})
    assert json.loads(m.read_text())["members"] == ["m0.pt", "m1.pt"]
    store_ensemble_calibration(m, {"unseen_fused": {"scale_ned": [3.0, 3.0, 3.0]}})
    paths, cal = read_manifest(m)
    assert paths == members and set(cal) == {"unseen_dnn", "unseen_fused"}
    (tmp_path / "w").rename(tmp_path / "moved")            # relative members: the folder moves whole
    ens = Corrector.load(tmp_path / "moved" / "ens.json")
    assert isinstance(ens, Ensemble) and len(ens.members) == 2
    np.testing.assert_allclose(ens.var_scale["unseen_dnn"], [1.0, 4.0, 1.0])
    tr, init, valid = _trace()
    one = [Corrector.load(tmp_path / "moved" / m).predict(tr, init, valid) for m in ("m0.pt", "m1.pt")]
    c = ens.predict(tr, init, valid)
    np.testing.assert_allclose(c.corr_ned, np.mean([o.corr_ned for o in one], axis=0), atol=1e-6)


@pytest.mark.parametrize("text, msg", [
    ("not json", "not a readable JSON"),
    ('{"members": ["a.pt"]}', "missing format tag"),
    ('{"format": "gnssfuse-ensemble", "members": []}', "non-empty list"),
    ('{"format": "gnssfuse-ensemble", "members": ["gone.pt"]}', "gone.pt: checkpoint not found"),
])
def test_bad_manifest_is_one_line_naming_the_file(tmp_path, text, msg):
    p = tmp_path / "ens.json"
    p.write_text(text)
    with pytest.raises(CheckpointError, match=msg) as exc:
        Corrector.load(p)
    text = str(exc.value)
    assert "\n" not in text and ("ens.json" in text or "gone.pt" in text)


def test_members_of_different_recipes_are_refused(tmp_path):
    a = _tiny(tmp_path / "a.pt", 0)
    b = _tiny(tmp_path / "b.pt", 1, output="wls")
    m = write_manifest(tmp_path / "e.json", [a, b])
    with pytest.raises(CheckpointError, match="share one recipe"):
        Corrector.load(m)
    with pytest.raises(CheckpointError, match="missing"):
        write_manifest(tmp_path / "f.json", [a, tmp_path / "nope.pt"])


def test_manifest_command(tmp_path, capsys):
    from learned.ensemble import main
    a, b = _tiny(tmp_path / "a.pt", 0), _tiny(tmp_path / "b.pt", 1)
    assert main([str(a), str(b), "--out", str(tmp_path / "e.json")]) == 0
    assert read_manifest(tmp_path / "e.json")[0] == [a, b]
    assert main([str(a), "--out", str(tmp_path / "e.pt")]) == 2
    assert main([str(a), str(_tiny(tmp_path / "c.pt", 2, output="wls")), "--out", str(tmp_path / "f.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "ends in .json" in err[0] and "share one recipe" in err[1]
    assert not (tmp_path / "f.json").exists()
    assert main([str(a), "--few", str(b), "--few-below", "5", "--out", str(tmp_path / "g.json")]) == 0
    from learned.ensemble import read_few_satellites
    assert read_few_satellites(tmp_path / "g.json") == (5, [b])
    assert main([str(a), "--few", str(b), "--few-below", "4", "--out", str(tmp_path / "h.json")]) == 2
    assert "--few-below 4" in capsys.readouterr().err and not (tmp_path / "h.json").exists()


def test_guard_counts_are_every_members_reasons_at_their_most():
    tr, init, valid = _trace()
    ranges = {"lo": [-1e-6] * 4, "hi": [1e-6] * 4}
    own = {"unseen_dnn": {"scale_ned": [3.0, 3.0, 3.0]}}
    a = Corrector(ShiftNet([1.0, 0.0, 0.0]), _config(calibration=own))
    b = Corrector(ShiftNet([1.0, 0.0, 0.0]), _config(input_ranges=ranges))
    got = Ensemble([a, b]).predict(tr, init, valid).info
    ia, ib = a.predict(tr, init, valid).info, b.predict(tr, init, valid).info
    assert set(got) == set(ia) | set(ib) | {"members"}
    assert all(got[k] == max(ia.get(k, 0), ib.get(k, 0)) for k in set(ia) | set(ib))
    np.testing.assert_allclose(a.var_scale["unseen_dnn"], 9.0)       # the member given keeps its own scale


def test_few_satellite_members_answer_where_satellites_are_few_and_travel_with_the_manifest(tmp_path):
    from fusion.trace import satellite_counts
    from learned.ensemble import read_few_satellites
    main = [_tiny(tmp_path / "w" / f"m{i}.pt", i) for i in range(2)]
    few = [_tiny(tmp_path / "w" / f"f{i}.pt", 10 + i) for i in range(2)]
    m = write_manifest(tmp_path / "w" / "ens.json", main, few=(7, few))
    store_ensemble_calibration(m, {"unseen_fused": {"scale_ned": [2.0, 2.0, 2.0]}})    # keeps the entry
    assert read_few_satellites(m) == (7, few)
    tr, init, valid = _trace()
    tr.mask[::3, 4:] = False                              # every third epoch: four satellites
    ens = Corrector.load(m)
    c = ens.predict(tr, init, valid)
    plain = Ensemble([Corrector.load(p) for p in main]).predict(tr, init, valid)
    alone = Ensemble([Corrector.load(p) for p in few]).predict(tr, init, valid)
    rows = c.valid & (satellite_counts(tr.sat_id, np.isfinite(plain.base)) < 7)
    assert rows.any() and (~rows & c.valid).any() and c.info["few_satellite_epochs"] == rows.sum()
    for k in ("corr_ned", "cov_ned", "sigma", "bias"):
        np.testing.assert_allclose(getattr(c, k)[rows], getattr(alone, k)[rows], atol=1e-4, err_msg=k)
        np.testing.assert_allclose(getattr(c, k)[~rows], getattr(plain, k)[~rows], atol=1e-4, err_msg=k)
    assert not np.allclose(plain.corr_ned[rows], alone.corr_ned[rows])
    (tmp_path / "w" / "bad.json").write_text(json.dumps({"format": "gnssfuse-ensemble", "members": ["m0.pt"],
                                                          "few_satellites": {"below": 3, "members": ["f0.pt"]}}))
    with pytest.raises(CheckpointError, match="bad.json.*few_satellites"):
        Corrector.load(tmp_path / "w" / "bad.json")
