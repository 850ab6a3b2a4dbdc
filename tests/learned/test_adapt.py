"""``gnssfuse adapt``: fine-tuning without ground truth (learned/adapt.py, fusion/cli/adapt.py)."""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch

import fusion.io.gsdc
import fusion.prepare.raw_load
import fusion.io.truth
from fusion.cli import main as cli
from fusion.errors import GnssfuseError
from fusion.prepare.load import load_trace
from learned.adapt import AdaptConfig, adapt
from learned.guard import widened_ranges
from learned.checkpoint import read_checkpoint
from learned.data import Samples
from learned.ensemble import read_manifest
from learned.infer import SHIPPED_WEIGHTS, Corrector
from learned.selfcheck import decide, holdout_mask, split

#: One network of the shipped ensemble: most tests adapt one, the ensemble's own are at the end.
ONE = read_manifest(SHIPPED_WEIGHTS)[0][0]
#: A few hundred epochs of the shipped trace keep every adaptation here to seconds.
FEW = 150


def _copy_trace(src, root):
    """The shipped trace copied to ``root/<collection>/<phone>`` (its name stays the same)."""
    dst = root / src.parent.name / src.name
    shutil.copytree(src, dst)
    return dst


def _differing(a, b) -> set[str]:
    """Names of the tensors that differ between two checkpoints' weights."""
    sa, sb = read_checkpoint(a)["model_state"], read_checkpoint(b)["model_state"]
    assert sa.keys() == sb.keys()
    return {k for k in sa if sa[k].dtype != sb[k].dtype or not torch.equal(sa[k], sb[k])}


def _same_checkpoint(a, b) -> bool:
    """Same weights and the same config, the adaptation's wall-clock times aside."""
    ca, cb = read_checkpoint(a), read_checkpoint(b)
    for c in (ca, cb):
        for rec in c["config"]["adapted"]:
            rec.pop("teacher_s"), rec.pop("train_s")
            rec.get("graph_check", {}).pop("seconds", None)
            for t in rec["traces"].values():
                t.pop("teacher_s")
        for h in c["history"]:
            h.pop("time_s")
    same_w = all(torch.equal(ca["model_state"][k], cb["model_state"][k]) for k in ca["model_state"])
    return same_w and ca["config"] == cb["config"] and ca["history"] == cb["history"]


def test_never_reads_ground_truth(shipped_trace_dir, tmp_path, monkeypatch):
    with_tripwire = _copy_trace(shipped_trace_dir, tmp_path / "a")
    without = _copy_trace(shipped_trace_dir, tmp_path / "b")
    # a truth file that fails any reader that opens it, and that the loaders would otherwise pick up
    (with_tripwire / "ground_truth.csv").write_bytes(b"\x00\xff\x13garbage" * 100)
    (without / "ground_truth.csv").unlink()
    with pytest.raises(GnssfuseError):
        load_trace(with_tripwire)
    # and every truth reader raises if called at all
    def boom(*a, **k):
        raise AssertionError("a ground-truth reader was called")
    for mod in (fusion.io.truth, fusion.io.gsdc, fusion.prepare.raw_load):
        for name in ("read_truth_csv", "interp_gapped", "match_nearest", "check_overlap"):
            if hasattr(mod, name):
                monkeypatch.setattr(mod, name, boom)
    cfg = AdaptConfig(epochs=1, max_epochs=FEW, margin=-1.0)      # accepted: the graph check runs too
    rec = adapt([with_tripwire], tmp_path / "a.pt", weights=ONE, cfg=cfg)
    adapt([without], tmp_path / "b.pt", weights=ONE, cfg=cfg)
    assert _same_checkpoint(tmp_path / "a.pt", tmp_path / "b.pt")
    assert list(rec["traces"]) == ["2021-04-28-US-MTV-1/Pixel4"] and rec["samples"] > 0
    assert rec["graph_check"]["measurements"] > 0


def test_seeded_and_reproducible(shipped_trace_dir, tmp_path):
    runs = {}
    for tag, seed in (("a", 3), ("b", 3), ("c", 4)):      # margin -1: keep the epoch whatever the self-check says
        adapt([shipped_trace_dir], tmp_path / f"{tag}.pt", weights=ONE,
              cfg=AdaptConfig(epochs=1, max_epochs=FEW, seed=seed, margin=-1.0, graph_margin=-1.0, part="all",
                              agree=1.0))
        runs[tag] = tmp_path / f"{tag}.pt"
    assert _same_checkpoint(runs["a"], runs["b"])
    assert not _same_checkpoint(runs["a"], runs["c"])


def test_cli_end_to_end_and_run_uses_the_result(shipped_trace_dir, tmp_path, capsys):
    out = tmp_path / "w.pt"
    # --margin -1: accepted whatever the self-check says, so that the weights do move (the decline is
    # tested on its own)
    assert cli(["adapt", "--weights", str(ONE), str(shipped_trace_dir), "--max-epochs", "300", "--epochs", "1",
                "--out", str(out), "--threads", "1", "--margin", "-1", "--graph-margin", "-1"]) == 0
    said = capsys.readouterr().out
    assert "without ground truth" in said and "2021-04-28-US-MTV-1/Pixel4" in said
    base, new = read_checkpoint(ONE), read_checkpoint(out)
    rec = new["config"]["adapted"][-1]
    assert rec["teacher"] == "fused" and rec["loo"] == 1.0 and rec["epochs"] == 1 and rec["from"] == ONE.name
    assert rec["part"] == "sat" and rec["agree"] == 0.0 and rec["decision"] == "accepted"
    # the first line says what became of it; by default the per-satellite head moves, and nothing else
    assert said.splitlines()[0].startswith("adapted") and "graph check: held-out satellites' error" in said
    assert _differing(ONE, out) == {"sat_head.weight", "sat_head.bias"}
    c = rec["traces"]["2021-04-28-US-MTV-1/Pixel4"]
    assert c["epochs"] == 300 and 0 < c["teacher_trusted"] <= c["teacher_solved"] <= 300
    assert not c["doppler"] and not c["carrier"]          # GSDC 2021 derived files carry neither
    assert "truth" not in repr(new["config"]["adapted"]).lower()
    assert new["config"]["calibration"] == base["config"]["calibration"]
    lo_b, hi_b = base["config"]["input_ranges"]["lo"], base["config"]["input_ranges"]["hi"]
    lo_n, hi_n = new["config"]["input_ranges"]["lo"], new["config"]["input_ranges"]["hi"]
    assert all(n <= b for n, b in zip(lo_n, lo_b)) and all(n >= b for n, b in zip(hi_n, hi_b))
    Corrector.load(out)
    assert cli(["run", str(shipped_trace_dir), "--mode", "fused", "--weights", str(out),
                "--out", str(tmp_path / "run")]) == 0
    assert (tmp_path / "run" / "estimates.csv").is_file()


def test_adapting_an_adapted_checkpoint_keeps_both_records(shipped_trace_dir, tmp_path):
    cfg = AdaptConfig(epochs=1, max_epochs=FEW)
    adapt([shipped_trace_dir], tmp_path / "one.pt", weights=ONE, cfg=cfg)
    adapt([shipped_trace_dir], tmp_path / "two.pt", weights=tmp_path / "one.pt",
          cfg=AdaptConfig(epochs=1, max_epochs=FEW, teacher="fused-nodnn", loo=0.0, agree=1.0, part="all"))
    recs = read_checkpoint(tmp_path / "two.pt")["config"]["adapted"]
    assert [(r["from"], r["teacher"], r["loo"]) for r in recs] == [(ONE.name, "fused", 1.0),
                                                                   ("one.pt", "fused-nodnn", 0.0)]
    with pytest.raises(GnssfuseError, match="teacher must be one of"):
        adapt([shipped_trace_dir], tmp_path / "x.pt", weights=ONE, cfg=AdaptConfig(teacher="wls"))


def test_widened_ranges():
    assert widened_ranges({"lo": [0, 1], "hi": [2, 3]}, {"lo": [-1, 2], "hi": [1, 5]}) == {"lo": [-1, 1],
                                                                                           "hi": [2, 5]}
    assert widened_ranges(None, {"lo": [0], "hi": [1]}) == {"lo": [0], "hi": [1]}


@pytest.mark.parametrize("extra, words", [
    (["--epochs", "0"], "--epochs >= 1"),
    (["--lr", "-1"], "--lr > 0"),
    (["--max-teacher-sigma", "0"], "--max-teacher-sigma > 0"),
    (["--max-epochs", "0"], "--max-epochs >= 1"),
    (["--loo", "-1"], "--loo >= 0"),
    (["--loo", "0"], "not both 0"),
    (["--margin", "1"], "-1 <= --margin < 1"),
    (["--graph-margin", "-2"], "-1 <= --graph-margin < 1"),
    (["--every", "1"], "--every >= 2"),
    (["--anchor", "-1"], "--anchor >= 0"),
    (["--min-teacher-sigma", "-1"], "--min-teacher-sigma >= 0"),
    (["--max-carrier-share", "1.5"], "0 <= --max-carrier-share <= 1"),
    (["--clk", "x.clk"], "--clk needs --sp3"),
    (["--max-epochs", "20", "--max-teacher-sigma", "1e-6"], "no epoch of 2021-04-28-US-MTV-1/Pixel4 has a teacher"),
    (["--max-epochs", "20", "--max-teacher-sigma", "1e-6"], "hold only 20 epochs in all, fewer than a held-out block"),
])
def test_bad_arguments_are_one_line_errors(shipped_trace_dir, tmp_path, capsys, extra, words):
    assert cli(["adapt", "--weights", str(ONE), str(shipped_trace_dir), "--out", str(tmp_path / "w.pt"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("gnssfuse adapt: error:") and words in err and "\n" not in err
    assert not (tmp_path / "w.pt").exists()


def test_bad_paths_are_one_line_errors(shipped_trace_dir, tmp_path, capsys):
    bad_ckpt = tmp_path / "bad.pt"
    bad_ckpt.write_text("not a checkpoint")
    cases = [([str(tmp_path / "nope"), "--out", str(tmp_path / "w.pt")], "does not exist"),
             ([str(shipped_trace_dir), "--out", str(tmp_path)], "is a folder"),
             ([str(shipped_trace_dir), "--out", str(tmp_path / "w.pt"), "--weights", str(bad_ckpt)],
              "bad.pt")]
    for argv, words in cases:
        assert cli(["adapt", "--weights", str(ONE), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err


def _epoch(n_sats=8, seed=0):
    """One epoch of consistent pseudoranges (B=1): satellites 20,000 km away in the upper half-sky."""
    from learned.features import line_of_sight_torch
    rng = np.random.default_rng(seed)
    rx = torch.tensor([[6378137.0, 0.0, 0.0]], dtype=torch.float64)
    d = rng.normal(size=(n_sats, 3))
    d[:, 0] = np.abs(d[:, 0]) + 0.3                       # above the receiver's horizon
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sat = rx[0] + 2.0e7 * torch.tensor(d)
    r, _ = line_of_sight_torch(sat[None], rx)
    return sat[None], r + 1234.5, torch.ones(1, n_sats, dtype=torch.bool), rx


def test_leave_one_out_loss_wants_a_large_sigma_for_the_satellite_the_others_refute():
    from learned.consistency import loo_nll
    sat, pr, mask, rx = _epoch()
    pr[0, 0] += 50.0                                       # one satellite 50 m off, the rest consistent
    sigma = torch.full(pr.shape, 3.0, dtype=torch.float64, requires_grad=True)
    loss = loo_nll(sat, pr, mask, rx + 5.0, sigma, torch.zeros_like(pr))
    loss.backward()
    assert sigma.grad[0, 0] < 0 and sigma.grad[0, 0] < sigma.grad[0, 1:].min()   # the outlier's sigma grows most
    # a consistent epoch: every sigma larger than the (zero) noise shrinks
    sat, pr, mask, rx = _epoch(seed=1)
    sigma = torch.full(pr.shape, 3.0, dtype=torch.float64, requires_grad=True)
    loo_nll(sat, pr, mask, rx + 5.0, sigma, torch.zeros_like(pr)).backward()
    assert (sigma.grad > 0).all()
    # epochs with fewer than five satellites carry no term (the others cannot fix a position)
    sat4, pr4, mask4, rx4 = _epoch(4)
    assert float(loo_nll(sat4, pr4, mask4, rx4, torch.ones_like(pr4), torch.zeros_like(pr4))) == 0.0


def test_teachers_in_worker_processes_match_in_process(shipped_trace_dir, tmp_path):
    two = [_copy_trace(shipped_trace_dir, tmp_path / "a"), _copy_trace(shipped_trace_dir, tmp_path / "b")]
    cfg = AdaptConfig(epochs=1, max_epochs=FEW)
    rec = adapt(two, tmp_path / "j1.pt", weights=ONE, cfg=cfg, jobs=1)
    adapt(two, tmp_path / "j2.pt", weights=ONE, cfg=cfg, jobs=2)
    # two logs of the same name are both recorded
    assert list(rec["traces"]) == ["2021-04-28-US-MTV-1/Pixel4", "2021-04-28-US-MTV-1/Pixel4 #2"]
    assert sum(c["samples"] for c in rec["traces"].values()) == rec["samples"]
    assert _same_checkpoint(tmp_path / "j1.pt", tmp_path / "j2.pt")


def test_a_log_too_short_to_hold_a_block_out_is_declined_saying_so(shipped_trace_dir, tmp_path, capsys):
    assert cli(["adapt", "--weights", str(ONE), str(shipped_trace_dir), "--max-epochs", "40", "--epochs", "1", "--out",
                str(tmp_path / "w.pt"), "--threads", "1"]) == 0
    said = capsys.readouterr().out
    assert "DECLINED" in said and "fewer than two blocks of --block 60" in said


def test_declined_adaptation_writes_the_base_weights_and_says_why(shipped_trace_dir, tmp_path, capsys):
    out = tmp_path / "w.pt"            # no epoch can lower the held-out error by 99 %: declined
    assert cli(["adapt", "--weights", str(ONE), str(shipped_trace_dir), "--max-epochs", str(FEW), "--epochs", "2",
                "--margin", "0.99", "--part", "all", "--agree", "1", "--out", str(out), "--threads", "1"]) == 0
    said = capsys.readouterr().out.splitlines()
    assert said[0].startswith("adaptation DECLINED") and "base weights" in said[0] and "margin 99.00%" in said[0]
    assert _differing(ONE, out) == set()          # every tensor, dtype and value
    base, new = read_checkpoint(ONE), read_checkpoint(out)
    assert new["config"]["input_ranges"] == base["config"]["input_ranges"]   # the guard is not loosened
    rec = new["config"]["adapted"][-1]
    assert rec["decision"] == "declined" and rec["best_epoch"] == 0 and "gain" in rec["reason"]
    assert len(rec["heldout"]) == 3 and all(v is not None for v in rec["heldout"]) and rec["heldout_samples"] > 0
    assert {k for k in new["config"] if k != "adapted"} == {k for k in base["config"] if k != "adapted"}


def test_accepted_adaptation_keeps_the_best_epoch_and_moves_only_the_chosen_part(shipped_trace_dir, tmp_path):
    rec = adapt([shipped_trace_dir], tmp_path / "sat.pt", weights=ONE,
                cfg=AdaptConfig(epochs=2, max_epochs=FEW, margin=-1.0, lr=1e-2, graph_check=False))
    assert rec["decision"] == "accepted" and rec["best_epoch"] == 1 + int(np.argmin(rec["heldout"][1:]))
    assert _differing(ONE, tmp_path / "sat.pt") == {"sat_head.weight", "sat_head.bias"}
    rec = adapt([shipped_trace_dir], tmp_path / "all.pt", weights=ONE,
                cfg=AdaptConfig(epochs=1, max_epochs=FEW, margin=-1.0, part="all", agree=1.0, graph_check=False))
    assert len(_differing(ONE, tmp_path / "all.pt")) > 10
    with pytest.raises(GnssfuseError, match="part must be one of"):
        adapt([shipped_trace_dir], tmp_path / "x.pt", weights=ONE,
              cfg=AdaptConfig(epochs=1, max_epochs=FEW, part="trunk"))


def test_a_teacher_tighter_than_the_checks_can_judge_declines_and_keeps_the_base(shipped_trace_dir, tmp_path):
    cfg = AdaptConfig(epochs=1, max_epochs=FEW, margin=-1.0, lr=1e-2, graph_check=False)
    kept = adapt([shipped_trace_dir], tmp_path / "kept.pt", weights=ONE, cfg=cfg)
    med = kept["teacher_sigma_h_median_m"]
    assert kept["decision"] == "accepted" and med >= cfg.min_teacher_sigma_m
    # the same adaptation where the least teacher sigma is above this log's median: declined, the base written
    tight = adapt([shipped_trace_dir], tmp_path / "tight.pt", weights=ONE,
                  cfg=dataclasses.replace(cfg, min_teacher_sigma_m=2 * med))
    assert tight["decision"] == "declined" and tight["best_epoch"] == 0
    assert f"median horizontal sigma is {med:.2f} m" in tight["reason"] and tight["heldout"] == kept["heldout"]
    assert _differing(ONE, tmp_path / "tight.pt") == set() and _differing(ONE, tmp_path / "kept.pt")


def test_a_log_whose_track_carrier_phase_ties_declines_and_keeps_the_base(tmp_path, monkeypatch):
    """A simulated phone log with carrier phase (truth removed): the same adaptation accepted with the carrier
    rule off is declined at the default, the base written byte for byte; the record counts the tied epochs."""
    import learned.adapt as adapt_module
    from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
    from fusion.sim.simulate import SimConfig, simulate
    sim = simulate(n_epochs=FEW, nav=read_rinex_nav(default_nav_path()), seed=4,
                   config=SimConfig(doppler=True, carrier=True, slip_prob=0.005)).trace
    monkeypatch.setattr(adapt_module, "load_log", lambda path, opts, max_epochs=None: dataclasses.replace(sim, truth=None))
    cfg = AdaptConfig(epochs=1, margin=-1.0, lr=1e-2, graph_check=False, min_teacher_sigma_m=0.0)
    kept = adapt([tmp_path / "sim"], tmp_path / "kept.pt", weights=ONE, cfg=dataclasses.replace(cfg, max_carrier_share=1.0))
    share = kept["teacher_carrier_share"]
    (counts,) = kept["traces"].values()
    assert kept["decision"] == "accepted" and counts["carrier"] and share > 0.9
    assert counts["carrier_linked"] == pytest.approx(share * counts["teacher_solved"], abs=1)
    tied = adapt([tmp_path / "sim"], tmp_path / "tied.pt", weights=ONE, cfg=cfg)
    assert tied["decision"] == "declined" and tied["best_epoch"] == 0 and tied["heldout"] == kept["heldout"]
    assert f"carrier phase ties {share:.0%} of the teacher's epochs, above 50%" in tied["reason"]
    assert _differing(ONE, tmp_path / "tied.pt") == set() and _differing(ONE, tmp_path / "kept.pt")


def test_a_log_without_carrier_is_not_touched_by_the_carrier_rule(shipped_trace_dir, tmp_path):
    cfg = AdaptConfig(epochs=1, max_epochs=FEW, margin=-1.0, lr=1e-2, graph_check=False, max_carrier_share=0.0)
    rec = adapt([shipped_trace_dir], tmp_path / "w.pt", weights=ONE, cfg=cfg)
    assert rec["decision"] == "accepted" and rec["teacher_carrier_share"] == 0.0


def test_scale_anchor_ignores_what_the_consistency_checks_and_pulls_what_it_cannot():
    from learned.adapt import scale_anchor
    mask = torch.tensor([[True, True, True, False]])
    f64 = dict(dtype=torch.float64)
    ref = {"sigma": torch.tensor([[2.0, 4.0, 8.0, 1.0]], **f64), "bias": torch.zeros(1, 4, **f64)}
    # ratios moved, the epoch's mean log-sigma kept, no bias: nothing to pull
    same_scale = dict(ref, sigma=ref["sigma"] * torch.tensor([[2.0, 0.5, 1.0, 9.0]], dtype=torch.float64))
    assert float(scale_anchor(same_scale, ref, mask)) == pytest.approx(0.0, abs=1e-12)
    # every sigma halved: (log 2)^2; a bias of one base sigma on one of three slots: 1/3
    assert float(scale_anchor(dict(ref, sigma=ref["sigma"] / 2), ref, mask)) == pytest.approx(np.log(2) ** 2)
    biased = dict(ref, bias=torch.tensor([[2.0, 0.0, 0.0, 50.0]], dtype=torch.float64))
    assert float(scale_anchor(biased, ref, mask)) == pytest.approx(1 / 3)


def _samples(n_per_trace=(130, 70), seed=0) -> Samples:
    rng = np.random.default_rng(seed)
    n = sum(n_per_trace)
    return Samples(rng.normal(size=(n, 6, 3)), rng.normal(size=(n, 6)), np.ones((n, 6), bool),
                   rng.normal(size=(n, 3)), np.repeat(np.arange(len(n_per_trace)), n_per_trace), ["a", "b"])


def test_held_out_split_is_interleaved_blocks_and_never_looks_at_the_teacher_or_truth():
    s = _samples()
    held = holdout_mask(s, block=20, every=4)
    # trace a: samples 20-39 and 100-119 held; trace b (restarts at 0): its samples 20-39
    assert np.flatnonzero(held).tolist() == [*range(20, 40), *range(100, 120), *range(150, 170)]
    other = _samples(seed=1)                       # other measurements and another "truth" (the teacher slot)
    other.truth[:] = np.nan
    assert np.array_equal(holdout_mask(other, 20, 4), held)
    fit, val = split(s, 20, 4)
    assert len(fit) + len(val) == len(s) and np.array_equal(val.pr, s.pr[held]) and np.array_equal(fit.pr, s.pr[~held])
    # a log shorter than one group still holds a block out (the second)
    assert holdout_mask(_samples((90,)), 60, 4).sum() == 30


def test_decide():
    assert decide([1.0, 0.999, 1.2], 0.005)[0] == 0                 # 0.1 % < 0.5 %
    best, why = decide([1.0, 0.9, 0.95], 0.005)
    assert best == 1 and "epoch 1" in why
    assert decide([1.0, 1.1], 0.0)[0] == 0                          # worse is never kept
    assert decide([float("nan"), 0.5], 0.005) == (0, "no held-out epoch with >= 5 satellites to validate on")
    assert decide([1.0, float("nan"), 0.9], 0.005)[0] == 2
    assert decide([0.0, 0.0], 0.005)[0] == 0 and "nothing to gain" in decide([0.0, 0.0], 0.005)[1]


@pytest.mark.parametrize("bad", [{"block": 0}, {"every": 1}])
def test_the_api_refuses_a_self_check_that_holds_nothing_out(bad, shipped_trace_dir, tmp_path):
    with pytest.raises(GnssfuseError, match="block >= 1 and every >= 2"):
        adapt([shipped_trace_dir], tmp_path / "w.pt", weights=ONE, cfg=AdaptConfig(max_epochs=FEW, **bad))


def test_the_command_line_defaults_are_the_apis(tmp_path):
    from fusion.cli.adapt import build_parser
    args = build_parser().parse_args(["x", "--out", str(tmp_path / "w.pt")])
    cfg = AdaptConfig()
    for name in ("epochs", "lr", "batch", "seed", "loo", "teacher", "part", "agree", "anchor", "margin", "block",
                 "every", "graph_check", "graph_margin"):
        assert getattr(args, name) == getattr(cfg, name), name
    assert args.max_teacher_sigma == cfg.max_teacher_sigma_m and args.elev_mask == cfg.elev_mask_deg
    assert args.min_teacher_sigma == cfg.min_teacher_sigma_m and args.max_carrier_share == cfg.max_carrier_share


def test_an_ensemble_is_adapted_member_by_member_into_a_manifest(shipped_trace_dir, tmp_path, capsys):
    """The default weights are the shipped ensemble: its adaptation is an ensemble too, each member fine-tuned
    on the same teacher's samples, the manifest written last with the base's calibration."""
    from learned.ensemble import Ensemble
    assert cli(["adapt", str(shipped_trace_dir), "--max-epochs", str(FEW), "--out", str(tmp_path / "w.pt")]) == 2
    err = capsys.readouterr().err.strip()
    assert "give --out a .json" in err and "\n" not in err and not (tmp_path / "w.pt").exists()
    base = tmp_path / "base.pt"                      # a copy: were the check missing, nothing shipped is lost
    shutil.copy(ONE, base)
    with pytest.raises(GnssfuseError, match="would overwrite the base weights"):
        adapt([shipped_trace_dir], base, weights=base, cfg=AdaptConfig(max_epochs=FEW))
    out = tmp_path / "w.json"
    assert cli(["adapt", str(shipped_trace_dir), "--max-epochs", str(FEW), "--epochs", "1", "--out", str(out),
                "--threads", "1", "--margin", "-1", "--graph-margin", "-1"]) == 0
    said = capsys.readouterr().out
    assert said.startswith(f"adapted {SHIPPED_WEIGHTS.name}") and "member 2:" in said
    bases, cal = read_manifest(SHIPPED_WEIGHTS)
    members, new_cal = read_manifest(out)
    assert [m.name for m in members] == [f"w_m{i}.pt" for i in range(len(bases))] and new_cal == cal
    train_s = 0.0
    for b, m in zip(bases, members):
        rec = read_checkpoint(m)["config"]["adapted"][-1]
        assert rec["from"] == b.name and rec["decision"] == "accepted" and rec["graph_check"]["measurements"] > 0
        assert _differing(b, m) == {"sat_head.weight", "sat_head.bias"}
        train_s += rec["train_s"]
    assert f"training {train_s:.0f} s" in said        # the whole ensemble's fine-tuning, not one member's
    assert isinstance(Corrector.load(out), Ensemble)
    assert cli(["run", str(shipped_trace_dir), "--mode", "fused", "--weights", str(out),
                "--out", str(tmp_path / "run")]) == 0


def test_an_ensemble_the_graph_check_declines_keeps_every_base_member(shipped_trace_dir, tmp_path):
    rec = adapt([shipped_trace_dir], tmp_path / "w.json",
                cfg=AdaptConfig(epochs=1, max_epochs=FEW, margin=-1.0, graph_margin=0.99, lr=1e-2))
    assert rec["decision"] == "declined" and "graph check" in rec["reason"]
    assert len(rec["members"]) == len(read_manifest(SHIPPED_WEIGHTS)[0])
    for b, m in zip(read_manifest(SHIPPED_WEIGHTS)[0], read_manifest(tmp_path / "w.json")[0]):
        assert _differing(b, m) == set()
        new = read_checkpoint(m)["config"]
        assert new["adapted"][-1]["decision"] == "declined"
        assert new["input_ranges"] == read_checkpoint(b)["config"]["input_ranges"]
