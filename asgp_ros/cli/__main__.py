import sys

from asgp_ros.cli import main

sys.exit(main())
