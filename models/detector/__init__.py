"""Stage 1: the centre detector (EfficientNet-style backbone, BiFPN neck, CenterNet heads).

Importing this package registers ``centre_detector`` and ``centre_detector_tiny`` with
:mod:`models.registry`.
"""

from models.detector.bifpn import BiFPN, BiFPNNeck
from models.detector.centernet import CentreNetHead, focal_loss
from models.detector.centre_detector import (
    SMALLER_VARIANT,
    VARIANTS,
    CentreDetector,
    build_centre_detector,
    build_centre_detector_tiny,
)
from models.detector.efficientnet import B0_STAGES, EfficientNetBackbone, MBConvStage, build_efficientnet
from models.detector.targets import CentreTargets, build_centre_targets, render_heatmap

__all__ = [
    "B0_STAGES",
    "SMALLER_VARIANT",
    "VARIANTS",
    "BiFPN",
    "BiFPNNeck",
    "CentreDetector",
    "CentreNetHead",
    "CentreTargets",
    "EfficientNetBackbone",
    "MBConvStage",
    "build_centre_detector",
    "build_centre_detector_tiny",
    "build_centre_targets",
    "build_efficientnet",
    "focal_loss",
    "render_heatmap",
]
