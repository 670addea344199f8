"""`python -m pig STAGE ...`: the `pig` command (pig.cli) without an installed script, as the workflow's rules run it."""
from pig.cli import main

raise SystemExit(main())
