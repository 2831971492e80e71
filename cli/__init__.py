"""The ``gsoe`` command line (:mod:`cli.main`, one ``cmd_*`` module per subcommand): the one layer that may import
both the simulator (:mod:`sim`) and the flight side (:mod:`nav`).  ``python -m cli ...`` runs it like ``gsoe``."""
