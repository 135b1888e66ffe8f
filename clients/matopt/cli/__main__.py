"""``python -m matopt.cli``: the ``matopt`` command where no console script is installed."""

from matopt.cli import main

main()
