"""A line per training epoch on the console, and a switch for Lightning's promotional tips.

Long runs with the progress bar off (or output going to a log file) print nothing for minutes between
epochs. :class:`EpochSummary` prints one line at each epoch's end: the epoch, the mean training loss, the
validation IoU and the time. :func:`silence_lightning_tips` drops the "💡 Tip" lines Lightning 2.6 prints
for every Trainer (cloud logging and model-registry advertisements).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from typing import IO, Any

import lightning as L
from lightning.pytorch.utilities import rank_zero_only
from torch import Tensor

from lightning_vtr.utils.validation import check_type

__all__ = ["EpochSummary", "LightningTipFilter", "silence_lightning_tips"]

#: The logger Lightning's ``rank_zero_info`` writes to once ``lightning.pytorch`` is imported; the tips of
#: ``logger_connector.configure_logger`` and ``callback_connector._maybe_show_litmodels_tip`` go through it.
_RANK_ZERO_LOGGER = "lightning.pytorch.utilities.rank_zero"


class LightningTipFilter(logging.Filter):
    """A :class:`logging.Filter` that drops Lightning's promotional "💡 Tip: ..." records and keeps the rest."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.msg if isinstance(record.msg, str) else ""
        return not message.lstrip().startswith("💡 Tip")


def silence_lightning_tips() -> None:
    """Stop Lightning from printing its "💡 Tip" advertisements (litlogger, litmodels) for every Trainer.

    Lightning has no switch for them: they are ``rank_zero_info`` records of the
    ``lightning.pytorch.utilities.rank_zero`` logger. This adds :class:`LightningTipFilter` to that logger
    (once; calling again changes nothing), so every other message of Lightning still shows. The harness in
    :mod:`lightning_vtr.experiments.training` calls it when it builds a Trainer; importing the package does
    not. To silence them in a script of your own::

        from lightning_vtr.utils.feedback import silence_lightning_tips

        silence_lightning_tips()
    """
    logger = logging.getLogger(_RANK_ZERO_LOGGER)
    if not any(isinstance(f, LightningTipFilter) for f in logger.filters):
        logger.addFilter(LightningTipFilter())


def _scalar(value: Any) -> float | None:
    if isinstance(value, Tensor):
        value = value.detach()
        return float(value.float().mean().item()) if value.numel() else None
    if isinstance(value, (int, float)):
        return float(value)
    return None


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


class EpochSummary(L.Callback):
    """Print one line per training epoch (global rank 0 only), e.g.::

        epoch 3/12  train loss 0.4123  val/iou@0.4 0.3521  21.4 s (total 1:25)

    The training loss is the mean of the losses the training steps returned in the epoch (not only the last
    one); the validation value is ``trainer.callback_metrics[monitor]`` when the model logged it that epoch
    (``val/iou@0.4`` for the package's models) and is left out otherwise (no validation that epoch, or another
    metric name). The time is the epoch's wall time from
    its start to its end hook, validation and the augmentation callback's generation included when they run
    before this callback's hook.

    Args:
        monitor: the logged metric to show, or ``None`` for none.
        stream: where the lines go (default ``sys.stdout`` at print time).

    Example::

        trainer = L.Trainer(max_epochs=10, callbacks=[EpochSummary()], enable_progress_bar=False)
    """

    def __init__(self, monitor: str | None = "val/iou@0.4", stream: IO[str] | None = None) -> None:
        if monitor is not None:
            check_type("monitor", monitor, str, "metric name (str) or None")
        self.monitor = monitor
        self.stream = stream
        self._losses: list[float] = []
        self._validated = False
        self._epoch_start: float | None = None
        self._fit_start: float | None = None

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._fit_start = time.perf_counter()

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._losses = []
        self._validated = False
        self._epoch_start = time.perf_counter()

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.sanity_checking:
            self._validated = True

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        value = _scalar(loss)
        if value is not None and math.isfinite(value):
            self._losses.append(value)

    def line(self, trainer: L.Trainer) -> str:
        """The line of the epoch that just ended (what :meth:`on_train_epoch_end` prints)."""
        now = time.perf_counter()
        epochs = f"/{trainer.max_epochs}" if trainer.max_epochs is not None and trainer.max_epochs >= 0 else ""
        parts = [f"epoch {trainer.current_epoch}{epochs}"]
        if self._losses:
            parts.append(f"train loss {sum(self._losses) / len(self._losses):.4f}")
        value = _scalar(trainer.callback_metrics.get(self.monitor)) if self.monitor and self._validated else None
        if value is not None:
            parts.append(f"{self.monitor} {value:.4f}")
        timing = f"{now - self._epoch_start:.1f} s" if self._epoch_start is not None else ""
        if self._fit_start is not None:
            timing += f" (total {_duration(now - self._fit_start)})"
        if timing:
            parts.append(timing.strip())
        return "  ".join(parts)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        self._print(self.line(trainer))

    @rank_zero_only
    def _print(self, text: str) -> None:
        print(text, file=self.stream or sys.stdout, flush=True)
