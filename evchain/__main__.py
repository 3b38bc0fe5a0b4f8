"""``python -m evchain``: the ``evchain`` command."""

import sys

from evchain.cli import main

sys.exit(main())
