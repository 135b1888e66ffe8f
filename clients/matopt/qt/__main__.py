"""``python -m matopt.qt``: the same as the ``matopt-qt`` command."""

import sys

from matopt.qt import main

sys.exit(main())
