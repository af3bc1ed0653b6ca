"""``python -m services.cli``: the ``mfvs`` command line."""
import sys

from services.cli import main

sys.exit(main())
