"""Speed of the viewpoint robustness map (target: 50 objects at K = 30 in at most 3 minutes on 2 CPU cores).

Measures :func:`~lightning_vtr.evaluation.robustness.robustness_map` of tiny Pix2Vox++ (64 px, untrained: the
speed does not depend on the weights) on the first ``--objects`` test objects of the embedded dataset (built
once and cached; the test split is topped up from the other splits when it has fewer objects), with mesh
rendering at the model's input size. Prints the number of rendered views and predicted sets, the objects per
second and the total time, split into rendering and the rest (transform, prediction, IoU).

    python benchmarks/robustness_map.py [--objects 50] [--k 30] [--sets-per-bin 1] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import torch

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.evaluation.robustness import robustness_map
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.synthesis.render import RenderSynthesizer


class TimedRenderSynthesizer(RenderSynthesizer):
    """Mesh rendering that adds up the time spent in :meth:`synthesize`."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.seconds = 0.0
        self.views = 0

    def synthesize(self, requests):
        start = time.perf_counter()
        out = super().synthesize(requests)
        self.seconds += time.perf_counter() - start
        self.views += sum(len(o) for o in out)
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=int, default=50)
    parser.add_argument("--k", type=int, default=30)
    parser.add_argument("--sets-per-bin", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    model = Pix2VoxPlusPlus(preset="tiny", validation_fscore=False)
    dm = VTRDataModule(image_size=model.image_size)
    records = dm.split_records("test")
    records += [r for split in ("val", "train") for r in dm.split_records(split)]
    records = records[: args.objects]
    synthesizer = TimedRenderSynthesizer(image_size=model.image_size)
    synthesizer.synthesize([])  # nothing rendered; the GL context starts on the first real call

    start = time.perf_counter()
    rmap = robustness_map(
        model, records, k=args.k, sets_per_bin=args.sets_per_bin, synthesizer=synthesizer, transform=dm.transform
    )
    total = time.perf_counter() - start
    sets = rmap.num_objects * rmap.num_bins * args.sets_per_bin
    print(
        f"{rmap.num_objects} objects x {rmap.num_bins} bins (K = {args.k}) x {args.sets_per_bin} set(s) of "
        f"{rmap.views_per_set} views: {synthesizer.views} views rendered, {sets} sets predicted"
    )
    print(f"total {total:.1f} s, {rmap.num_objects / total:.3f} objects/s (target: 50 objects in 180 s)")
    print(
        f"rendering {synthesizer.seconds:.1f} s ({synthesizer.views / max(synthesizer.seconds, 1e-9):.1f} views/s), "
        f"the rest {total - synthesizer.seconds:.1f} s; mean IoU over the sphere {rmap.overall():.3f}"
    )


if __name__ == "__main__":
    main()
