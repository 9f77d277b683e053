"""``lightning-vtr dataset-info``: a per-category, per-split summary of a ShapeNet-VTR directory; with
``--verify``, also read every image and voxel file once and list the ones a training run would fail on."""

from __future__ import annotations

import argparse

from lightning_vtr.cli.arguments import positive_int

__all__ = ["EXIT_PROBLEMS", "add_arguments", "run"]


#: The exit status of ``--verify`` when it finds problems (2 stays for errors a user can fix, e.g. a bad path).
EXIT_PROBLEMS = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Print a per-category, per-split summary of a ShapeNet-VTR directory. With --verify, read every image "
        "and voxel file once (in parallel) and list every missing, unreadable or inconsistent file; the exit "
        f"status is then {EXIT_PROBLEMS} when there is any."
    )
    parser.add_argument("root", help="dataset directory, or `embedded` for the embedded dataset")
    parser.add_argument("--verify", action="store_true", help="read every file and list the problems")
    parser.add_argument(
        "--workers", type=positive_int, default=None, help="threads reading files with --verify (default CPUs + 4)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar with --verify")


def run(args: argparse.Namespace) -> int:
    from lightning_vtr.cli.arguments import dataset_folder
    from lightning_vtr.data.format import dataset_summary
    from lightning_vtr.utils.paths import printable

    args.root = dataset_folder(args.root, "root", progress=not args.no_progress, read=False)
    print(dataset_summary(args.root, check_entries=not args.verify))
    if not args.verify:
        return 0
    from lightning_vtr.data.verify import verify_dataset

    report = verify_dataset(args.root, workers=args.workers, progress=not args.no_progress)
    for problem in report.problems:
        print(printable(f"  PROBLEM [{problem.kind}] {problem}"))
    print(report.summary())
    return 0 if report.ok else EXIT_PROBLEMS
