"""The paper-style robustness table (Table 1 layout) and the conversion from ``trainer.test`` output.

Results are nested dicts ``{method: {view_set: {metric: value in [0, 1]}}}``; the table prints
them in percent with rows = methods and columns = Aligned / Hemispherical / Spherical x metrics.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.validation import check_choice

__all__ = [
    "BEST_IOU",
    "TABLE_FORMATS",
    "VIEW_SET_TITLES",
    "best_threshold_iou",
    "format_cell",
    "format_robustness_table",
    "results_from_test_output",
]

#: Printed titles of the view sets, the table's column groups (in the paper's order, :data:`VIEW_SETS`).
VIEW_SET_TITLES: dict[str, str] = {name: name.capitalize() for name in VIEW_SETS}
#: Output formats of :func:`format_robustness_table`.
TABLE_FORMATS = ("markdown", "text")
#: Name of the derived metric :func:`best_threshold_iou` (the IoU VTR's test script prints).
BEST_IOU = "iou_best"
_METRIC_TITLES = {"fscore": "F-score", BEST_IOU: "best mIoU"}


def _metric_title(name: str) -> str:
    if name.startswith("iou@"):
        return "mIoU" if name == "iou@0.4" else f"mIoU@{name[4:]}"
    return _METRIC_TITLES.get(name, name)


def best_threshold_iou(metrics: Mapping[str, float]) -> float | None:
    """The best-threshold mIoU of one view set: the largest of its ``iou@<t>`` values, ``None`` without any.

    Each logged ``iou@<t>`` is a mean over the test objects at threshold ``t``, so their maximum is the
    number VTR's test script prints ("the IoU score": the maximum over thresholds of the mean IoU, one
    threshold for the whole set), not the mean of per-object maxima
    (:func:`~lightning_vtr.metrics.voxel_iou_best` computes it from volumes).

    Example:
        >>> best_threshold_iou({"iou@0.3": 0.41, "iou@0.4": 0.43, "iou@0.5": 0.40, "fscore": 0.2})
        0.43
    """
    values = [float(v) for k, v in metrics.items() if k.startswith("iou@") and not math.isnan(float(v))]
    return max(values) if values else None


def results_from_test_output(outputs: Iterable[Mapping[str, float]], method: str | None = None) -> dict:
    """Collect ``test/<set>/<metric>`` keys of ``trainer.test(...)`` output into a nested dict.

    Args:
        outputs: the list of dicts ``trainer.test`` returns (one per test dataloader; they are
            merged). Per-category keys ``test/<set>/<category>/<metric>`` are kept under
            ``"<set>/<category>"``; other keys are ignored.
        method: when given, wrap the result as ``{method: ...}``, ready for
            :func:`format_robustness_table`.

    Returns:
        ``{view_set: {metric: value}}`` (or ``{method: {view_set: {metric: value}}}``).
    """
    results: dict[str, dict[str, float]] = {}
    for output in outputs:
        for key, value in output.items():
            parts = key.split("/")
            if len(parts) < 3 or parts[0] != "test":
                continue
            group, metric = "/".join(parts[1:-1]), parts[-1]
            results.setdefault(group, {})[metric] = float(value)
    return {method: results} if method is not None else results


def format_cell(value: float | None, std: float | None = None, *, digits: int = 2) -> str:
    """One table cell in percent: ``"64.63"``, ``"60.00 ± 14.14"`` with a spread, ``"-"`` for a missing value.

    Args:
        value: a fraction in ``[0, 1]`` (a mean over seeds, say); ``None`` or NaN print ``-``.
        std: its spread, also a fraction; ``None`` or NaN print the value alone.
        digits: decimals of the percentages.

    Example:
        >>> format_cell(0.6), format_cell(0.6, 0.1414), format_cell(float("nan"), 0.1)
        ('60.00', '60.00 ± 14.14', '-')
    """
    if value is None or _missing(value):
        return "-"
    text = f"{100 * value:.{digits}f}"
    return text if std is None or _missing(std) else f"{text} ± {100 * std:.{digits}f}"


def _missing(value: float | None) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def format_robustness_table(
    results: Mapping[str, Mapping[str, Mapping[str, float]]],
    *,
    std: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None,
    metric_names: Sequence[str] = ("iou@0.4", "fscore"),
    fmt: str = "markdown",
    view_sets: Sequence[str] = VIEW_SETS,
    digits: int = 2,
) -> str:
    """Format ``{method: {view_set: {metric: value}}}`` like the paper's Table 1, values in %.

    Missing values print as ``-``; each cell is :func:`format_cell` of its value (and spread).

    Args:
        results: values in ``[0, 1]`` per method, view set and metric (e.g. ``iou@0.4``, ``fscore``);
            means, when ``std`` is given.
        std: spreads in the same layout (e.g. the sample standard deviation over seeds); a cell with
            one prints ``mean ± std``, a cell without one the mean alone.
        metric_names: metrics shown under each view set, in order.
        fmt: ``"markdown"`` (a pipe table) or ``"text"`` (aligned columns).
        view_sets: the column groups, in order.
        digits: decimals of the percentages.

    Returns:
        The table as a string without a trailing newline.

    Raises:
        ValueError: if ``fmt`` is unknown.

    Example:
        >>> print(format_robustness_table({"Pix2Vox++": {"aligned": {"iou@0.4": 0.6463, "fscore": 0.4202}}},
        ...                               view_sets=("aligned",)))
        | Method | Aligned mIoU | Aligned F-score |
        |---|---|---|
        | Pix2Vox++ | 64.63 | 42.02 |
    """
    check_choice("fmt", fmt, TABLE_FORMATS)
    spreads = std or {}

    def cells(method: str, per_set: Mapping[str, Mapping[str, float]]) -> list[str]:
        spread = spreads.get(method, {})
        return [
            format_cell(per_set.get(s, {}).get(m), spread.get(s, {}).get(m), digits=digits)
            for s in view_sets
            for m in metric_names
        ]

    header = ["Method"] + [f"{VIEW_SET_TITLES.get(s, s)} {_metric_title(m)}" for s in view_sets for m in metric_names]
    rows = [[method, *cells(method, per_set)] for method, per_set in results.items()]
    if fmt == "markdown":
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(row) + " |" for row in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(row: list[str]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))).rstrip()

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *[line(r) for r in rows]])
