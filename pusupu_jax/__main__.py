"""``python -m pusupu_jax``: the ``pusupu`` command."""

import sys

from .cli import main

sys.exit(main())
