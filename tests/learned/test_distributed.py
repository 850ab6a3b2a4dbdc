"""``gnssfuse train`` under torchrun: two CPU processes (gloo) train, rank 0 writes one loadable checkpoint
whose validation error is in line with a one-process run, and ``--resume`` continues it."""
import os
import subprocess
import sys


from learned.checkpoint import read_checkpoint
from learned.infer import Corrector

ARGS = ["train", "--data", "toy", "--sim-traces", "6", "--sim-epochs", "60", "--guess-mix", "box=0.5,wls=0.5",
        "--quiet"]


def _train(tmp_path, out, epochs, nproc=1, extra=()):
    env = dict(os.environ, OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    launcher = ([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(nproc),
                 "--master_port", str(29500 + os.getpid() % 1000)] if nproc > 1 else [sys.executable])
    cmd = launcher + ["-m", "fusion.cli", *ARGS, "--epochs", str(epochs), "--out", str(out), *extra]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=240)
    assert run.returncode == 0, run.stderr[-2000:]
    return run


def test_two_process_training_matches_one_process_and_resumes(tmp_path):
    one = tmp_path / "one.pt"
    two = tmp_path / "two.pt"
    _train(tmp_path, one, 3)
    run = _train(tmp_path, two, 3, nproc=2)
    assert "world size 2" in run.stderr
    assert run.stdout.count("best epoch") == 1            # rank 0 alone logs
    blob = read_checkpoint(two)
    assert blob["config"]["world_size"] == 2
    Corrector.load(two)                                   # loads and builds
    best = lambda p: min(h["val_score_m"] for h in read_checkpoint(p)["history"])  # noqa: E731
    assert abs(best(two) - best(one)) < 0.25 * best(one)
    _train(tmp_path, two, 4, nproc=2, extra=["--resume"])
    assert [h["epoch"] for h in read_checkpoint(str(two) + ".last")["history"]] == [1, 2, 3, 4]
