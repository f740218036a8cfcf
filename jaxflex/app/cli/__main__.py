import sys

from jaxflex.app.cli import main

sys.exit(main())
