"""Zero-1-to-3's float16 path (the CUDA default) on the CPU, with and without CUDA autocast's casting rules."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from cuda_autocast import cuda_autocast_rules
from helpers import one_thread

from lightning_vtr.synthesis.zero123 import Zero123Synthesizer

_one_thread = pytest.fixture(autouse=True)(one_thread)


@pytest.mark.parametrize("autocast", [False, True], ids=["fp16-weights", "fp16-weights-under-16-mixed"])
def test_zero123_float16_path_under_cuda_rules(tiny_zero123, monkeypatch, autocast):
    synth = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, num_inference_steps=2, image_size=32)
    image = np.zeros((48, 48, 4), dtype=np.uint8)
    image[10:30, 14:40] = (200, 40, 40, 255)
    args = ([image], torch.zeros(1, 2), torch.tensor([[30.0, 0.0]]))
    expected = synth(*args, output_type="pt")
    # the CUDA default (float16 modules), which the synthesizer refuses on a CPU device: placed here on the CPU
    monkeypatch.setattr(synth, "_resolve_placement", lambda: (torch.device("cpu"), torch.float16))
    if autocast:
        with cuda_autocast_rules(torch.float16):
            out = synth(*args, output_type="pt")
    else:
        out = synth(*args, output_type="pt")
    assert next(synth.unet.parameters()).dtype == torch.float16
    assert out.dtype == torch.float32 and out.shape == expected.shape == (1, 3, 64, 64)
    assert torch.isfinite(out).all() and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    # the same sampling in float16: the decoded image within a few float16 roundings of float32's per step
    assert float((out - expected).abs().mean()) < 0.02
