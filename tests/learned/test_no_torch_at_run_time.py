"""The learned modes run without torch: the numpy network (learned/npnet.py) from the shipped .npz."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("mode", ["dnn", "fused"])
def test_run_mode_never_imports_torch(shipped_trace_dir, tmp_path, mode):
    code = textwrap.dedent(f"""
        import sys
        from fusion.cli import main
        rc = main(["run", {str(shipped_trace_dir)!r}, "--mode", {mode!r}, "--out", {str(tmp_path / 'o')!r}])
        assert rc == 0, rc
        print("TORCH" if "torch" in sys.modules else "NO-TORCH")
    """)
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1] == "NO-TORCH"
    assert (tmp_path / "o" / "metrics.json").is_file() or (tmp_path / "o").is_dir()


@pytest.mark.parametrize("member", [0, 1, 2])
def test_shipped_npz_is_the_shipped_pt(member):
    """Each shipped member's .npz twin was exported from the .pt beside it (hash recorded), with equal tensors."""
    pytest.importorskip("torch")
    from learned.checkpoint import read_checkpoint
    from learned.ensemble import read_manifest
    from learned.infer import SHIPPED_WEIGHTS
    from learned.npz_weights import file_sha256, npz_path_for, read_npz
    pt = read_manifest(SHIPPED_WEIGHTS)[0][member]
    weights, config, sha = read_npz(npz_path_for(pt))
    assert sha == file_sha256(pt)
    blob = read_checkpoint(pt)
    assert config == blob["config"] | {}
    assert set(weights) == set(blob["model_state"])
    for k, v in blob["model_state"].items():
        np.testing.assert_array_equal(weights[k], v.float().numpy())


def test_stale_npz_falls_back_to_the_pt(tmp_path):
    """An .npz exported from another .pt is not used for this one (its hash differs)."""
    pytest.importorskip("torch")
    from learned.checkpoint import save_checkpoint
    from learned.features import FeatureConfig
    from learned.model import build_model
    from learned.npz_weights import load_for_inference, npz_path_for
    cfg = {"model": {"kind": "set", "hparams": {"d_in": 4}}, "features": FeatureConfig().to_dict()}
    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    import torch
    torch.manual_seed(0)
    save_checkpoint(a, build_model("set"), cfg)
    torch.manual_seed(1)
    save_checkpoint(b, build_model("set"), cfg)
    npz_path_for(a).write_bytes(npz_path_for(b).read_bytes())      # a copied-over, stale twin
    w, _, read = load_for_inference(a)
    assert read == a
    wb, _, read_b = load_for_inference(b)
    assert read_b == npz_path_for(b)
    assert not np.array_equal(w["head.weight"], wb["head.weight"])


def _without_torch(code: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter where ``import torch`` fails, as on an install without the
    train extra."""
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-c", "import sys; sys.modules['torch'] = None\n" + textwrap.dedent(code)],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def test_an_install_without_torch_runs_fused_and_says_what_training_needs(shipped_trace_dir, tmp_path):
    proc = _without_torch(f"""
        from fusion.cli import main
        assert main(["run", {str(shipped_trace_dir)!r}, "--mode", "fused", "--out", {str(tmp_path / 'o')!r}]) == 0
    """, tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    proc = _without_torch(f"""
        import sys
        from fusion.cli import main
        sys.exit(main(["train", "--data", "toy", "--out", {str(tmp_path / 'w.pt')!r}]))
    """, tmp_path)
    assert proc.returncode == 2
    assert "gnssfuse[train]" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_a_pt_without_its_npz_and_without_torch_is_a_one_line_error(tmp_path):
    import shutil

    from learned.ensemble import read_manifest
    from learned.infer import SHIPPED_WEIGHTS
    pt = tmp_path / "copy.pt"
    shutil.copy(read_manifest(SHIPPED_WEIGHTS)[0][0], pt)  # no .npz beside it
    proc = _without_torch(f"""
        from learned.infer import Corrector
        try:
            Corrector.load({str(pt)!r})
        except Exception as exc:
            print(type(exc).__name__, exc)
    """, tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("CheckpointError") and "learned.export" in proc.stdout
