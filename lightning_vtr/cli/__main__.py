"""``python -m lightning_vtr.cli``: the same as the ``lightning-vtr`` command."""

import sys

from lightning_vtr.cli.dispatch import main

sys.exit(main())
