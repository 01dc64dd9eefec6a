import sys

from piezod.cli import main

sys.exit(main())
