"""``python -m mmpc.cli``: the ``mmpc`` command."""

import sys

from mmpc.cli.main import main

sys.exit(main())
