"""A line per epoch (epoch, mean train loss, val IoU, time), and Lightning's tips filtered out."""

from __future__ import annotations

import io
import logging
import re

import lightning as L
import pytest
import torch
from lightning.pytorch.utilities import rank_zero_info
from torch import nn

from lightning_vtr.utils.feedback import EpochSummary, LightningTipFilter, silence_lightning_tips


class _KnownLosses(L.LightningModule):
    """Training losses 1, 3 in every epoch (mean 2); validation logs val/iou@0.4 = 0.25 (0.5 in epoch 1)."""

    def __init__(self):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(()))

    def training_step(self, batch, batch_idx):
        return self.w * 0 + (1.0 + 2.0 * batch_idx)

    def validation_step(self, batch, batch_idx):
        self.log("val/iou@0.4", 0.25 * (1 + self.current_epoch))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.0)


def _loader(n=2):
    return torch.utils.data.DataLoader(torch.zeros(n, 1), batch_size=1)


def _fit(tmp_path, summary, **kw):
    trainer = L.Trainer(
        max_epochs=2,
        default_root_dir=tmp_path,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=1,
        callbacks=[summary],
        **kw,
    )
    trainer.fit(_KnownLosses(), _loader(), _loader(1))


def test_one_line_per_epoch_with_mean_loss_validation_iou_and_time(tmp_path):
    stream = io.StringIO()
    _fit(tmp_path, EpochSummary(stream=stream))
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2  # none for the sanity check
    pattern = r"epoch {e}/2  train loss 2\.0000  val/iou@0\.4 {v}  \d+\.\d s \(total 0:\d\d\)"
    assert re.fullmatch(pattern.format(e=0, v=r"0\.2500"), lines[0]), lines[0]
    assert re.fullmatch(pattern.format(e=1, v=r"0\.5000"), lines[1]), lines[1]


def test_an_epoch_without_validation_shows_no_stale_value(tmp_path):
    stream = io.StringIO()
    _fit(tmp_path, EpochSummary(stream=stream), check_val_every_n_epoch=2)
    first, second = stream.getvalue().splitlines()
    assert "val/" not in first and "val/iou@0.4 0.5000" in second
    with pytest.raises(TypeError, match="`monitor` must be a metric name"):
        EpochSummary(monitor=3)


@pytest.fixture
def rank_zero_records():
    """Records reaching Lightning's rank-zero logger (after its filters), and the filters restored afterwards."""
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    filters, level = list(logger.filters), logger.level
    seen: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            seen.append(record.getMessage())

    handler = Keep(level=logging.INFO)
    # start unsilenced whatever ran before (the harness silences the tips for the whole process)
    logger.filters[:] = [f for f in filters if not isinstance(f, LightningTipFilter)]
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield seen
    logger.removeHandler(handler)
    logger.filters[:] = filters
    logger.setLevel(level)


def test_silence_lightning_tips_drops_only_the_tips(rank_zero_records):
    silence_lightning_tips()
    silence_lightning_tips()  # idempotent
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    assert sum(isinstance(f, LightningTipFilter) for f in logger.filters) == 1
    rank_zero_info("💡 Tip: For seamless cloud logging ...")
    rank_zero_info("GPU available: False, used: False")
    assert rank_zero_records == ["GPU available: False, used: False"]


def test_a_trainer_built_after_silencing_prints_no_tip(rank_zero_records):
    L.Trainer(logger=False, enable_progress_bar=False)
    assert any(m.startswith("💡 Tip") for m in rank_zero_records)  # Lightning 2.6 prints one per Trainer ...
    rank_zero_records.clear()
    silence_lightning_tips()
    L.Trainer(logger=False, enable_progress_bar=False)
    assert rank_zero_records and not any("Tip" in m for m in rank_zero_records)  # ... and none once silenced
