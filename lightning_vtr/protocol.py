"""The contract between a reconstruction model and the view-augmentation callback.

Any ``LightningModule`` that has these attributes and this method can be trained with
:class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`; the package's own Pix2Vox++ and
LRGT implement it, and a user's model can too (no inheritance needed).

Batches (what :class:`~lightning_vtr.data.VTRDataModule` yields) are dictionaries:

* ``"images"``: ``(B, V, 3, H, W)`` float, already transformed (resized, composited on the
  background, normalised) by the datamodule.
* ``"voxels"``: ``(B, R, R, R)`` float in {0, 1}, indexed per :mod:`lightning_vtr.geometry`.
* ``"viewpoints"``: ``(B, V, 2)`` (yaw, pitch) in degrees of each input image.
* ``"category"``: list of ``B`` category names; ``"object_id"``: list of ``B`` object ids.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:  # this module stays light: dataset build workers import VIEW_SETS without torch
    from torch import Tensor

__all__ = ["VIEW_SETS", "ReconstructionModel", "check_reconstruction_model"]

#: The paper's three view sets, in table order: training views (a fixed elevation) and the two test sets.
VIEW_SETS: tuple[str, ...] = ("aligned", "hemispherical", "spherical")


@runtime_checkable
class ReconstructionModel(Protocol):
    """What the callback needs from a multi-view voxel reconstruction model.

    Attributes:
        image_size: the square input size ``H = W`` the model expects, in pixels.
        num_views: the number of input views per sample it is trained with.
        voxel_resolution: ``R`` of its ``(B, R, R, R)`` output.
    """

    image_size: int
    num_views: int
    voxel_resolution: int

    def predict_voxels(self, images: Tensor) -> Tensor:
        """Occupancy probabilities ``(B, R, R, R)`` in ``[0, 1]`` for images ``(B, V, 3, H, W)``."""
        ...


def check_reconstruction_model(model: object) -> None:
    """Raise ``TypeError`` naming what is missing if ``model`` does not satisfy :class:`ReconstructionModel`."""
    missing = [name for name in ("image_size", "num_views", "voxel_resolution") if not hasattr(model, name)]
    if not callable(getattr(model, "predict_voxels", None)):
        missing.append("predict_voxels(images) -> (B, R, R, R)")
    if missing:
        raise TypeError(
            f"{type(model).__name__} does not satisfy lightning_vtr.ReconstructionModel: missing {', '.join(missing)}. "
            "Add these attributes and method (see lightning_vtr.protocol)."
        )
