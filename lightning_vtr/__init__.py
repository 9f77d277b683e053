"""lightning_vtr: view transformation robustness for multi-view 3D object reconstruction."""

from lightning_vtr.protocol import ReconstructionModel, check_reconstruction_model

__version__ = "0.1.0"
__all__ = ["ReconstructionModel", "check_reconstruction_model", "__version__"]
