"""``python -m cellcal.core.cli``: the same as the ``cellcal`` command."""

import sys

from cellcal.core.cli import main

sys.exit(main())
