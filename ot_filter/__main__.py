import sys

from ot_filter.cli import main

sys.exit(main())
