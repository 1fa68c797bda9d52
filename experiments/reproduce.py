"""Reproduce the paper's integrated-error tables and figures: the same as ``platoon-opt reproduce``.

    python experiments/reproduce.py [--out DIR] [--seeds N] [--quick] [--scheduler ADDRESS] ...

Both call ``platoon_opt.harness.paper_study`` and ``run_study`` with ``solvers.get_allocator``.
"""

import sys

from platoon_opt.study.cli import main

if __name__ == "__main__":
    sys.exit(main(["reproduce", *sys.argv[1:]]))
