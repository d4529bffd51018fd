import sys

from deepcontact.cli import main

sys.exit(main())
