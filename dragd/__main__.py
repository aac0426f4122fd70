import sys

from dragd.cli.app import main

if __name__ == "__main__":  # not when a spawned process (the telemetry writer) imports the parent's main module
    sys.exit(main())
