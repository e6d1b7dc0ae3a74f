"""``python -m cli``: the ``tbp`` command without its console script (a worktree, a test harness)."""

import sys

from cli import main

if __name__ == "__main__":
    sys.exit(main())
