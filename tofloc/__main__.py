"""``python -m tofloc ARGS``: the ``tofloc`` command (:func:`tofloc.cli.main`), for an
environment whose scripts folder is not on ``PATH``."""

import sys

from tofloc.cli import main

if __name__ == "__main__":
    sys.exit(main())
