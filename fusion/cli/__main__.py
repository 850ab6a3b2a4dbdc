"""``python -m fusion.cli``: the same as the ``gnssfuse`` script (also under ``torchrun -m``)."""
from fusion.cli import entry

entry()
