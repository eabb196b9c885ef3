"""``python -m cellcal.core.cli``: the same as the ``cellcal`` command."""

import sys

from cellcal.core.cli.main import main

sys.exit(main())
