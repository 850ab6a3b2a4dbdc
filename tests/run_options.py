"""The run options a command line gives (``fusion.options``' parser), for tests of one flag or another."""
from __future__ import annotations

import argparse

from fusion.options import add_run_options, options_from_args
from fusion.run_types import RunOptions


def parse_run_options(argv: list[str]) -> RunOptions:
    """RunOptions from command-line words such as ``["--no-doppler"]``."""
    p = argparse.ArgumentParser()
    add_run_options(p)
    return options_from_args(p.parse_args(argv))
