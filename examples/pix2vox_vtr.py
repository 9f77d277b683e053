"""Pix2Vox++ with and without error-guided view augmentation, on the embedded dataset (or ShapeNet-VTR).

Pretrains tiny Pix2Vox++ on Aligned views, then fine-tunes it for the same number of epochs twice, once
without augmentation and once with ``ErrorGuidedViewAugmentation``, and prints the paper's Table-1 layout
(mIoU@0.4 and F-score on Aligned / Hemispherical / Spherical) for both.

    python examples/pix2vox_vtr.py                       # ~3 min on 2 CPU cores
    python examples/pix2vox_vtr.py --preset paper --data /data/shapenet_vtr --accelerator gpu --devices 4 \\
        --pretrain-epochs 100 --finetune-epochs 50 --batch-size 32

Runs are cached under ``--out``: re-running skips finished runs, and an interrupted run resumes from its
last checkpoint. The work is :func:`lightning_vtr.experiments.comparison.run_comparison`'s.
"""

from __future__ import annotations

import argparse
import warnings

from lightning_vtr.experiments.comparison import add_comparison_arguments, run_comparison


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    return add_comparison_arguments(parser, "pix2vox").parse_args(argv)


# Lightning 2.6 on torch 2.13 warns about a deprecated pytree API at every epoch; it is not ours to fix.
warnings.filterwarnings("ignore", message=".*treespec.*")


def main(argv: list[str] | None = None) -> dict:
    return run_comparison(parse_args(argv), "pix2vox")


if __name__ == "__main__":
    main()
