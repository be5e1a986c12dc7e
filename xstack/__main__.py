import sys

from xstack.cli import main

sys.exit(main())
