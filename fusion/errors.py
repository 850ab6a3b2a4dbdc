"""Errors raised by gnssfuse.

Every error a user can provoke with bad input is a ``ValueError`` subclass, so callers that
already catch ``ValueError`` keep working, and the CLI can print one line and exit non-zero.
"""
from __future__ import annotations


class GnssfuseError(ValueError):
    """Base class for every input error gnssfuse raises on purpose."""


class DataError(GnssfuseError):
    """A measurement / truth / navigation file is missing, malformed or inconsistent.

    The message always names the file (and row or epoch where known) and what is wrong.
    """


class GeometryError(GnssfuseError):
    """A solve cannot proceed: too few satellites, singular geometry, divergence."""


class ModeUnavailableError(GnssfuseError):
    """A mode cannot run in this installation (its module or a dependency such as torch is missing):
    "unavailable", as opposed to a mode that ran and failed on the input."""


class CheckpointError(GnssfuseError):
    """A model checkpoint is corrupt, truncated or does not match the code that loads it."""


class ConfigError(GnssfuseError):
    """A settings file (e.g. ``--graph-config``) that cannot be used: unreadable, not TOML, an unknown
    setting or a value of the wrong type."""
