"""``python -m i4cal``: the ``i4cal`` command line (:func:`i4cal.cli.main`: the service's commands and ``bench``)."""

import sys

from i4cal.cli import main

if __name__ == "__main__":
    sys.exit(main())
