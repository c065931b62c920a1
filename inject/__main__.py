"""``python -m inject``."""
import sys

from inject.cli.main import main

sys.exit(main())
