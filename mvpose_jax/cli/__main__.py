"""``python -m mvpose_jax.cli``: the ``mvpose-jax`` command."""

import sys

from mvpose_jax.cli import main

sys.exit(main())
