"""``python -m service.cli``: the same entry point as the ``oarmreg`` script."""

from service.cli.main import main

raise SystemExit(main())
