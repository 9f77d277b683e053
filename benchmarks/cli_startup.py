"""How long ``lightning-vtr --help`` and ``lightning-vtr COMMAND --help`` take to answer: the median wall time of a
few fresh processes per command line (each imports only what its command needs).

Run: ``python benchmarks/cli_startup.py [--repeats 5]``. Prints one line per command line: the median, the fastest
and the slowest of the runs, in seconds. Measure on an idle machine: other processes on the cores slow every start.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

COMMAND_LINES = (
    [],
    ["build-dataset"],
    ["dataset-info"],
    ["report"],
    ["predict"],
    ["pix3d"],
    ["evaluate-folder"],
    ["robustness"],
    ["fit"],
    ["validate"],
    ["test"],
)


def seconds(words: list[str]) -> float:
    """Wall time of one ``python -m lightning_vtr.cli WORDS --help`` process."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "lightning_vtr.cli", *words, "--help"], check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="processes per command line (default 5)")
    args = parser.parse_args()
    seconds([])  # warm the file cache
    print(f"{'command line':<40} median    min    max  (seconds, {args.repeats} runs)")
    for words in COMMAND_LINES:
        runs = [seconds(words) for _ in range(args.repeats)]
        line = " ".join(["lightning-vtr", *words, "--help"])
        print(f"{line:<40} {statistics.median(runs):6.2f} {min(runs):6.2f} {max(runs):6.2f}")


if __name__ == "__main__":
    main()
