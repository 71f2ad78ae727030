"""``python -m i4cal``: the ``i4cal`` command line (:func:`service.cli.main`)."""

import sys

from service.cli import main

if __name__ == "__main__":
    sys.exit(main())
