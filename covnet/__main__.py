"""``python -m covnet`` is the ``covnet`` command."""

import sys

from covnet.cli import main

sys.exit(main())
