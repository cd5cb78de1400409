"""``python -m server.cli``: the ``steelscan`` command."""

import sys

from server.cli.main import main

sys.exit(main())
