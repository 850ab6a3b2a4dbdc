"""``gnssfuse`` command line: a thin dispatcher.

Each subcommand lives in the module that owns the work and exposes ``main(argv, prog) -> int``.
Modules are imported only when their subcommand runs, so ``gnssfuse run --mode wls`` never
imports torch.
"""
from __future__ import annotations

import importlib
import sys

from fusion.errors import GnssfuseError

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("fusion.pipeline", "solve one trace in one mode (wls, dnn, fused, fused-nodnn)"),
    "evaluate": ("fusion.report", "compare modes on traces: tables, CDFs, box plots, report.md"),
    "simulate": ("fusion.simulate", "simulate a GNSS trace (GSDC 2021 derived format + truth)"),
    "train": ("learned.train", "train the set-transformer correction network"),
}


def _usage() -> str:
    lines = ["usage: gnssfuse COMMAND [options]   (gnssfuse COMMAND --help for each)", "", "commands:"]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gnssfuse: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[cmd][0])
    try:
        return int(module.main(rest, prog=f"gnssfuse {cmd}") or 0)
    except (GnssfuseError, OSError) as exc:
        # One line, no traceback: the message already names the file/epoch and the problem
        # (OSError: a missing input, an unwritable --out folder).
        print(f"gnssfuse {cmd}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
