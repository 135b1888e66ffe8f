"""``python -m matopt_client.cli``: the ``matopt`` command where no console script is installed."""

from matopt_client.cli import main

main()
