import sys

from dragd.cli.app import main

sys.exit(main())
