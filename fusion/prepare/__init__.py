"""Parsed records -> :class:`~fusion.trace.Trace`: satellite states, corrections, inter-signal biases,
truth matched to epochs and the first WLS where a format needs one (:mod:`fusion.io` only parses files)."""
