"""``python -m msagv``: the same as the ``msagv`` command."""

import sys

from .cli import main

sys.exit(main())
