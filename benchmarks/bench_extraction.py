"""Extraction benchmark (not a timed test): forwards to ``i4cal bench speed --only extraction,extract-calibrate``.

Run:  python benchmarks/bench_extraction.py [--frames 30] [--dataset DIR] [--workers 2] [--json PATH]

Per-frame board + eight rods (median ms, target <= 20 ms), extract + calibrate of the paper-sized dataset
(s, target <= 5 s) and its peak memory (MB, target <= 500 MB); the code is in
:mod:`i4cal.benchmarks.speed`.
"""

import sys

from i4cal.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "speed", "--only", "extraction,extract-calibrate", *sys.argv[1:]]))
