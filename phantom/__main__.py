import sys

from phantom.host.cli import main

sys.exit(main())
