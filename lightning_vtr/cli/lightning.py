"""``lightning-vtr fit|validate|test|predict``: config-driven runs through Lightning's ``LightningCLI``.

Any ``LightningModule`` with the members of :class:`~lightning_vtr.protocol.ReconstructionModel`
(``predict_voxels``, ``image_size``, ``num_views``, ``voxel_resolution``) is a valid ``model`` (for ``fit``, with
its own ``training_step`` and ``configure_optimizers``), named ``--model module.Class`` with the working folder
importable (as under ``python -m``); the package's models are
:class:`~lightning_vtr.models.base.VoxelReconstructionModule` subclasses. The checkpoints record the model's class
path, so ``lightning-vtr predict --ckpt`` and ``robustness`` load those of the package's models without
``--model`` (a checkpoint never chooses code: a class of your own is named with ``--model``);
the data is :class:`~lightning_vtr.data.VTRDataModule`; the augmentation callback and its selector and
synthesizer are configured under ``trainer.callbacks`` (see ``configs/``)::

    lightning-vtr fit --config configs/pix2vox_tiny_vtr.yaml
    lightning-vtr fit --config configs/pix2vox_tiny_vtr.yaml --print_config
    lightning-vtr test --config configs/pix2vox_tiny_vtr.yaml --ckpt_path runs/.../last.ckpt
    lightning-vtr predict --config configs/pix2vox_tiny_vtr.yaml --ckpt_path runs/.../last.ckpt \\
        --trainer.callbacks+=lightning_vtr.export.VoxelPredictionWriter --trainer.callbacks.output_dir=predictions

``predict`` runs on the test split of every view set (the test loaders) when the datamodule has no
``predict_dataloader`` of its own; :class:`~lightning_vtr.export.VoxelPredictionWriter` writes the binvox
files, meshes, sheets and ``index.html``.

:class:`VTRLightningCLI` holds these defaults, so a script of one's own gets the same command line with
``VTRLightningCLI()``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from types import MethodType
from typing import Any

import lightning as L
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.utilities.model_helpers import is_overridden

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models.registry import CLASS_PATH_KEY

__all__ = [
    "HELP_COLUMNS",
    "HIDDEN_OPTIONS",
    "LIGHTNING_SUBCOMMANDS",
    "TRAINER_DEFAULTS",
    "TRUST_REMEDY",
    "RecordModelClass",
    "VTRLightningCLI",
    "lightning_help",
    "run_lightning_cli",
]

#: The ``LightningCLI`` sub-commands ``lightning-vtr`` passes on.
LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")
#: Trainer defaults of :class:`VTRLightningCLI`: the callback's samples reach the next epoch's loader only
#: when the dataloaders are rebuilt every epoch.
TRAINER_DEFAULTS: dict[str, Any] = {"reload_dataloaders_every_n_epochs": 1}
#: What the message of a ``--ckpt_path`` that ``weights_only`` loading refuses advises: LightningCLI's own opt-in.
TRUST_REMEDY = "load it only if you made it or trust who did: `--weights_only false`"
#: Options of the classes' signatures that ``--help`` does not show: removed arguments still accepted as ``None``.
HIDDEN_OPTIONS = ("data.max_generated", "data.init_args.max_generated")
#: The terminal width (``COLUMNS``) :func:`lightning_help` wraps the help at: the width of a stdout that is not a
#: terminal, so the shipped texts equal what ``lightning-vtr fit --help > file`` writes.
HELP_COLUMNS = 80


class RecordModelClass(L.Callback):
    """Records the model's class path in every checkpoint (under
    :data:`~lightning_vtr.models.registry.CLASS_PATH_KEY`), so that
    :func:`~lightning_vtr.models.registry.load_model` finds a class of ``lightning_vtr`` without ``--model`` (any
    other class is named with ``--model``). A class defined in a script run as ``__main__`` is not recorded (it
    cannot be imported back)."""

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        cls = type(pl_module)
        if cls.__module__ != "__main__":
            checkpoint[CLASS_PATH_KEY] = f"{cls.__module__}.{cls.__qualname__}"


class VTRLightningCLI(LightningCLI):
    """``LightningCLI`` with the package's defaults.

    Compared with ``LightningCLI()``: the model is any ``LightningModule`` subclass (``subclass_mode_model``)
    that satisfies :class:`~lightning_vtr.protocol.ReconstructionModel` (checked once it is built; for ``fit``
    also its own ``training_step`` and ``configure_optimizers``), the data :class:`~lightning_vtr.data.VTRDataModule`,
    the Trainer reloads its dataloaders every epoch (:data:`TRAINER_DEFAULTS`, which the callback needs) and
    records the model's class path in its checkpoints (:class:`RecordModelClass`), a re-run overwrites the saved
    ``config.yaml``, and the models' own ``configure_optimizers`` is kept (``auto_configure_optimizers=False``).
    Every argument of ``LightningCLI`` can still be given; ``trainer_defaults`` and ``save_config_kwargs`` are
    merged over these defaults.

    Example::

        # my_cli.py: `python my_cli.py fit --config configs/pix2vox_tiny_vtr.yaml`
        from lightning_vtr.cli.lightning import VTRLightningCLI

        VTRLightningCLI()
    """

    def __init__(
        self,
        model_class: Any = L.LightningModule,
        datamodule_class: Any = VTRDataModule,
        *,
        subclass_mode_model: bool = True,
        trainer_defaults: dict[str, Any] | None = None,
        save_config_kwargs: dict[str, Any] | None = None,
        auto_configure_optimizers: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            model_class,
            datamodule_class,
            subclass_mode_model=subclass_mode_model,
            trainer_defaults=_with_recorder({**TRAINER_DEFAULTS, **(trainer_defaults or {})}),
            save_config_kwargs={"overwrite": True, **(save_config_kwargs or {})},
            auto_configure_optimizers=auto_configure_optimizers,
            **kwargs,
        )

    def _add_arguments(self, parser: Any) -> None:
        super()._add_arguments(parser)
        for action in parser._actions:  # removed options: accepted as before, not advertised
            if action.dest in HIDDEN_OPTIONS:
                action.help = argparse.SUPPRESS

    def instantiate_classes(self) -> None:
        """Build the classes, then refuse a model without the protocol's members (one line naming them)."""
        super().instantiate_classes()
        from lightning_vtr.models.registry import check_model, check_model_class

        check_model_class(type(self.model), "--model", training=self.subcommand == "fit")
        check_model(self.model)

    def instantiate_trainer(self, **kwargs: Any) -> L.Trainer:
        """The Trainer, each checkpoint callback that was not told otherwise also writing ``last.ckpt``.

        A ``ModelCheckpoint`` whose ``save_last`` is unset (``None``, as in the one Lightning adds when the
        config names none) keeps the last epoch as ``last.ckpt`` too, the file the docs' commands name;
        ``save_last: false`` in a config is kept.
        """
        from lightning.pytorch.callbacks import ModelCheckpoint

        trainer = super().instantiate_trainer(**kwargs)
        for callback in trainer.callbacks:  # type: ignore[attr-defined]
            if isinstance(callback, ModelCheckpoint) and callback.save_last is None:
                callback.save_last = True
        return trainer

    def _parse_ckpt_path(self) -> None:
        """Lightning's: apply ``--ckpt_path``'s hyperparameters to the model, once the checkpoint is known to
        name no class outside ``lightning_vtr`` that the command line or config did not name.

        LightningCLI would build the class the checkpoint's ``_class_path`` names, importing its module; a
        checkpoint never chooses the code that runs, so such a class must be the configured model's.

        Raises:
            UsageError: the checkpoint names another class outside ``lightning_vtr`` (one line).
            DataError: ``weights_only`` loading refuses the file, unless ``--weights_only false`` was given.
        """
        from pathlib import Path

        from lightning_vtr.errors import DataError
        from lightning_vtr.models.registry import check_recorded_classes, read_checkpoint

        subcommand = self.config.get("subcommand") if hasattr(self.config, "get") else None
        settings = self.config.get(subcommand) if subcommand else None
        ckpt_path = settings.get("ckpt_path") if settings is not None else None
        if settings is None or not ckpt_path or not Path(ckpt_path).is_file():
            return super()._parse_ckpt_path()
        trusted = settings.get("weights_only") is False
        try:
            checkpoint = read_checkpoint(ckpt_path, "--ckpt_path", remedy=TRUST_REMEDY)
        except DataError:
            if trusted:
                return None  # a full pickle the user trusts: the config alone builds the model
            raise
        model = settings.get("model")
        configured = model.get("class_path") if hasattr(model, "get") else None
        check_recorded_classes(
            checkpoint, ckpt_path, [configured] if isinstance(configured, str) else [], trust_checkpoint=trusted
        )
        del checkpoint
        return super()._parse_ckpt_path()

    def _prepare_subcommand_kwargs(self, subcommand: str) -> dict[str, Any]:
        """Lightning's, with ``weights_only=True`` unless the command line says otherwise: ``--ckpt_path`` is
        read as tensors and plain containers, never as a full pickle (``--weights_only false`` opts in)."""
        kwargs = super()._prepare_subcommand_kwargs(subcommand)
        if (
            "weights_only" in self._subcommand_method_arguments.get(subcommand, ())
            and kwargs.get("weights_only") is None
        ):
            kwargs["weights_only"] = True
        return kwargs

    def before_predict(self) -> None:
        """Give a datamodule without ``predict_dataloader`` one: its test loaders (every view set's test split)."""
        dm = getattr(self, "datamodule", None)
        if dm is not None and not is_overridden("predict_dataloader", dm) and hasattr(dm, "test_dataloader"):
            dm.predict_dataloader = MethodType(_test_loaders, dm)


def _with_recorder(defaults: dict[str, Any]) -> dict[str, Any]:
    """``defaults`` with a :class:`RecordModelClass` among its ``callbacks``."""
    callbacks = defaults.get("callbacks") or []
    callbacks = list(callbacks) if isinstance(callbacks, (list, tuple)) else [callbacks]
    if not any(isinstance(c, RecordModelClass) for c in callbacks):
        callbacks.append(RecordModelClass())
    return {**defaults, "callbacks": callbacks}


def _test_loaders(datamodule: Any) -> Any:
    return datamodule.test_dataloader()


def _option_values(words: Sequence[str], names: tuple[str, ...]) -> list[str]:
    """The values of the options ``names`` in ``words`` (``--name VALUE`` and ``--name=VALUE``)."""
    values = []
    for i, word in enumerate(words):
        name, sep, value = word.partition("=")
        if name in names:
            if sep:
                values.append(value)
            elif i + 1 < len(words):
                values.append(words[i + 1])
    return values


def check_config(path: str, option: str = "--config") -> None:
    """A config of ``lightning-vtr fit|validate|test|predict``: an existing, non-empty YAML file of settings.

    Raises:
        FileNotFoundError: no file there (a usage error).
        DataError: an empty file, not UTF-8 text, not YAML, or YAML that is not a mapping of settings.
    """
    from pathlib import Path

    import yaml

    from lightning_vtr.errors import DataError

    file = Path(path).expanduser()
    if not file.is_file():
        found = "a folder" if file.is_dir() else "no such file"
        raise FileNotFoundError(f"`{option}` must be a YAML config file, got {path!r} ({found})")
    expected = f"`{option}` must be a YAML config of LightningCLI settings (trainer:, model:, data:), got {path!r}"
    data = file.read_bytes()
    if not data.strip():
        raise DataError(f"{expected}: an empty file ({len(data)} bytes)")
    try:
        settings = yaml.safe_load(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise DataError(f"{expected}: {len(data)} bytes that are not UTF-8 text (a binary file)") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or "not valid YAML"
        raise DataError(f"{expected}: invalid YAML{where} ({problem}; truncated?)") from None
    if not isinstance(settings, dict):
        raise DataError(f"{expected}: YAML holding a {type(settings).__name__}, not a mapping of settings")


def run_lightning_cli(argv: Sequence[str] | None = None) -> int:
    """Run :class:`VTRLightningCLI` on ``argv`` (``None``: ``sys.argv[1:]``); returns the exit status 0.

    The configs and ``--ckpt_path`` are checked first (:func:`check_config`,
    :func:`lightning_vtr.models.registry.check_checkpoint`), and jsonargparse's errors are raised as
    :class:`~lightning_vtr.errors.UsageError` (one line from ``lightning-vtr``) instead of printing the usage.
    """
    import argparse
    import os
    import sys

    from lightning_vtr.errors import DataError, UsageError
    from lightning_vtr.models.registry import check_checkpoint

    words = list(sys.argv[1:] if argv is None else argv)
    named = [name for name in _option_values(words, ("--model", "--model.class_path")) if "." in name]
    configs = _option_values(words, ("--config", "-c"))
    if (named or configs) and os.getcwd() not in sys.path:
        # `--model mymodel.MyVoxelNet` (or a config's class_path) from the folder holding mymodel.py: only classes
        # the user names import from the working folder, never one a checkpoint names
        sys.path.insert(0, os.getcwd())
    for name in _option_values(words, ("--model", "--model.class_path")):
        if "." in name:  # a class path: one line for what jsonargparse would bury in its long message
            from lightning_vtr.models.registry import check_model_class, import_class

            check_model_class(import_class(name), training=bool(words) and words[0] == "fit")
    if not any(word in ("-h", "--help") for word in words):
        for path in _option_values(words, ("--config", "-c")):
            check_config(path)
        trusted = any(value.lower() == "false" for value in _option_values(words, ("--weights_only",)))
        for path in _option_values(words, ("--ckpt_path",)):
            if path not in ("best", "last", "hpc", "registry", "null", "None"):
                check_checkpoint(path, "--ckpt_path", trust_checkpoint=trusted, remedy=TRUST_REMEDY)
                check_checkpoint_class(path, configured_model(words))
        roots = _option_values(words, ("--data.root",))
        if not roots:  # the last config that names a dataset root decides, as in LightningCLI
            roots = [root for path in _option_values(words, ("--config", "-c")) if (root := config_root(path))][-1:]
        for root in roots:
            if root not in ("null", "None", ""):  # before the Trainer prints its banner
                from pathlib import Path

                from lightning_vtr.data.format import load_metadata

                load_metadata(Path(root).expanduser())
    try:
        VTRLightningCLI(args=None if argv is None else list(argv), parser_kwargs={"exit_on_error": False})
    except argparse.ArgumentError as err:
        raise UsageError(str(err)) from None
    except RuntimeError as err:
        checkpoints = _option_values(words, ("--ckpt_path",))
        if checkpoints and str(err).startswith("Error(s) in loading state_dict for "):
            raise DataError(_weights_mismatch(str(err), checkpoints[-1])) from None
        raise
    return 0


def lightning_help(command: str) -> str:
    """The text ``lightning-vtr COMMAND --help`` prints from the live ``LightningCLI`` parser (the path
    :func:`run_lightning_cli` takes), wrapped at :data:`HELP_COLUMNS` columns, with the program named
    ``lightning-vtr``.

    The ``known subclasses`` it lists are those of the modules imported so far, so the texts shipped in
    ``lightning_vtr/cli/help/`` are made in a fresh process (``python -m lightning_vtr.cli.gen_help``).

    Args:
        command: ``"fit"``, ``"validate"``, ``"test"`` or ``"predict"``.

    Raises:
        ValueError: ``command`` is not a LightningCLI sub-command.
    """
    import contextlib
    import io
    import os
    import sys

    if command not in LIGHTNING_SUBCOMMANDS:
        raise ValueError(f"`command` must be one of {', '.join(LIGHTNING_SUBCOMMANDS)}, got {command!r}")
    saved_columns, saved_argv = os.environ.get("COLUMNS"), sys.argv
    os.environ["COLUMNS"] = str(HELP_COLUMNS)
    sys.argv = ["lightning-vtr", command, "--help"]  # argparse names the program after sys.argv[0]
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed), contextlib.suppress(SystemExit):
            run_lightning_cli(None)  # the words of sys.argv, as from the entry point
    finally:
        sys.argv = saved_argv
        if saved_columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = saved_columns
    return printed.getvalue()


def _config_section(path: str, section: str) -> Any:
    """The ``section`` (``"data"``, ``"model"``) of a LightningCLI YAML config; ``None`` when it is unreadable."""
    from pathlib import Path

    import yaml

    try:
        settings = yaml.safe_load(Path(path).expanduser().read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return settings.get(section) if isinstance(settings, dict) else None


def config_root(path: str) -> str | None:
    """The dataset root a LightningCLI config sets (``data: {root: ...}`` or ``data: {init_args: {root: ...}}``),
    ``None`` when it sets none or is not a readable YAML mapping."""
    data = _config_section(path, "data")
    if not isinstance(data, dict):
        return None
    init_args = data.get("init_args")
    root = init_args.get("root") if isinstance(init_args, dict) else data.get("root")
    return str(root) if root is not None else None


def configured_model(words: Sequence[str]) -> type | None:
    """The model class a LightningCLI command line names: the last ``--model`` / ``--model.class_path`` value,
    else the last config's ``model: {class_path: ...}``; ``None`` when none names an importable class."""
    import importlib

    names = [value for value in _option_values(words, ("--model", "--model.class_path")) if "." in value]
    if not names:
        sections = [_config_section(path, "model") for path in _option_values(words, ("--config", "-c"))]
        names = [m["class_path"] for m in sections if isinstance(m, dict) and isinstance(m.get("class_path"), str)]
    if not names:
        return None
    module, _, name = names[-1].rpartition(".")
    try:
        found = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        return None  # LightningCLI reports it
    return found if isinstance(found, type) else None


def _model_classes() -> list[type]:
    """The package's reconstruction model classes (:data:`lightning_vtr.models.MODELS`)."""
    from lightning_vtr.models import MODELS

    return list(MODELS.values())


def check_checkpoint_class(path: str, model: type | None) -> None:
    """Refuse a ``--ckpt_path`` whose hyperparameters the configured model class does not take.

    LightningCLI applies a checkpoint's hyperparameters to the configured model; those of another class
    would otherwise end in jsonargparse's long validation error.

    Raises:
        DataError: the checkpoint holds hyperparameters ``model.__init__`` has no argument for; the message
            names the class that takes them, when one is defined.
    """
    import inspect

    import torch

    from lightning_vtr.errors import DataError

    if model is None:
        return
    try:
        hparams = torch.load(path, map_location="cpu", weights_only=True).get("hyper_parameters") or {}
    except Exception:  # check_checkpoint read it already; a full pickle is left to Lightning
        return

    def takes(cls: type[object]) -> bool:
        parameters = inspect.signature(cls.__init__).parameters
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
            return True
        return all(key in parameters for key in hparams if not key.startswith("_"))

    if takes(model):
        return
    owners = [cls.__name__ for cls in _model_classes() if takes(cls)]
    unknown = [key for key in hparams if not key.startswith("_") and key not in inspect.signature(model).parameters]
    owner = f"a checkpoint of {' or '.join(owners)}" if owners else "a checkpoint of another model class"
    raise DataError(
        f"`--ckpt_path` must be a checkpoint of the configured model ({model.__name__}), got {path!r}: {owner} "
        f"(hyperparameters {', '.join(unknown[:3])}{', ...' if len(unknown) > 3 else ''} that "
        f"{model.__name__} does not take)"
    )


def _weights_mismatch(message: str, checkpoint: str) -> str:
    """One line for torch's ``load_state_dict`` error on ``--ckpt_path``: which model, how many keys differ."""
    import re

    model = message[len("Error(s) in loading state_dict for ") :].split(":", 1)[0]
    counts = []
    for kind in ("Missing", "Unexpected"):
        found = re.search(kind + r" key\(s\) in state_dict: (.*?)\.\s*(\n|$)", message)
        if found:
            counts.append(f"{found.group(1).count(chr(34)) // 2} {kind.lower()} keys")
    if "size mismatch" in message:
        counts.append(f"{message.count('size mismatch')} shape mismatches")
    mismatch = ", ".join(counts) or "weights that do not fit"
    return (
        f"`--ckpt_path` must be a checkpoint of the configured model ({model}), got {checkpoint!r}: {mismatch} "
        "(a checkpoint of the other model class or of another preset?)"
    )
