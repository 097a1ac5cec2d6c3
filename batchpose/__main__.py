import sys

from batchpose.cli import main

sys.exit(main())
