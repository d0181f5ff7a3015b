"""``python -m sumoco`` is the ``sumoco`` command."""

import sys

from sumoco.cli import main

sys.exit(main())
