"""``python -m pusupu_jax.cli``: the ``pusupu`` command."""

import sys

from .cli import main

sys.exit(main())
