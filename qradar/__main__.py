"""``python -m qradar``: the same as the ``qradar`` command."""

import sys

from .cli import main

sys.exit(main())
