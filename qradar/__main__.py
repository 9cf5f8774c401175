"""``python -m qradar``: the same as the ``qradar`` command."""

import sys

from .entry import main

sys.exit(main())
