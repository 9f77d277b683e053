"""The experiment configuration: one dataclass whose fields are also the command-line flags.

Each field that a command line may set carries ``metadata`` (:func:`flag`): its help line and how its words are
parsed. :mod:`lightning_vtr.experiments.flags` turns those fields into ``argparse`` arguments, so a setting has
one name (``pretrain_epochs`` is ``--pretrain-epochs``) and one default (the field's, or the instance a
command passes).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["FINETUNE_LR_SCHEDULES", "RECIPES", "ExperimentConfig", "flag"]

FINETUNE_LR_SCHEDULES = ("cosine", "constant")
"""Fine-tuning learning-rate schedules (``ExperimentConfig.finetune_lr``)."""
RECIPES: tuple[str, ...] = ("reference", "plain", "pix2vox", "lrgt")
"""Training-image recipes (``ExperimentConfig.recipe``): ``"reference"`` or a name of
:data:`~lightning_vtr.data.IMAGE_RECIPES` (written out so that ``lightning-vtr report --help`` imports no torch;
a test keeps them equal)."""


def flag(
    help: str,
    *,
    choices: Any = None,
    minimum: int | None = None,
    comma_separated: bool = False,
    default_text: str | None = None,
) -> dict[str, Any]:
    """The ``metadata`` of a dataclass field that is a command-line flag.

    Args:
        help: the flag's help line (the default is appended).
        choices: the accepted values: a collection, or a callable returning one (read when the parser is built).
        minimum: the least accepted integer (``1``: a positive integer).
        comma_separated: a sequence field read as one comma-separated word.
        default_text: how the help names the default (e.g. what ``None`` means); default: the value.

    Returns:
        A dict for ``dataclasses.field(metadata=...)``.

    Example::

        epochs: int = field(default=10, metadata=flag("training epochs", minimum=1))
    """
    return {
        "flag": {
            "help": help,
            "choices": choices,
            "minimum": minimum,
            "comma_separated": comma_separated,
            "default_text": default_text,
        }
    }


@dataclass
class ExperimentConfig:
    """One experiment's budget and settings.

    Attributes:
        model: a name in :data:`~lightning_vtr.models.registry.MODELS` (``"pix2vox"`` or ``"lrgt"``), or the
            import path ``module.Class`` of any ``LightningModule`` with ``predict_voxels``, ``image_size``,
            ``num_views``, ``voxel_resolution``, its own ``training_step`` and ``configure_optimizers`` (the working
            folder is importable). Such a class is built with ``model_kwargs`` alone.
        preset: the preset of a registered model (``"tiny"`` on a laptop, ``"paper"`` for the published
            configuration); not passed to a model given as a class path.
        data: a ShapeNet-VTR directory; ``None`` uses the embedded procedural dataset.
        pretrain_epochs: epochs on Aligned before any view strategy (the paper's pre-trained model).
        finetune_epochs: epochs of fine-tuning, the same for every strategy (including none).
        batch_size: training and test batch size.
        num_workers: data-loading worker processes.
        image_size: input image side in pixels; ``None`` takes the preset's.
        fraction: share of training objects the callback gives new views per selection (its ``fraction``).
        seed: random seed of the models, data and callbacks.
        accelerator: the Trainer's ``accelerator``.
        devices: the Trainer's ``devices``; a string of digits (from a command line) becomes an int.
        precision: the Trainer's ``precision``.
        out: where runs are written.
        recipe: the training images' recipe (``VTRDataModule(recipe=...)``): ``"plain"`` (composite on white,
            ImageNet normalisation; the default), ``"reference"`` (the model's published recipe, its class's
            ``image_recipe``: ``"pix2vox"`` or ``"lrgt"``) or a name of :data:`~lightning_vtr.data.IMAGE_RECIPES`.
        test_repeats: view sets per test object, each a fixed choice of the model's ``num_views`` views of the
            tested view set (``VTRDataModule(test_repeats=...)``); the same for every strategy of a seed, so
            differences between strategies are paired. More repeats cut the variance of a test mean cheaply.
        embedded: options of the embedded procedural dataset (``data=None``).
        finetune_lr: learning-rate schedule of fine-tuning, the same for every strategy: ``"cosine"``
            anneals each parameter group's rate from the model's own value to 0 over ``finetune_epochs``
            (:class:`~lightning_vtr.experiments.training.CosineFineTuning`), so the tested weights are not one
            noisy step of a constant rate; ``"constant"`` keeps the model's scheduler.
        model_kwargs: extra arguments of the model class.
        trainer_kwargs: extra ``L.Trainer`` arguments of every fit and test (e.g. ``limit_train_batches``);
            they override the harness's defaults, except ``devices=1`` of the evaluation.

    Raises:
        ValueError: ``finetune_lr`` or ``recipe`` is not a known name, or ``test_repeats`` is below 1.
        TypeError: ``test_repeats`` is not an int.

    Example:
        >>> config = ExperimentConfig(model="lrgt", pretrain_epochs=100, finetune_epochs=50, devices="2")
        >>> config.devices, config.out
        (2, 'runs/vtr')
    """

    model: str = field(
        default="pix2vox",
        metadata=flag("reconstruction model: pix2vox, lrgt or your LightningModule as module.Class (from this folder)"),
    )
    preset: str = field(
        default="tiny", metadata=flag("preset of pix2vox / lrgt: tiny, or paper (the published configuration)")
    )
    data: str | None = field(
        default=None,
        metadata=flag("ShapeNet-VTR directory", default_text="the embedded procedural dataset"),
    )
    pretrain_epochs: int = field(default=16, metadata=flag("epochs on Aligned before fine-tuning", minimum=1))
    finetune_epochs: int = field(default=12, metadata=flag("fine-tuning epochs per strategy", minimum=1))
    batch_size: int = field(default=8, metadata=flag("batch size", minimum=1))
    num_workers: int = field(default=0, metadata=flag("data-loading worker processes", minimum=0))
    image_size: int | None = field(
        default=None, metadata=flag("input image size (pixels)", minimum=1, default_text="the preset's")
    )
    fraction: float = field(
        default=0.05, metadata=flag("share of training objects given new views per selection, in (0, 1]")
    )
    seed: int = field(default=0, metadata=flag("random seed"))
    accelerator: str = field(default="auto", metadata=flag("Trainer accelerator"))
    devices: int | str = field(default=1, metadata=flag("Trainer devices"))
    precision: str = field(default="32-true", metadata=flag("Trainer precision"))
    finetune_lr: str = field(
        default="cosine",
        metadata=flag(
            "fine-tuning learning-rate schedule: annealed to 0 or the model's own", choices=FINETUNE_LR_SCHEDULES
        ),
    )
    test_repeats: int = field(
        default=1,
        metadata=flag(
            "fixed view sets each test object is tested on, the same for every strategy of a seed", minimum=1
        ),
    )
    recipe: str = field(
        default="plain",
        metadata=flag(
            "training-image recipe: reference (the model's published one) or a named recipe", choices=RECIPES
        ),
    )
    out: str = field(default="runs/vtr", metadata=flag("output directory"))
    embedded: dict[str, Any] = field(default_factory=dict)
    model_kwargs: dict[str, Any] = field(default_factory=dict)
    trainer_kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from lightning_vtr.utils.validation import check_choice, check_int

        check_choice("finetune_lr", self.finetune_lr, FINETUNE_LR_SCHEDULES)
        check_choice("recipe", self.recipe, RECIPES)
        check_int("test_repeats", self.test_repeats, minimum=1)
        if isinstance(self.devices, str) and self.devices.isdigit():
            self.devices = int(self.devices)
