"""``python -m wm``: the ``wm`` command (:func:`wm.cli.main`), for an interpreter whose
scripts folder is not on the PATH."""

import sys

from wm.cli import main

sys.exit(main())
