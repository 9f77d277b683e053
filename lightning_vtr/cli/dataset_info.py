"""``lightning-vtr dataset-info``: a per-category, per-split summary of a ShapeNet-VTR directory."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["HELP", "add_arguments", "run"]

HELP = "summarise a ShapeNet-VTR dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = "Print a per-category, per-split summary of a ShapeNet-VTR directory."
    parser.add_argument("root", type=Path, help="dataset directory")


def run(args: argparse.Namespace) -> int:
    from lightning_vtr.data.format import dataset_summary

    print(dataset_summary(args.root))
    return 0
