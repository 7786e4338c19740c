"""``python -m sitl.vehicle``: run the simulated vehicle (see sitl/vehicle/__init__.py)."""

import sys

from sitl.vehicle.cli import main

sys.exit(main())
