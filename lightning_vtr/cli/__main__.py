"""``python -m lightning_vtr.cli``: the same as the ``lightning-vtr`` command."""

import sys

from lightning_vtr.cli.main import main

sys.exit(main())
