"""Checkpoints never run code or choose code.

Each attack a downloaded checkpoint or a copied output folder could make is built in ``tmp_path`` and refused
with one line, its payload never running: a pickle payload (in a report's earlier output, behind an
``argparse.Namespace``, under ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1``), a recorded class path naming a module of
the working folder or of the standard library, a relative class path, and datamodule settings naming a folder.
A checkpoint ``Trainer.fit`` wrote still loads, and every ``torch.load`` of the package reads ``weights_only``.
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
from pathlib import Path

import lightning as L
import pytest
import torch
from helpers import one_thread

import lightning_vtr
from lightning_vtr.cli import main
from lightning_vtr.errors import DataError, UsageError
from lightning_vtr.models import Pix2VoxPlusPlus
from lightning_vtr.models.registry import CLASS_PATH_KEY, check_checkpoint, check_recorded_classes, load_model

_one_thread = pytest.fixture(autouse=True)(one_thread)

#: ``evilmod.py`` of an attacker's folder: importing it leaves a marker beside it.
EVIL_MODULE = (
    "from pathlib import Path\n"
    "Path(__file__).with_name('imported').write_text('evilmod ran')\n"
    "import lightning as L\n"
    "class Net(L.LightningModule):\n"
    "    pass\n"
)


class _Payload:
    """Unpickled by a full pickle load, it runs ``touch MARKER``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def fitted(tiny_dataset, tmp_path_factory) -> Path:
    """``last.ckpt`` of tiny Pix2Vox++ fitted one batch by ``Trainer.fit``, its class recorded as ``fit`` does."""
    from lightning_vtr.cli.lightning import RecordModelClass
    from lightning_vtr.data import VTRDataModule

    folder = tmp_path_factory.mktemp("fitted")
    L.seed_everything(0, verbose=False)
    dm = VTRDataModule(str(tiny_dataset), image_size=64, batch_size=2)
    trainer = L.Trainer(
        max_epochs=1,
        limit_train_batches=1,
        limit_val_batches=0,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=str(folder),
        callbacks=[RecordModelClass(), L.pytorch.callbacks.ModelCheckpoint(dirpath=folder / "ckpt", save_last=True)],
    )
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        trainer.fit(Pix2VoxPlusPlus(preset="tiny", validation_fscore=False), datamodule=dm)
    finally:
        torch.set_num_threads(previous)
    return folder / "ckpt" / "last.ckpt"


def _variant(fitted: Path, path: Path, **changes) -> Path:
    """``fitted`` with top-level entries changed (``None`` removes one), saved at ``path``."""
    checkpoint = torch.load(fitted, map_location="cpu", weights_only=True)
    for key, value in changes.items():
        if value is None:
            checkpoint.pop(key, None)
        else:
            checkpoint[key] = value
    torch.save(checkpoint, path)
    return path


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


@pytest.fixture
def evil_folder(tmp_path, monkeypatch) -> Path:
    """The working folder holds ``evilmod.py``; it is forgotten afterwards."""
    folder = tmp_path / "evil"
    folder.mkdir()
    (folder / "evilmod.py").write_text(EVIL_MODULE)
    monkeypatch.chdir(folder)
    yield folder
    sys.modules.pop("evilmod", None)
    while str(folder) in sys.path:
        sys.path.remove(str(folder))


@pytest.fixture
def picture(tmp_path) -> Path:
    """An image folder of one 64-px picture."""
    from PIL import Image

    folder = tmp_path / "chair"
    folder.mkdir()
    Image.new("RGB", (64, 64), (200, 30, 30)).save(folder / "view.png")
    return folder


# ------------------------------------------------------------------------------------- every torch.load reads weights
def _calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            yield node


def _name(node: ast.expr) -> str:
    return ast.unparse(node)


def test_every_checkpoint_read_of_the_package_passes_weights_only():
    package = Path(lightning_vtr.__file__).parent
    unsafe, loaders = [], []
    for file in sorted(package.rglob("*.py")):
        tree = ast.parse(file.read_text(), str(file))
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.ImportFrom)
                and node.module == "torch"
                and any(a.name == "load" for a in node.names)
            ):
                unsafe.append(f"{file}:{node.lineno}: from torch import load")
        for call in _calls(tree):
            func = _name(call.func)
            keywords = {k.arg: k.value for k in call.keywords}
            where = f"{file.relative_to(package.parent)}:{call.lineno}: {func}"
            if func in ("torch.load", "torch.serialization.load"):
                loaders.append(where)
                value = keywords.get("weights_only")
                if not (isinstance(value, ast.Constant) and value.value is True):
                    unsafe.append(where)
            elif func.endswith(".load_from_checkpoint") and "weights_only" not in keywords:
                unsafe.append(where)  # Lightning's default lets TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD read a full pickle
            elif func.split(".")[-1] in ("fit", "validate", "test", "predict") and "ckpt_path" in keywords:
                unsafe += [] if "weights_only" in keywords else [where]
    assert any(w.startswith("lightning_vtr/models/registry.py") for w in loaders)  # the walk sees the package's reads
    assert unsafe == []


# ------------------------------------------------------------------------- 1. a report's earlier output is data
def test_report_resume_refuses_a_pickled_pretrained_checkpoint(fitted, tmp_path):
    from lightning_vtr.experiments.config import ExperimentConfig
    from lightning_vtr.experiments.training import load_run_model, run_strategy

    marker = tmp_path / "pwned"
    out = tmp_path / "out"
    pretrained = out / "pretrain" / "pretrained.ckpt"
    pretrained.parent.mkdir(parents=True)
    _variant(fitted, pretrained, payload=_Payload(marker))
    config = ExperimentConfig(out=str(out), finetune_epochs=1, accelerator="cpu")
    with pytest.raises(DataError) as err:
        run_strategy("none", config, pretrained)
    message = str(err.value)
    assert "'posix.system'" in message and str(pretrained) in message and "\n" not in message
    assert "weights_only loading refuses" in message and "another `--out`" in message
    run_dir = out / "none"
    (run_dir / "checkpoints").mkdir(parents=True)
    _variant(fitted, run_dir / "checkpoints" / "last.ckpt", payload=_Payload(marker))
    with pytest.raises(DataError, match="holds the global 'posix.system'"):
        load_run_model(config, run_dir)
    assert not marker.exists()


def test_report_resume_refuses_a_pickled_last_checkpoint_before_fitting(fitted, tiny_dataset, tmp_path):
    from lightning_vtr.experiments.config import ExperimentConfig
    from lightning_vtr.experiments.training import run_strategy

    marker = tmp_path / "pwned"
    out = tmp_path / "out"
    (out / "none" / "checkpoints").mkdir(parents=True)
    last = _variant(fitted, out / "none" / "checkpoints" / "last.ckpt", payload=_Payload(marker))
    config = ExperimentConfig(out=str(out), data=str(tiny_dataset), finetune_epochs=1, accelerator="cpu")
    with pytest.raises(DataError, match="holds the global 'posix.system'") as err:
        run_strategy("none", config, fitted)
    assert str(last) in str(err.value) and not marker.exists()
    assert not (out / "none" / "results.json").exists()


def test_report_resume_reads_its_own_checkpoint(fitted, tmp_path):
    from lightning_vtr.experiments.config import ExperimentConfig
    from lightning_vtr.experiments.training import load_run_model

    run_dir = tmp_path / "none"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "last.ckpt").write_bytes(fitted.read_bytes())
    model = load_run_model(ExperimentConfig(out=str(tmp_path)), run_dir)
    saved = torch.load(fitted, map_location="cpu", weights_only=True)["state_dict"]
    name = next(iter(saved))
    assert torch.equal(model.state_dict()[name], saved[name])


# -------------------------------------------------------------------------------- 2. a checkpoint never picks code
@pytest.mark.parametrize("recorded", ["evilmod.Net", "this.Zen"])
@pytest.mark.parametrize("where", ["recorded", "hyper_parameters"])
def test_predict_refuses_a_class_path_outside_the_package(
    fitted, evil_folder, picture, capsys, recorded, where, tmp_path
):
    if where == "recorded":
        ckpt = _variant(fitted, tmp_path / "evil.ckpt", **{CLASS_PATH_KEY: recorded})
    else:
        hparams = torch.load(fitted, map_location="cpu", weights_only=True)["hyper_parameters"]
        hparams = {**hparams, "_class_path": recorded, "_instantiator": "lightning.pytorch.cli.instantiate_module"}
        ckpt = _variant(fitted, tmp_path / "evil.ckpt", **{CLASS_PATH_KEY: None, "hyper_parameters": hparams})
    module = recorded.split(".")[0]
    already = module in sys.modules
    status = main(["predict", "--ckpt", str(ckpt), "--images", str(picture), "--out", str(tmp_path / "out")])
    err = _one_line(capsys)
    assert status == 2
    assert f"names the model class '{recorded}', outside lightning_vtr" in err
    assert f"pass `--model {recorded}` if you trust it" in err
    assert not (evil_folder / "imported").exists()
    assert already or module not in sys.modules
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "recorded", ["lightning_vtr.cli.__main__.Net", "lightning_vtr.cli.predict.run", "lightning_vtr._private.Net"]
)
def test_predict_refuses_a_command_line_or_private_module_of_the_package(fitted, picture, capsys, recorded, tmp_path):
    """``lightning_vtr.cli.__main__`` runs the command line when imported: a checkpoint may not name it."""
    ckpt = _variant(fitted, tmp_path / "main.ckpt", **{CLASS_PATH_KEY: recorded})
    before = set(sys.modules)
    status = main(["predict", "--ckpt", str(ckpt), "--images", str(picture), "--out", str(tmp_path / "out")])
    assert status == 2
    assert f"names the model class '{recorded}'" in _one_line(capsys)
    assert "lightning_vtr.cli.__main__" not in set(sys.modules) - before
    assert not (tmp_path / "out").exists()


def test_robustness_and_load_model_refuse_a_class_path_outside_the_package(
    fitted, evil_folder, tiny_dataset, capsys, tmp_path
):
    ckpt = _variant(fitted, tmp_path / "evil.ckpt", **{CLASS_PATH_KEY: "evilmod.Net"})
    argv = ["robustness", "--ckpt", str(ckpt), "--data", str(tiny_dataset), "--out", str(tmp_path / "maps")]
    assert main(argv) == 2
    assert "names the model class 'evilmod.Net', outside lightning_vtr" in _one_line(capsys)
    with pytest.raises(UsageError, match="pass `--model evilmod.Net` if you trust it"):
        load_model(ckpt)
    assert not (evil_folder / "imported").exists() and "evilmod" not in sys.modules
    assert str(evil_folder) not in sys.path  # the working folder is importable only for the user's --model


def test_load_from_checkpoint_never_imports_the_class_a_checkpoint_names(fitted, evil_folder, tmp_path):
    hparams = torch.load(fitted, map_location="cpu", weights_only=True)["hyper_parameters"]
    ckpt = _variant(fitted, tmp_path / "evil.ckpt", hyper_parameters={**hparams, "_class_path": "evilmod.Net"})
    sys.path.insert(0, str(evil_folder))  # even where the folder is importable
    with pytest.raises(ValueError, match=r"is a checkpoint of Net \(evilmod.Net\), not of Pix2VoxPlusPlus"):
        Pix2VoxPlusPlus.load_from_checkpoint(ckpt)
    assert not (evil_folder / "imported").exists() and "evilmod" not in sys.modules


def test_validate_refuses_a_ckpt_path_naming_a_class_outside_the_package(fitted, evil_folder, capsys, tmp_path):
    hparams = torch.load(fitted, map_location="cpu", weights_only=True)["hyper_parameters"]
    hparams = {**hparams, "_class_path": "evilmod.Net", "_instantiator": "lightning.pytorch.cli.instantiate_module"}
    ckpt = _variant(fitted, tmp_path / "evil.ckpt", hyper_parameters=hparams, **{CLASS_PATH_KEY: None})
    argv = ["validate", "--model", "lightning_vtr.models.Pix2VoxPlusPlus", "--model.preset", "tiny"]
    assert main([*argv, "--ckpt_path", str(ckpt), "--trainer.logger", "false"]) == 2
    err = _one_line(capsys)
    assert "names the model class 'evilmod.Net', outside lightning_vtr" in err
    assert not (evil_folder / "imported").exists() and "evilmod" not in sys.modules


def test_a_class_path_in_the_hyperparameters_is_not_imported_without_trust(tmp_path):
    checkpoint = {"hyper_parameters": {"selector": {"class_path": "evilmod.Picker", "init_args": {}}}}
    with pytest.raises(UsageError, match="names the class 'evilmod.Picker' in its hyperparameters"):
        check_recorded_classes(checkpoint, tmp_path / "x.ckpt")
    check_recorded_classes(checkpoint, tmp_path / "x.ckpt", trust_checkpoint=True)  # the user's opt-in
    package = {"hyper_parameters": {"selector": {"class_path": "lightning_vtr.selection.ErrorGuidedSelector"}}}
    check_recorded_classes(package, tmp_path / "x.ckpt")


# -------------------------------------------------------------------- 3. weights_only refusals are refusals
def test_a_namespace_before_a_payload_is_refused_under_the_torch_override(
    fitted, picture, capsys, tmp_path, monkeypatch
):
    marker = tmp_path / "pwned"
    hparams = torch.load(fitted, map_location="cpu", weights_only=True)["hyper_parameters"]
    ckpt = _variant(
        fitted, tmp_path / "ns.ckpt", hyper_parameters=argparse.Namespace(**hparams), payload=_Payload(marker)
    )
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    status = main(["predict", "--ckpt", str(ckpt), "--images", str(picture), "--out", str(tmp_path / "out")])
    err = _one_line(capsys)
    assert status == 1
    assert "holds the globals 'argparse.Namespace', 'posix.system', which weights_only loading refuses" in err
    assert "--trust-checkpoint" in err and str(ckpt) in err
    with pytest.raises(Exception, match="Weights only load failed"):  # the package's models default to weights_only
        Pix2VoxPlusPlus.load_from_checkpoint(ckpt)
    assert main(["validate", "--ckpt_path", str(ckpt), "--model", "lightning_vtr.models.Pix2VoxPlusPlus"]) == 1
    assert "`--weights_only false`" in _one_line(capsys)
    assert not marker.exists()


def test_trust_checkpoint_is_the_opt_in_that_loads_a_full_pickle(fitted, tmp_path):
    marker = tmp_path / "trusted"
    ckpt = _variant(fitted, tmp_path / "mine.ckpt", payload=_Payload(marker))
    with pytest.raises(DataError, match="holds the global 'posix.system'"):
        check_checkpoint(ckpt)
    assert not marker.exists()
    model = load_model(ckpt, trust_checkpoint=True)
    assert isinstance(model, Pix2VoxPlusPlus) and marker.exists()  # trusted: the pickle ran, as documented


# ------------------------------------------------------------ 4. a checkpoint's data settings do not widen reads
def test_predict_ignores_folders_named_by_the_checkpoint(fitted, picture, tmp_path, monkeypatch):
    import lightning_vtr.data.datamodule as datamodule
    from lightning_vtr.evaluation.predict import make_datamodule

    stored = torch.load(fitted, map_location="cpu", weights_only=True)["datamodule_hyper_parameters"]
    settings = {**stored, "background": "folder:/", "generated_dir": str(tmp_path / "gen"), "num_workers": 64}
    ckpt = _variant(fitted, tmp_path / "folder.ckpt", datamodule_hyper_parameters=settings)
    scanned = []
    monkeypatch.setattr(datamodule, "BackgroundFolder", lambda folder, *a, **k: scanned.append(folder))
    model = load_model(ckpt)
    dm = make_datamodule(ckpt, model)
    assert dm.recipe.background_folder is None and scanned == []
    assert dm._generated_dir_arg is None and dm.num_workers == 0
    recipe = {"background_folder": "/", "normalize": "pm1"}
    ckpt = _variant(fitted, tmp_path / "recipe.ckpt", datamodule_hyper_parameters={**stored, "recipe": recipe})
    dm = make_datamodule(ckpt, model)
    assert dm.recipe.background_folder is None and dm.recipe.normalize == "pm1" and scanned == []
    assert main(["predict", "--ckpt", str(ckpt), "--images", str(picture), "--out", str(tmp_path / "out")]) == 0
    assert scanned == [] and (tmp_path / "out" / "predictions.json").is_file()


# ----------------------------------------------------------------------------- 5. one line for a relative path
def test_a_relative_class_path_gets_one_line(fitted, evil_folder, picture, capsys, tmp_path):
    argv = ["predict", "--ckpt", str(fitted), "--images", str(picture), "--out", str(tmp_path / "out")]
    assert main([*argv, "--model", ".evilmod.Net"]) == 2
    assert "`--model` must be an absolute class path module.Class, got '.evilmod.Net'" in _one_line(capsys)
    ckpt = _variant(fitted, tmp_path / "relative.ckpt", **{CLASS_PATH_KEY: ".evilmod.Net"})
    assert main(["predict", "--ckpt", str(ckpt), "--images", str(picture), "--out", str(tmp_path / "out")]) == 2
    assert "names the model class '.evilmod.Net', outside lightning_vtr" in _one_line(capsys)
    assert not (evil_folder / "imported").exists() and "evilmod" not in sys.modules


# ---------------------------------------------------------------------------------------- what still loads
def test_a_checkpoint_trainer_fit_wrote_loads_in_load_model_and_predict(fitted, picture, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")  # explicit weights_only=True wins
    model = load_model(fitted)
    assert type(model) is Pix2VoxPlusPlus and not model.training
    saved = torch.load(fitted, map_location="cpu", weights_only=True)["state_dict"]
    assert all(torch.equal(model.state_dict()[k], v) for k, v in saved.items())
    out = tmp_path / "out"
    assert main(["predict", "--ckpt", str(fitted), "--images", str(picture), "--out", str(out), "--no-sheets"]) == 0
    assert (out / "chair" / "prediction.binvox").is_file()


def test_lightning_cli_reads_ckpt_path_with_weights_only():
    from lightning_vtr.cli.lightning import VTRLightningCLI

    cli = object.__new__(VTRLightningCLI)  # only what _prepare_subcommand_kwargs reads
    cli.model, cli.datamodule = "model", None
    cli._subcommand_method_arguments = {"validate": {"ckpt_path", "weights_only"}}
    cli.config_init = {"validate": {"ckpt_path": "x.ckpt", "weights_only": None}}
    assert cli._prepare_subcommand_kwargs("validate")["weights_only"] is True
    cli.config_init = {"validate": {"ckpt_path": "x.ckpt", "weights_only": False}}  # the user's own opt-in
    assert cli._prepare_subcommand_kwargs("validate")["weights_only"] is False
