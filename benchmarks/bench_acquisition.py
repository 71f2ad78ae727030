"""Acquisition benchmark (not a timed test): forwards to ``i4cal bench speed --only acquisition,modbus``.

Run:  python benchmarks/bench_acquisition.py [--poses 40] [--real-renderer] [--reads 1000] [--json PATH]

Overhead per pose beyond the simulated motion on the simulated bench (median ms, target <= 30 ms) and the
Modbus TCP loopback round trip (median ms); the code is in :mod:`i4cal.benchmarks.speed`.
"""

import sys

from i4cal.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "speed", "--only", "acquisition,modbus", *sys.argv[1:]]))
