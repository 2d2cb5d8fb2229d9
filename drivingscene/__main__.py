import sys

from drivingscene.cli import main

sys.exit(main())
