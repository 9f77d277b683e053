"""The report's viewpoint robustness maps (``ReportConfig.maps``): the map of each strategy's final model.

For every seed and fitted run, :func:`~lightning_vtr.evaluation.robustness.robustness_map` (what
``lightning-vtr robustness`` measures) tests the run's final weights on view sets drawn around every bin of the
``map_k``-degree grid, on ``map_objects`` test objects spread over the categories, the same objects and view sets
for every strategy of the seed. Each map is cached in ``seed_<s>/<run>/robustness_map/``. A row's map pools its
seeds: its objects are every seed's objects (``seed_<s>/<object_id>``), so its per-bin mean is the mean over seeds
of each seed's per-bin mean.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning_vtr.experiments import training
from lightning_vtr.experiments.report_config import ReportConfig
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.utils.paths import join_under

__all__ = ["MAP_DIR", "run_map", "strategy_maps", "write_maps"]

MAP_DIR = "robustness_map"
"""The folder of a run's cached map, under ``seed_<s>/<run>/``."""


def _device(config: ReportConfig) -> str:
    import torch

    accelerator = config.experiment.accelerator
    return "cuda" if accelerator in ("auto", "gpu", "cuda") and torch.cuda.is_available() else "cpu"


def run_map(config: ReportConfig, seed: int, run: str) -> Any:
    """The robustness map of one run's final weights (``seed_<s>/<run>/checkpoints/last.ckpt``), cached.

    Args:
        config: the report (its experiment, ``map_k``, ``map_objects`` and synthesizer).
        seed: the seed; it also draws the view sets, so every run of a seed gets the same ones.
        run: the run's name (a fitted run).

    Returns:
        A :class:`~lightning_vtr.evaluation.robustness.RobustnessMap`; a cache measured with another ``map_k`` or
        ``map_objects`` is measured again.
    """
    from lightning_vtr.evaluation.robustness import META_FILE, RobustnessMap, robustness_map
    from lightning_vtr.evaluation.robustness_callback import ObjectSubset

    seed_exp = config.seed_config(seed)
    run_dir = join_under(seed_exp.out, run)
    cache = join_under(run_dir, MAP_DIR)
    if (cache / META_FILE).is_file():
        cached = RobustnessMap.from_csv(cache)
        if cached.k == config.map_k and cached.extra.get("map_objects") == config.map_objects:
            return cached
    model = training.load_run_model(seed_exp, run_dir).to(_device(config))
    dm = training.make_datamodule(seed_exp, model)
    rmap = robustness_map(
        model,
        ObjectSubset.spread(dm, "test", config.map_objects),
        k=config.map_k,
        seed=seed,
        synthesizer=config.synthesizer,
        progress=False,
    )
    rmap.extra.update(run=run, seed=seed, map_objects=config.map_objects)
    rmap.to_csv(cache, per_category=True)  # robustness.json, written last, marks a whole cache
    return rmap


def strategy_maps(config: ReportConfig, rows: dict[str, str], runs: list[ReportRun]) -> dict[str, Any]:
    """Each row's map, pooled over the seeds.

    Args:
        config: the report.
        rows: row title -> run name.
        runs: the plan (a run fitted once for two rows is measured once).

    Returns:
        ``{row title: RobustnessMap}`` whose objects are every seed's objects, named ``seed_<s>/<object_id>``.
    """
    import numpy as np

    from lightning_vtr.evaluation.robustness import RobustnessMap

    source = {run.name: run.same_as or run.name for run in runs}
    out = {}
    for title, run in rows.items():
        per_seed = {seed: run_map(config, seed, source.get(run, run)) for seed in config.seeds}
        first = next(iter(per_seed.values()))
        out[title] = RobustnessMap.from_iou(
            np.concatenate([m.iou for m in per_seed.values()]),
            k=first.k,
            object_ids=[f"seed_{s}/{o}" for s, m in per_seed.items() for o in m.object_ids],
            categories=[c for m in per_seed.values() for c in m.categories],
            threshold=first.threshold,
            views_per_set=first.views_per_set,
            sets_per_bin=first.sets_per_bin,
            seed=first.seed,
            aligned_pitch=first.aligned_pitch,
            extra={"run": run, "seeds": list(per_seed)},
        )
    return out


def write_maps(out: Path, maps: dict[str, Any], reference: str | None) -> dict[str, Any]:
    """Write ``out/maps/``: per row ``<title>.png`` (one colour scale for all), ``<title>/`` (its ``bins.csv``,
    ``objects.csv``, ``robustness.json``), with ``reference`` every other row's difference map to it, and
    ``index.html`` last.

    Args:
        out: the report's folder.
        maps: row title -> pooled map (:func:`strategy_maps`).
        reference: the row title the difference maps subtract (``None``: none).

    Returns:
        ``{row title: {"overall": area-weighted mean IoU over the sphere, "objects": count, "k": bin interval,
        "picture": the PNG's path relative to out, "folder": the CSV folder's}}``.
    """
    from lightning_vtr.evaluation.robustness_plot import map_file_stem, write_index_html

    folder = join_under(out, "maps")
    summary = {}
    for title, rmap in maps.items():
        stem = map_file_stem(title)
        rmap.to_csv(join_under(folder, stem), per_category=True)
        summary[title] = {
            "overall": rmap.overall(),
            "objects": rmap.num_objects,
            "k": rmap.k,
            "picture": f"maps/{stem}.png",
            "folder": f"maps/{stem}",
        }
    write_index_html(
        folder,
        maps,
        reference=reference if reference in maps else None,
        title="Viewpoint robustness of each strategy's final model",
    )
    return summary
