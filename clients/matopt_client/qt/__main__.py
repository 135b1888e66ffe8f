"""``python -m matopt_client.qt``: the same as the ``matopt-qt`` command."""

import sys

from matopt_client.qt import main

sys.exit(main())
