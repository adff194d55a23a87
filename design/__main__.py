"""``python -m design``: see :mod:`design.cli`."""

from .cli import main

raise SystemExit(main())
