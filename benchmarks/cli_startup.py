"""How long ``lightning-vtr --help`` and ``lightning-vtr COMMAND --help`` take to answer: the median wall time of a
few fresh processes per command line (each imports only what its command needs).

``fit`` / ``validate`` / ``test --help`` print the help texts shipped with the package (``lightning_vtr/cli/help/``);
with ``--live`` the same command lines are also timed through the live ``LightningCLI`` parser (what any other
LightningCLI command line, such as ``fit --config CONFIG.yaml --help``, and an environment whose library versions
differ from the shipped texts' get), marked ``(live)``.

Run: ``python benchmarks/cli_startup.py [--repeats 5] [--live]``. Prints one line per command line: the median, the
fastest and the slowest of the runs, in seconds. Measure on an idle machine: other processes on the cores slow
every start.
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
#: The LightningCLI commands whose ``--help`` ``--live`` also times through the live parser.
LIVE_COMMANDS = ("fit", "validate", "test")
#: The path ``lightning-vtr`` takes for a LightningCLI command line that has no shipped help.
_LIVE = "import sys\nfrom lightning_vtr.cli.lightning import run_lightning_cli\nrun_lightning_cli(sys.argv[1:])"


def seconds(words: list[str], live: bool = False) -> float:
    """Wall time of one ``python -m lightning_vtr.cli WORDS --help`` process (``live``: through the live
    LightningCLI parser instead)."""
    program = ["-c", _LIVE] if live else ["-m", "lightning_vtr.cli"]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, *program, *words, "--help"], capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if done.returncode != 0 or "usage:" not in done.stdout:
        raise SystemExit(f"`{' '.join([*words, '--help'])}` printed no help (exit {done.returncode}): {done.stderr}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="processes per command line (default 5)")
    parser.add_argument("--live", action="store_true", help="also time fit/validate/test --help via LightningCLI")
    args = parser.parse_args()
    seconds([])  # warm the file cache
    runs_of = [(words, False) for words in COMMAND_LINES]
    if args.live:
        seconds([LIVE_COMMANDS[0]], live=True)  # warm the cache of Lightning's files too
        runs_of += [([command], True) for command in LIVE_COMMANDS]
    print(f"{'command line':<47} median    min    max  (seconds, {args.repeats} runs)")
    for words, live in runs_of:
        runs = [seconds(words, live) for _ in range(args.repeats)]
        line = " ".join(["lightning-vtr", *words, "--help"]) + (" (live)" if live else "")
        print(f"{line:<47} {statistics.median(runs):6.2f} {min(runs):6.2f} {max(runs):6.2f}")


if __name__ == "__main__":
    main()
