"""The adaptation's graph check (learned/graph_check.py): satellites held out of the fused graph."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.cli import main as cli
from fusion.errors import GnssfuseError
from fusion.prepare.load import load_trace
from learned.adapt import AdaptConfig, adapt
from learned.checkpoint import read_checkpoint
from learned.graph_check import CAP, graph_decision, heldout_residuals, satellite_folds
from learned.ensemble import read_manifest
from learned.infer import SHIPPED_WEIGHTS

#: One network of the shipped ensemble.
ONE = read_manifest(SHIPPED_WEIGHTS)[0][0]

FEW = 150


@pytest.fixture(scope="module")
def trace(shipped_trace_dir):
    return load_trace(shipped_trace_dir).select(np.arange(FEW))


def test_folds_deal_whole_satellites_and_every_one_once(trace):
    fold = satellite_folds(trace, 4, seed=0)
    assert (fold[~trace.mask] == -1).all() and set(np.unique(fold[trace.mask])) == {0, 1, 2, 3}
    for sid in np.unique(trace.sat_id[trace.mask]):          # one satellite, one fold, at every epoch
        assert len(np.unique(fold[trace.mask & (trace.sat_id == sid)])) == 1
    assert np.array_equal(fold, satellite_folds(trace, 4, seed=0))
    assert not np.array_equal(fold, satellite_folds(trace, 4, seed=1))


def test_held_out_residuals_see_where_the_phone_is_not_the_clock(trace):
    held = satellite_folds(trace, 4) == 0
    at_truth = heldout_residuals(trace, trace.truth, held)
    assert at_truth.size == (held & trace.mask & np.isfinite(trace.truth).all(1)[:, None]).sum()
    # a clock common to every satellite of an epoch changes nothing: the kept satellites fix it
    clocked = replace(trace, pr=trace.pr + np.linspace(0.0, 3e5, trace.n_epochs)[:, None])
    assert np.allclose(heldout_residuals(clocked, trace.truth, held), at_truth, atol=1e-6)
    # positions 10 and 30 m east of the truth predict the held-out pseudoranges worse and worse
    from fusion.geometry import ned2ecef_vec
    scores = [np.minimum(heldout_residuals(trace, trace.truth + ned2ecef_vec(
        np.tile([0.0, east, 0.0], (trace.n_epochs, 1)), trace.truth), held), CAP).mean() for east in (0, 10, 30)]
    assert scores[0] < scores[1] < scores[2]
    # unsolved epochs score nothing
    gone = trace.truth.copy()
    gone[:10] = np.nan
    assert heldout_residuals(trace, gone, held).size == (held[10:] & trace.mask[10:]).sum()


def test_graph_decision():
    assert graph_decision({"error_m": 2.0}, {"error_m": 1.9, "measurements": 9}, 0.0)[0]
    keep, why = graph_decision({"error_m": 2.0}, {"error_m": 2.0, "measurements": 9}, 0.0)
    assert not keep and "not above" in why              # not better is not kept
    assert not graph_decision({"error_m": 2.0}, {"error_m": 1.9, "measurements": 9}, 0.1)[0]
    assert not graph_decision({"error_m": float("nan")}, {"error_m": 1.0, "measurements": 0}, 0.0)[0]


def test_the_default_margin_tolerates_one_percent():
    from learned.adapt import AdaptConfig
    from learned.graph_check import MARGIN
    assert AdaptConfig().graph_margin == MARGIN == -0.01
    assert graph_decision({"error_m": 2.0}, {"error_m": 2.009, "measurements": 9}, MARGIN)[0]     # 0.45 % worse
    assert not graph_decision({"error_m": 2.0}, {"error_m": 2.024, "measurements": 9}, MARGIN)[0]  # 1.2 % worse


def test_a_graph_check_that_fails_writes_the_base_weights_and_says_why(shipped_trace_dir, tmp_path, capsys):
    out = tmp_path / "w.pt"      # the self-check keeps anything (-1); no adaptation gains 99 % in the graph
    assert cli(["adapt", str(shipped_trace_dir), "--weights", str(ONE), "--max-epochs", str(FEW), "--epochs", "1",
                "--margin", "-1", "--graph-margin", "0.99", "--lr", "1e-2", "--out", str(out), "--threads", "1"]) == 0
    said = capsys.readouterr().out.splitlines()[0]
    assert said.startswith("adaptation DECLINED") and "graph check" in said
    base, new = read_checkpoint(ONE), read_checkpoint(out)
    assert all(np.array_equal(base["model_state"][k], new["model_state"][k]) for k in base["model_state"])
    assert new["config"]["input_ranges"] == base["config"]["input_ranges"]
    rec = new["config"]["adapted"][-1]
    g = rec["graph_check"]
    assert rec["decision"] == "declined" and rec["best_epoch"] == 0 and g["folds"] == 4
    assert g["measurements"] > 0 and g["base_m"] > 0 and g["adapted_m"] > 0 and g["base_m"] != g["adapted_m"]


def test_the_api_refuses_a_graph_check_without_folds(shipped_trace_dir, tmp_path):
    with pytest.raises(GnssfuseError, match="at least 2 satellite folds"):
        adapt([shipped_trace_dir], tmp_path / "w.pt", weights=ONE, cfg=AdaptConfig(max_epochs=FEW, graph_folds=1))


def test_graph_errors_are_paired_and_skip_a_fold_any_graph_cannot_solve(trace, monkeypatch):
    import learned.graph_check as gc
    from fusion.errors import GeometryError
    from fusion.run_types import RunOptions
    calls = []

    def positions(tr, opts):                 # the truth, 5 m off for the second option; its 2nd fold fails
        calls.append(opts.elev_mask_deg)
        if opts.elev_mask_deg == 11.0 and len(calls) == 4:
            raise GeometryError("too few satellites")
        return trace.truth + (5.0 if opts.elev_mask_deg == 11.0 else 0.0)

    monkeypatch.setattr(gc, "_positions", positions)
    a, b = gc.graph_errors([trace], [RunOptions(), RunOptions(elev_mask_deg=11.0)], folds=4)
    assert a["folds_unsolved"] == b["folds_unsolved"] == 1
    assert a["measurements"] == b["measurements"] > 0          # the same three folds for both
    assert a["error_m"] < b["error_m"]
