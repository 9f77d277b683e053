"""Where the report's time went: seconds per stage of the pretrainings, fine-tunings and tests, from the
:class:`~lightning_vtr.experiments.training.StageTimer` measurements cached with each run, and their tables.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from lightning_vtr.experiments.output_files import REPORT_TIMING, read_output_json
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.experiments.report_run import write_json

__all__ = ["finite_or_none", "record_invocation", "time_split", "time_tables"]


_FIT_STAGES = (
    ("training steps", "train_steps"),
    ("data loading", "train_data"),
    ("validation", "validation"),
    ("selection + synthesis", "augmentation"),
    ("other (setup, checkpoints)", "fit_other"),
)
"""Rows of the time split: (label, where the seconds come from)."""
_TEST_STAGES = (("model", "test_steps"), ("data loading", "test_data"))


def _stage(timing: dict | None, key: str, fallback: float | None = None) -> float:
    if timing and key in timing:
        return float(timing[key])
    return math.nan if fallback is None else float(fallback)


def time_split(
    runs: list[ReportRun], payloads: dict[str, dict[int, dict]], pretraining: dict[int, dict | None], seeds: list[int]
) -> dict[str, Any]:
    """Seconds per stage, summed over seeds: pretraining, fine-tuning and testing (with their parts), and per
    run the mean per seed. Missing measurements (runs cached by an older version) are NaN."""

    def total(values: list[float]) -> float:
        return math.fsum(values) if values and all(math.isfinite(v) for v in values) else math.nan

    def mean(values: list[float]) -> float:
        return total(values) / len(values) if values else math.nan

    split: dict[str, Any] = {"pretraining": {}, "fine_tuning": {}, "testing": {}, "per_run": {}}
    pre = [(pretraining.get(s) or {}).get("seconds") for s in seeds]
    split["pretraining"]["total"] = total([_stage(t, "fit") for t in pre])
    for _, key in _FIT_STAGES:
        split["pretraining"][key] = total([_stage(t, key) for t in pre])
    fitted = [r for r in runs if r.fitted]
    fine = {r.name: [payloads[r.name][s] for s in seeds] for r in fitted}
    split["fine_tuning"]["total"] = total([p.get("train_seconds", math.nan) for ps in fine.values() for p in ps])
    for _, key in _FIT_STAGES:
        split["fine_tuning"][key] = total([_stage(p.get("timing"), key) for ps in fine.values() for p in ps])
    tested = [payloads[r.name][s] for r in runs if r.same_as is None for s in seeds]
    split["testing"]["total"] = total([_stage(p.get("timing"), "test", p.get("eval_seconds")) for p in tested])
    for _, key in _TEST_STAGES:
        split["testing"][key] = total([_stage(p.get("timing"), key) for p in tested])
    for run in runs:
        ps = [payloads[run.name][s] for s in seeds]
        split["per_run"][run.name] = {
            "fine_tuning": mean([p.get("train_seconds", math.nan) for p in ps]),
            **{key: mean([_stage(p.get("timing"), key) for p in ps]) for _, key in _FIT_STAGES},
            "testing": mean([_stage(p.get("timing"), "test", p.get("eval_seconds")) for p in ps]),
        }
        if run.single_view_of is not None:  # no fit of its own
            split["per_run"][run.name].update(
                dict.fromkeys(("fine_tuning", *(key for _, key in _FIT_STAGES)), math.nan)
            )
        if run.same_as is not None:  # counted once, under the run it repeats
            split["per_run"][run.name] = dict.fromkeys(split["per_run"][run.name], math.nan)
    split["measured"] = math.fsum(
        v for v in (split[k]["total"] for k in ("pretraining", "fine_tuning", "testing")) if math.isfinite(v)
    )
    return split


def finite_or_none(value: Any) -> Any:
    """``value`` with every NaN float replaced by ``None`` (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    return None if isinstance(value, float) and math.isnan(value) else value


def _seconds(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.1f}"


def time_tables(split: dict[str, Any], runs: list[ReportRun], seeds: list[int]) -> str:
    measured = split["measured"]

    def share(value: float) -> str:
        return f"{100 * value / measured:.1f}" if math.isfinite(value) and measured > 0 else "-"

    lines = ["| Stage | Seconds | Share (%) |", "|---|---|---|"]
    for stage, title, parts in (
        ("pretraining", "Pretraining", _FIT_STAGES),
        ("fine_tuning", "Fine-tuning", _FIT_STAGES),
        ("testing", "Testing", _TEST_STAGES),
    ):
        value = split[stage]["total"]
        lines.append(f"| {title} | {_seconds(value)} | {share(value)} |")
        for label, key in parts:
            if stage == "pretraining" and key == "augmentation":
                continue
            value = split[stage][key]
            lines.append(f"| &nbsp;&nbsp;{label} | {_seconds(value)} | {share(value)} |")
    lines.append(f"| Measured in all | {_seconds(measured)} | 100.0 |")
    per_seed = " per seed" if len(seeds) > 1 else ""
    header = ["Run", f"Fine-tuning (s{per_seed})", *(label for label, _ in _FIT_STAGES), f"Testing (s{per_seed})"]
    lines += ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for run in runs:
        row = split["per_run"][run.name]
        name = run.name if run.same_as is None else f"{run.name} (= {run.same_as}, fitted once)"
        cells = [name, _seconds(row["fine_tuning"]), *(_seconds(row[key]) for _, key in _FIT_STAGES)]
        lines.append("| " + " | ".join([*cells, _seconds(row["testing"])]) + " |")
    return "\n".join(lines)


def record_invocation(path: Path, wall: float, split: dict[str, Any]) -> dict[str, Any]:
    """Add this invocation's wall time and the current split to ``timing.json``.

    Args:
        path: the report's ``timing.json`` (created when missing).
        wall: this invocation's wall time, seconds.
        split: :func:`time_split`'s seconds per stage.

    Returns:
        The file's content: ``{"invocations": [seconds, ...], "split": split with NaN as None}``.
    """
    timing = read_output_json(
        path, REPORT_TIMING, f"delete that file ({path}) to start its record of wall times afresh"
    )
    timing = timing or {"invocations": []}
    timing["invocations"].append(wall)
    timing["split"] = finite_or_none(split)
    write_json(path, timing)
    return timing
