"""``python -m agents.cli``: the ``tensegrity-gym`` command."""

from agents.cli import main

raise SystemExit(main())
