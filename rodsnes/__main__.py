import sys

from rodsnes.cli import main

sys.exit(main())
