"""``python -m cli SUBCOMMAND ...``: the ``gsoe`` command line."""

from cli.main import main

raise SystemExit(main())
