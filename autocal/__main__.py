"""``python -m autocal``: the ``autocal`` command line."""

from autocal.cli.main import main

raise SystemExit(main())
