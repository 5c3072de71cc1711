import sys

from mvtex.cli import main

sys.exit(main())
