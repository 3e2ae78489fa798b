import sys

from drums.cli import main

sys.exit(main())
