"""``python -m lgshape.bench ARGS``: as ``lgshape bench ARGS``."""
import sys

from .driver import main

sys.exit(main())
