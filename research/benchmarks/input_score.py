"""Cost of the input-side research score, ``ErrorGuidedSelector(score=InputScore())``, against ``visible``.

Run from the repository root: ``python -m research.benchmarks.input_score`` (options: ``--objects``, ``--k``, ``--threads``, ``--repeats``).
On the embedded dataset's first training objects and tiny Pix2Vox++ (random weights: the cost does not depend
on them), it times one selection per object as the callback makes it: every bin centre rendered from the mesh
(the callback's default synthesizer), turned into model input, predicted from alone, and scored by the loss.
It prints objects per second with the share of rendering, input transform and prediction, and, in the same
run, objects per second of the ``visible`` score on the same objects' predictions from their Aligned views.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.experiments.training import ExperimentConfig, make_datamodule, make_model
from lightning_vtr.selection import ErrorGuidedSelector
from research.scores import InputScore


class _Timed:
    """Wraps a callable and adds its wall time to ``seconds``."""

    def __init__(self, fn):
        self.fn, self.seconds = fn, 0.0

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--objects", type=int, default=8, help="training objects selected per repeat")
    parser.add_argument("--k", type=int, default=30, help="bin interval K in degrees (30: 72 candidate views)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    config = ExperimentConfig(seed=0)
    model = make_model(config).eval()
    dm = make_datamodule(config, model)
    dm.prepare_data()
    dm.setup("fit")
    records = dm.split_records("train")[: args.objects]
    items = [dm.eval_item(r, "aligned", seed=1) for r in records]
    target = torch.stack([it["voxels"] for it in items])
    with torch.no_grad():
        predicted = model.predict_voxels(torch.stack([it["images"] for it in items]))

    selector = ErrorGuidedSelector(k=args.k, score=InputScore(), min_separation=30.0, temperature=1.0)
    callback = ErrorGuidedViewAugmentation(selector=selector, progress_bar=False)
    render = _Timed(callback.synthesizer.synthesize)
    callback.synthesizer.synthesize = render
    transform = _Timed(dm.transform)
    predict = _Timed(model.predict_voxels)
    model.predict_voxels = predict  # an instance attribute: the selector's calls go through the timer

    class _Trainer:  # the one attribute the callback's context reads
        datamodule = dm

    # the first call opens the renderer's GL context: not part of a selection's cost
    callback.synthesizer.synthesize([callback._request(dm, records[0], torch.zeros(1, 2))])
    render.seconds = 0.0

    times = []
    for repeat in range(args.repeats):
        start = time.perf_counter()
        for row, record in enumerate(records):
            context = callback._context(_Trainer, model, [callback._request(dm, record)])
            context.transform = transform
            selector.select(
                predicted[row : row + 1],
                target[row : row + 1],
                [record.category],
                generator=torch.Generator().manual_seed(repeat),
                context=context,
            )
        times.append(time.perf_counter() - start)
    total = sum(times)
    n_views = selector.candidates.shape[0]
    print(f"score='input', K = {args.k} ({n_views} views per object), {args.threads} torch thread(s), tiny Pix2Vox++:")
    print(
        f"  {args.objects / statistics.median(times):.2f} objects/s (median of {args.repeats} x {args.objects} objects; "
        f"{n_views * args.objects / statistics.median(times):.0f} candidate views/s)"
    )
    print(
        f"  rendering {100 * render.seconds / total:.0f} %, input transform {100 * transform.seconds / total:.0f} %, "
        f"prediction {100 * predict.seconds / total:.0f} %, the rest {100 * (1 - (render.seconds + transform.seconds + predict.seconds) / total):.0f} %"
    )

    visible = ErrorGuidedSelector(k=args.k, score="visible", min_separation=30.0, temperature=1.0)
    times = []
    for repeat in range(args.repeats):
        start = time.perf_counter()
        visible.select(
            predicted, target, [r.category for r in records], generator=torch.Generator().manual_seed(repeat)
        )
        times.append(time.perf_counter() - start)
    print(f"score='visible' on the same objects: {args.objects / statistics.median(times):.0f} objects/s")


if __name__ == "__main__":
    main()
