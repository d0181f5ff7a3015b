"""``python -m sumoco`` is the ``sumoco`` command."""

import sys

from sumoco.app.cli import main

sys.exit(main())
