"""``python -m covnet`` is the ``covnet`` command."""

import sys

from covnet.cli import main

if __name__ == "__main__":
    sys.exit(main())
