"""experiments/fold_ensembles.py's helpers: simulated traces grouped by their street kind, and the table's means
over logs and folds."""
from __future__ import annotations

from pathlib import Path

from tests.experiment_module import experiment_module


def test_simulated_traces_are_grouped_by_their_street_kind_and_read_with_every_signal():
    mod = experiment_module("fold_ensembles")
    sims = [Path(f"/x/{n}/SimPhone") for n in ("ho-urban-101", "ho-suburban-102", "ho-deep-301", "walk-7")]
    got = mod.logs(sims)
    assert [g for g, _, _ in got] == ["smartLoc", "urban", "suburban", "deep", "simulated", "Pixel5 (test)"]
    assert got[0][2].signals is None and len(got[1][2].signals) > 1 and got[-1][2].nav == (mod.NAV,)


def test_the_table_gives_each_recipe_the_mean_of_its_folds_means():
    mod = experiment_module("fold_ensembles")
    got = {("fused-nodnn", "deep"): [10.0, 12.0], ("r", "deep", "AB"): [4.0, 6.0], ("r", "deep", "CD"): [8.0, 8.0]}
    lines = mod.table(got, ["r"], ["deep"]).splitlines()
    assert lines[2] == "| (`fused-nodnn`) | 11.00 |"
    assert lines[3] == "| r | 6.50 (5.00 / 8.00) |"


def test_recipes_sharing_their_first_run_get_manifests_of_their_own(tmp_path):
    from learned.ensemble import read_manifest
    mod = experiment_module("fold_ensembles")
    runs = [tmp_path / f"s{i}" for i in range(3)]
    for r in runs:
        r.mkdir()
        for fold in mod.FOLDS2:
            (r / f"fold_{fold}.pt").write_bytes(b"")
    three, two = mod.manifests("three seeds", runs), mod.manifests("two/seeds", runs[:2])
    for fold in mod.FOLDS2:
        assert three[fold] != two[fold] and three[fold].parent == two[fold].parent == runs[0]
        assert [p.parent.name for p in read_manifest(three[fold])[0]] == ["s0", "s1", "s2"]
        assert len(read_manifest(two[fold])[0]) == 2


def test_street_kind_reads_the_kind_sim_city_traces_writes_into_a_name():
    experiment_module("fold_ensembles")                        # puts experiments/ on the path
    from sim_city_traces import street_kind
    assert street_kind("ho-suburban-102") == "suburban" and street_kind("sim-urban-7") == "urban"
    assert street_kind("/tmp/simdeepho/ho-deep-301/SimPhone") == "deep"
    assert street_kind("ho-urban-105/SimPhone") == "urban" and street_kind("smartloc/Berlin") is None
