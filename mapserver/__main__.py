"""``python -m mapserver``: the ``mapserver`` command, for an environment whose scripts are not
on the PATH."""

import sys

from mapserver.cli import main

sys.exit(main())
