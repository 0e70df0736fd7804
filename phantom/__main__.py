import sys

from phantom.cli.main import main

sys.exit(main())
