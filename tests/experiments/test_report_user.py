"""``lightning-vtr report`` as a new user meets it with a model and a selector of their own: the model's arguments
(``--model-arg``), ``--no-progress``, the settings of a selector without ``settings()`` in ``report.json``, one
seed's tables and wording, and an ``equivalent_command`` that re-runs the same configuration."""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
import textwrap

import pytest
import torch
from helpers import USER_SELECTOR_SOURCE, one_thread

from lightning_vtr.cli import main
from lightning_vtr.cli.report import add_arguments, report_config
from lightning_vtr.errors import UsageError
from lightning_vtr.experiments import training
from lightning_vtr.experiments.flags import key_values
from lightning_vtr.experiments.report_render import equivalent_command

_one_thread = pytest.fixture(autouse=True)(one_thread)

#: ``sizednet.py``: a model whose input size is a constructor argument, and refuses any other size.
MODEL_SOURCE = textwrap.dedent(
    """
    import lightning as L
    import torch
    import torch.nn.functional as F
    from torch import nn


    class SizedNet(L.LightningModule):
        def __init__(self, image_size: int = 32, width: int = 8, num_views: int = 3, voxel_resolution: int = 32):
            super().__init__()
            self.image_size, self.num_views, self.voxel_resolution = image_size, num_views, voxel_resolution
            self.colour = nn.Linear(3, width)
            self.grid = nn.Parameter(torch.zeros(width, voxel_resolution, voxel_resolution, voxel_resolution))

        def predict_voxels(self, images):
            if images.shape[-1] != self.image_size:
                raise ValueError(f"SizedNet takes {self.image_size}-px images, got {images.shape[-1]}")
            weights = torch.softmax(self.colour(images.mean(dim=(1, 3, 4))), dim=-1)
            return torch.sigmoid(torch.einsum("bk,kxyz->bxyz", weights, self.grid))

        def training_step(self, batch, batch_idx):
            return F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"])

        def configure_optimizers(self):
            return torch.optim.Adam(self.parameters(), lr=0.01)
    """
)
#: ``sideviews.py``: a selector with no ``settings()`` of its own.
SELECTOR_SOURCE = USER_SELECTOR_SOURCE
ROWS = textwrap.dedent(
    """
    side:
      title: Side views
      description: three fixed side views
      selector: {class_path: sideviews.SideViews, init_args: {pitch: 20.0}}
      callback_kwargs: {fraction: 0.15}
    """
)


@pytest.fixture
def user_folder(tmp_path, monkeypatch):
    """The current folder holds ``sizednet.py``, ``sideviews.py`` and ``rows.yaml``; the modules are forgotten after."""
    (tmp_path / "sizednet.py").write_text(MODEL_SOURCE)
    (tmp_path / "sideviews.py").write_text(SELECTOR_SOURCE)
    (tmp_path / "rows.yaml").write_text(ROWS)
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    for name in ("sizednet", "sideviews"):
        sys.modules.pop(name, None)
    while str(tmp_path) in sys.path:
        sys.path.remove(str(tmp_path))


def _config(argv: list[str]):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return report_config(parser.parse_args(argv), command="lightning-vtr report")


def test_model_args_and_no_progress_reach_the_experiment_and_its_trainers(user_folder, tmp_path):
    argv = ["--model", "sizednet.SizedNet", "--model-arg", "image_size=64", "--model-arg", "width=4"]
    config = _config([*argv, "--model-arg", "num_views=3", "--no-progress", "--jobs", "1"])
    assert config.experiment.model_kwargs == {"image_size": 64, "width": 4, "num_views": 3}  # YAML values: ints
    assert key_values(["widths=[8, 16]", "name=small", "on=true"], "--model-arg") == {
        "widths": [8, 16],
        "name": "small",
        "on": True,
    }
    assert config.experiment.trainer_kwargs == {"enable_progress_bar": False}
    trainer = training._trainer(config.experiment, tmp_path / "run", 1)
    assert trainer.progress_bar_callback is None  # no fit bar, so the callback's synthesis bar stays off too
    assert _config(["--jobs", "1"]).experiment.trainer_kwargs == {}
    assert training._trainer(_config(["--jobs", "1"]).experiment, tmp_path / "run", 1).progress_bar_callback is not None


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--model-arg", "image_size"], "`--model-arg` must be KEY=VALUE with KEY an argument name, got 'image_size'"),
        (
            ["--model-arg", "width=4", "--model-arg", "width=8"],
            "`--model-arg` gives 'width' twice (width=4 and 'width=8'); give it once",
        ),
        (
            ["--model-arg", "depth=3"],
            "`--model-arg` depth: sizednet.SizedNet takes no argument 'depth'; it takes image_size, width, num_views, "
            "voxel_resolution",
        ),
    ],
)
def test_a_bad_model_arg_gets_one_line(user_folder, argv, message):
    with pytest.raises(UsageError) as caught:
        _config(["--model", "sizednet.SizedNet", *argv, "--jobs", "1"])
    assert str(caught.value) == message


def test_the_model_arg_is_in_the_help():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    text = parser.format_help()
    assert "--model-arg KEY=VALUE" in text and "--no-progress" in text


def test_a_user_report_records_what_ran_and_its_equivalent_command_reruns_it(user_folder, tiny_dataset, capfd):
    out = user_folder / "report"
    argv = ["report", "--model", "sizednet.SizedNet", "--model-arg", "image_size=64", "--model-arg", "width=4"]
    argv += ["--image-size", "64", "--data", str(tiny_dataset), "--seeds", "0", "--jobs", "1", "--accelerator", "cpu"]
    argv += ["--pretrain-epochs", "1", "--finetune-epochs", "1", "--test-repeats", "1", "--no-progress"]
    argv += ["--strategies-file", "rows.yaml", "--strategies", "none,side", "--out", str(out)]
    assert main(argv) == 0
    printed = capfd.readouterr()
    assert "it/s" not in printed.out + printed.err  # no progress bar drew a line

    # the model was built with its arguments: a 64-px model of width 4
    weights = torch.load(out / "seed_0" / "pretrain" / "pretrained.ckpt", map_location="cpu", weights_only=True)
    assert weights["state_dict"]["colour.weight"].shape == (4, 3)
    record = json.loads((out / "report.json").read_text())
    experiment = record["settings"]["experiment"]
    assert experiment["model_kwargs"] == {"image_size": 64, "width": 4} and experiment["image_size"] == 64
    # the user's selector has no settings(): its constructor's arguments are recorded
    assert record["strategies"]["side"]["selector_settings"] == {"pitch": 20.0}
    assert record["strategies"]["side"]["callback_settings"]["selector_settings"] == {"pitch": 20.0}
    assert "SideViews(pitch=20.0)" in record["strategies"]["side"]["selector_repr"]
    selection = json.loads((out / "seed_0" / "side" / "vtr_selection" / "settings.json").read_text())
    assert selection["settings"]["selector_settings"] == {"pitch": 20.0}

    # one seed: no interval, no sign count, and the words say so; counts are pluralised
    markdown = (out / "report.md").read_text()
    assert "sizednet.SizedNet with image_size=64, width=4 at 64 px on " in markdown
    assert "seed 0; pretraining 1 epoch on Aligned, then 1 fine-tuning epoch per strategy" in markdown
    assert "tested on 1 fixed view set, the same" in markdown
    assert "## Table 1: robustness to view transformations (%, test set; 1 seed: no interval)" in markdown
    assert "the one seed's difference; 1 seed: no interval" in markdown
    for name in ("report.md", "table1.md", "differences.md", "categories.md", "table1.tex", "differences.tex"):
        text = (out / name).read_text()
        assert "1 seeds" not in text and "1 epochs" not in text, name
    section = markdown.split("## Paired difference to None-VTR (mIoU points)")[1]
    difference = next(line for line in section.splitlines() if line.startswith("| Side views |"))
    cells = difference.strip("| ").split(" | ")[1:]
    assert len(cells) == 3 and all(re.fullmatch(r"[+-]\d+\.\d\d", cell) for cell in cells)  # the difference alone
    assert r"\textbf" not in (out / "table1.tex").read_text()  # one seed separates no row

    # the equivalent command: the same configuration, nothing that does not apply to a class of yours
    words = shlex.split(record["equivalent_command"])
    assert "--preset" not in words
    for flag, value in (("--image-size", "64"), ("--data", str(tiny_dataset)), ("--accelerator", "cpu")):
        assert words[words.index(flag) + 1] == value
    assert [words[i + 1] for i, w in enumerate(words) if w == "--model-arg"] == ["image_size=64", "width=4"]
    assert "--no-progress" in words
    # run it: each cached run's configuration is compared with the one it would run (another one is refused),
    # so it succeeds only with the same configuration, and records the same settings
    assert main(words[1:]) == 0
    again = json.loads((out / "report.json").read_text())
    assert {k: v for k, v in again["settings"].items() if k != "command"} == {
        k: v for k, v in record["settings"].items() if k != "command"
    }
    assert again["equivalent_command"] == record["equivalent_command"] == again["command"]
    assert equivalent_command(_config(words[2:])) == record["equivalent_command"]
