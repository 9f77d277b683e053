"""A run with ErrorGuidedViewAugmentation interrupted after epoch 2 and resumed to epoch 4 ends with exactly the
weights and optimizer state of an uninterrupted 4-epoch run (tiny Pix2Vox++, mesh rendering, CPU)."""

from __future__ import annotations

import pytest
import torch
from helpers import assert_same_training_state, fit_pix2vox, one_thread

_one_thread = pytest.fixture(autouse=True)(one_thread)


def _placed(entries: list[dict]) -> list[dict]:
    """The index entries without the folder they were written to."""
    return [{k: v for k, v in e.items() if k != "root"} for e in entries]


@pytest.mark.slow
def test_resume_restores_weights_and_optimizer_state(tiny_dataset, pix2vox_run_4_epochs, tmp_path):
    full, _ = pix2vox_run_4_epochs  # fit_pix2vox(tiny_dataset, ..., epochs=4), shared with the kill test
    part = fit_pix2vox(tiny_dataset, tmp_path / "part", epochs=2)
    # the run ended on its last epoch, which generates nothing: the resume catches up the generation of epoch 1
    assert [s["epoch"] for s in part.datamodule.generated_samples] == [-1] * 3 + [0] * 3
    last = tmp_path / "part" / "ckpt" / "last.ckpt"
    interrupted = torch.load(last, map_location="cpu", weights_only=False)["state_dict"]
    resumed = fit_pix2vox(tiny_dataset, tmp_path / "part", epochs=4, ckpt_path=str(last))
    # epochs 2 and 3 trained after the resume
    after = resumed.lightning_module.state_dict()
    assert not torch.equal(interrupted["encoder.backbone.0.weight"], after["encoder.backbone.0.weight"])

    # the resumed run trained on what the uninterrupted one did: the same generated samples, epoch by epoch
    assert [s["epoch"] for s in resumed.datamodule.generated_samples] == [-1] * 3 + [0] * 3 + [1] * 3 + [2] * 3
    # (each entry's "root" names the folder its run wrote it to: the two runs write to their own)
    assert _placed(resumed.datamodule.generated_samples) == _placed(full.datamodule.generated_samples)
    assert {s["root"] for s in resumed.datamodule.generated_samples} == {str((tmp_path / "part" / "gen").absolute())}
    assert resumed.global_step == full.global_step == 4 * 2
    assert_same_training_state(resumed, full)
