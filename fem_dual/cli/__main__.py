"""`python3 -m fem_dual.cli ...`: the command line."""
import sys

from fem_dual.cli import main

sys.exit(main())
