import sys

from dragd.cli.app import main

if __name__ == "__main__":  # not when imported (multiprocessing's spawn imports the main module of its parent)
    sys.exit(main())
