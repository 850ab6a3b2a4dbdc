"""``python -m learned.export CKPT.pt [--out W.npz]``: write the torch-free weights of a checkpoint
(:mod:`learned.npz_weights`), for checkpoints saved before training wrote them itself."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fusion.errors import GnssfuseError
from learned.npz_weights import export_checkpoint


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m learned.export", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path, help="a .pt checkpoint written by gnssfuse train")
    p.add_argument("--out", type=Path, default=None, help="the .npz to write (default: beside the .pt)")
    args = p.parse_args(argv)
    try:
        print(export_checkpoint(args.checkpoint, args.out))
    except GnssfuseError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
