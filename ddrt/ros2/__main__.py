"""`python -m ddrt.ros2`: the bridge's process (the daemon starts it so)."""

import sys

from ddrt.ros2.main import main

sys.exit(main())
