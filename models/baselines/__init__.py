"""The 2-D baselines of docs/design.md section 9: U-Net (one per view), TMVA-Net and SMVA-Net.

Importing this package registers ``unet``, ``tmvanet``, ``smvanet`` and their ``*_tiny`` variants with
:mod:`models.registry` (see :mod:`models.baselines.builders`).
"""

from models.baselines.builders import (
    build_smvanet,
    build_smvanet_tiny,
    build_tmvanet,
    build_tmvanet_tiny,
    build_unet,
    build_unet_tiny,
)
from models.baselines.losses import (
    MultiViewLoss,
    class_weights_from_counts,
    coherence_loss,
    soft_dice_loss,
)
from models.baselines.mvnet import MultiViewNet
from models.baselines.unet import UNet

__all__ = [
    "MultiViewLoss",
    "MultiViewNet",
    "UNet",
    "build_smvanet",
    "build_smvanet_tiny",
    "build_tmvanet",
    "build_tmvanet_tiny",
    "build_unet",
    "build_unet_tiny",
    "class_weights_from_counts",
    "coherence_loss",
    "soft_dice_loss",
]
