"""``python -m wheelleg_balance.validation.paper.main_job``: the main_job command."""
import sys

from .cli import main

sys.exit(main())
