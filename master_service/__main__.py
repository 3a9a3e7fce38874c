"""``python -m master_service`` is ``surprise-master``."""

from master_service.cli import main

raise SystemExit(main())
