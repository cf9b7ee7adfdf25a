"""``python -m onboard.settings``: print the settings tables, or write them into docs/SETTINGS.md."""
from onboard.settings.docs import main

raise SystemExit(main())
