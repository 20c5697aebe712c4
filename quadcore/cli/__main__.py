"""``python -m quadcore.cli``: the ``quadcore`` command."""

import sys

from quadcore.cli import main

sys.exit(main())
