"""MinkUNet: a residual sparse U-Net labelling every input voxel (docs/design.md section 7).

Layout (widths w0..w8): stem of two 3^3 convs to w0; four encoder stages, each a 2^3 stride-2 conv then
2 residual blocks (to w1..w4, tensor strides 2..16); four decoder stages, each a 2^3 transposed conv to
w5..w8, concatenation with the encoder tensor of the same stride and 2 residual blocks; a linear
classifier per voxel.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Self

from torch import Tensor, nn

from models.capabilities import InputShapes, Stage
from models.segmenter.blocks import DownBlock, UpBlock, submanifold_bn_relu
from models.sparse import PointwiseConv, SparseTensor

BASE_WIDTHS: tuple[int, ...] = (32, 32, 64, 128, 256, 256, 128, 96, 96)
"""Stage widths at ratio 1: stem, four encoder stages, four decoder stages."""


def scaled_widths(ratio: float) -> tuple[int, ...]:
    """`BASE_WIDTHS` times `ratio`, each truncated to an integer (at least 1), as spvnas/torchsparse do.

    At ratio 0.37 this gives widths (11, 11, 23, 47, 94, 94, 47, 35, 35) and 2,920,060 parameters with
    4 input features and 5 classes (the paper: 2.93 M); rounding to nearest would give 2,990,999.

    Raises:
        ValueError: a non-positive ratio.
    """
    if ratio <= 0:
        raise ValueError(f"ratio must be > 0, got {ratio}")
    # The epsilon keeps exact products (256 x 0.375 = 96) from truncating one below on float error.
    return tuple(max(1, int(width * ratio + 1e-9)) for width in BASE_WIDTHS)


class MinkUNet(nn.Module):
    """Residual sparse U-Net.

    `forward(x)` maps a `SparseTensor` with features (N, in_channels) at tensor stride 1 to logits
    (N, num_classes), row `i` for voxel `x.coords[i]`.
    """

    stage: ClassVar[Stage] = Stage.SEGMENTER
    channel_tracer: ClassVar[str] = "sparse_unet"

    def make_input(self, coords: Tensor, feats: Tensor) -> SparseTensor:
        """Input for ROI points: ``coords`` (N, 4) int64 (batch, range, angle, Doppler bins), ``feats`` (N, F)."""
        return SparseTensor(coords, feats)

    def dense_input_shapes(self, profile: Any) -> InputShapes | None:
        """None: the cost depends on the ROI (count a real forward with ``MacRecorder``)."""
        return None

    def __init__(
        self,
        *,
        in_channels: int,
        num_classes: int,
        widths: Sequence[int] = BASE_WIDTHS,
        blocks_per_stage: int = 2,
    ) -> None:
        """Build the network.

        Args:
            in_channels: features per input voxel (4: x, y, radial velocity, normalised log power).
            num_classes: output classes, background included.
            widths: 9 stage widths (stem, encoder 1-4, decoder 1-4).
            blocks_per_stage: residual blocks per encoder/decoder stage.

        Raises:
            ValueError: a bad width list or count.
        """
        super().__init__()
        widths = tuple(int(w) for w in widths)
        if len(widths) != 9 or min(widths) < 1:
            raise ValueError(f"widths must be 9 positive ints (stem, 4 encoder, 4 decoder), got {widths}")
        if in_channels < 1 or num_classes < 1 or blocks_per_stage < 1:
            raise ValueError(
                f"in_channels, num_classes and blocks_per_stage must be >= 1, got "
                f"{in_channels}, {num_classes}, {blocks_per_stage}"
            )
        self.config: dict[str, Any] = {
            "in_channels": in_channels,
            "num_classes": num_classes,
            "widths": list(widths),
            "blocks_per_stage": blocks_per_stage,
        }
        stem_width, encoder_widths, decoder_widths = widths[0], widths[1:5], widths[5:]
        self.stem = nn.Sequential(
            submanifold_bn_relu(in_channels, stem_width), submanifold_bn_relu(stem_width, stem_width)
        )
        encoder_in = (stem_width, *encoder_widths[:-1])
        self.encoder = nn.ModuleList(
            DownBlock(c_in, c_out, num_blocks=blocks_per_stage)
            for c_in, c_out in zip(encoder_in, encoder_widths, strict=True)
        )
        # Decoder stage i up-samples to the stride of encoder output 3 - i (the stem for the last one).
        skip_widths = (*encoder_widths[:-1][::-1], stem_width)
        decoder_in = (encoder_widths[-1], *decoder_widths[:-1])
        self.decoder = nn.ModuleList(
            UpBlock(c_in, c_skip, c_out, num_blocks=blocks_per_stage)
            for c_in, c_skip, c_out in zip(decoder_in, skip_widths, decoder_widths, strict=True)
        )
        self.classifier = PointwiseConv(decoder_widths[-1], num_classes, bias=True)
        self.add_branches(widths)

    def add_branches(self, widths: tuple[int, ...]) -> None:
        """Modules a subclass adds beside the U-Net, built last from the 9 checked stage widths; none here.

        `SPVCNN` adds its point MLPs here, so both networks share this constructor and its checks.
        """

    @classmethod
    def from_ratio(cls, ratio: float, *, in_channels: int = 4, num_classes: int = 5, blocks_per_stage: int = 2) -> Self:
        """The paper's preset: widths `[32,32,64,128,256,256,128,96,96] x ratio` (0.37 -> 2.92 M params).

        Called on `SPVCNN` it builds an SPVCNN with the same widths. Small ratios (0.1) are the tiny
        test variants.
        """
        return cls(
            in_channels=in_channels,
            num_classes=num_classes,
            widths=scaled_widths(ratio),
            blocks_per_stage=blocks_per_stage,
        )

    def encode(self, x: SparseTensor) -> list[SparseTensor]:
        """Stem and encoder: [stem output at stride 1, stage outputs at strides 2, 4, 8, 16]."""
        x.cache.build_pyramid(x.stride, len(self.encoder) + 1)  # every level's kernel maps in one compiled pass
        features = [self.stem(x)]
        for stage in self.encoder:
            features.append(stage(features[-1]))
        return features

    def forward(self, x: SparseTensor) -> Tensor:
        """Logits (N, num_classes) for the N voxels of `x` (features (N, in_channels), stride 1)."""
        *skips, y = self.encode(x)
        for stage, skip in zip(self.decoder, reversed(skips), strict=True):
            y = stage(y, skip)
        return self.classifier(y.feats)
