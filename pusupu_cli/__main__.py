"""``python -m pusupu_cli``: the ``pusupu`` command."""

import sys

from .cli import main

sys.exit(main())
