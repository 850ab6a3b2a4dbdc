"""``python -m fusion.cli``: the same as the ``gnssfuse`` script (also under ``torchrun -m``)."""
import sys

from fusion.cli import main

sys.exit(main())
