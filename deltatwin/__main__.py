"""``python -m deltatwin``: the same command line as ``deltatwin``."""
import sys

from deltatwin.cli import main

sys.exit(main())
