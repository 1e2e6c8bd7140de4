"""``python -m srvwire``: the same command line as the ``srvwire`` script."""

import sys

from srvwire.cli import main

if __name__ == "__main__":
    sys.exit(main())
