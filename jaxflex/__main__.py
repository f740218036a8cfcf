import sys

from jaxflex.cli import main

sys.exit(main())
