"""Image encoders: uint8 images [..., C, H, W] -> features [..., features_dim], scaled by 1/255
inside the network (rollouts and exported policies keep uint8).

- ``NatureCNN`` (``policy.encoder.name=nature``): the DQN paper's network, SB3's ``NatureCNN`` and
  CleanRL's ``ppo_atari`` encoder: Conv 32x8x8/4, Conv 64x4x4/2, Conv 64x3x3/1 (ReLU after each),
  flatten, Linear 512, ReLU. The conv stack is TorchRL's ``ConvNet``.
- ``ImpalaCNN`` (``policy.encoder.name=impala``): Espeholt et al. (2018)'s ResNet as CleanRL's
  ``ppo_procgen`` writes it: per stage Conv 3x3 (padding 1), MaxPool 3/2 (padding 1) and two residual
  blocks (x + Conv(ReLU(Conv(ReLU(x))))), stages of 16, 32, 32 channels; then ReLU, flatten,
  Linear 256, ReLU. Plain torch: TorchRL's ``ImpalaNet`` blocks apply an in-place ReLU to the
  block's input, so their residual adds ReLU(x), not x, and they are lazily shaped.

With ``policy.ortho_init`` every Conv2d and Linear is initialised orthogonally with gain sqrt(2) and
zero bias, as SB3's ``ActorCriticPolicy`` does for its features extractor (CleanRL's
``layer_init``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torch._C._functorch import is_batchedtensor
from torch.nn import functional as F
from torchrl.modules import ConvNet

from rlexp.config.schema import EncoderConfig

#: ``policy.encoder.name`` -> (default channels, default features_dim)
DEFAULTS: dict[str, tuple[tuple[int, ...], int]] = {
    "nature": ((32, 64, 64), 512),
    "impala": ((16, 32, 32), 256),
}
NATURE_KERNELS = (8, 4, 3)
NATURE_STRIDES = (4, 2, 1)


class NatureCNN(nn.Module):
    """The Nature DQN CNN (SB3 / CleanRL Atari): uint8 [..., C, H, W] -> ReLU(Linear(convs(x/255)))."""

    def __init__(
        self,
        in_shape: Sequence[int],
        channels: Sequence[int] = DEFAULTS["nature"][0],
        kernel_sizes: Sequence[int] = NATURE_KERNELS,
        strides: Sequence[int] = NATURE_STRIDES,
        features_dim: int = DEFAULTS["nature"][1],
    ) -> None:
        super().__init__()
        c, h, w = (int(x) for x in in_shape)
        self.in_shape = (c, h, w)
        self.features_dim = int(features_dim)
        self.convs = ConvNet(
            in_features=c,
            num_cells=list(channels),
            kernel_sizes=list(kernel_sizes),
            strides=list(strides),
            paddings=0,
            activation_class=nn.ReLU,
        )
        with torch.no_grad():
            flat = int(self.convs(torch.zeros(1, c, h, w)).shape[-1])
        self.linear = nn.Linear(flat, self.features_dim)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        batch = image.shape[:-3]
        x = F.relu(self.linear(self.convs(scaled(image))))
        return x.reshape(*batch, self.features_dim)


def scaled(image: torch.Tensor) -> torch.Tensor:
    """uint8 images [..., C, H, W] -> float32 [N, C, H, W] / 255, the encoders' input. On the CPU in
    channels-last memory (the uint8 tensor made so, 4x less to move than the float one; no copy
    where it already is, ``channels_last_images``): oneDNN's fast layout for these convolutions
    (one torch thread, 256 frames: a Nature CNN forward and backward on 84x84x4 ~25% faster,
    IMPALA's on 64x64x3 ~30%, its forward 2.5x). The same values: only the order of the
    convolutions' sums differs (float rounding). Not under ``vmap`` (TorchRL's GAE with a value
    network), which has no memory formats. There a uint8 image is cast and divided in one pass
    (``torch.div`` computes in float32: the same values, bit for bit, as the cast followed by the
    division, without a float32 intermediate to write and read again), eagerly; traced or compiled
    (export, ``algorithm.compile``) the graph keeps the cast and the division it had."""
    x = image.reshape(-1, *image.shape[-3:])
    if x.device.type == "cpu" and not is_batchedtensor(x):
        x = x.contiguous(memory_format=torch.channels_last)
        if x.dtype == torch.uint8 and not (torch.jit.is_tracing() or torch.compiler.is_compiling()):
            return torch.div(x, 255.0)
    return x.to(torch.float32) / 255.0


def channels_last_images(data: TensorDictBase | torch.Tensor) -> TensorDictBase | torch.Tensor:
    """``data`` (a flattened rollout, or its observation) with every uint8 ``[N, C, H, W]`` entry on
    the CPU in channels-last memory (``scaled``'s layout), everything else as it is (a tensor is
    returned unchanged). Made once per update, the minibatches gathered from it keep the layout
    (indexing preserves it), so ``scaled`` no longer converts every minibatch: one pass over the
    rollout's images per update instead of one per minibatch and epoch. Values are untouched."""
    if not isinstance(data, TensorDictBase):
        return data

    def layout(x: torch.Tensor) -> torch.Tensor:
        if x.dtype == torch.uint8 and x.dim() == 4 and x.device.type == "cpu":
            return x.contiguous(memory_format=torch.channels_last)
        return x

    return data.apply(layout)


class ResidualBlock(nn.Module):
    """x + Conv(ReLU(Conv(ReLU(x)))), 3x3 convs keeping the channels and the size."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv0 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv1(F.relu(self.conv0(F.relu(x))))


class ConvSequence(nn.Module):
    """One IMPALA stage: Conv 3x3, MaxPool 3/2 (halves H and W, rounding up), residual blocks."""

    def __init__(self, in_channels: int, out_channels: int, num_blocks: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.blocks = nn.Sequential(*(ResidualBlock(out_channels) for _ in range(num_blocks)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.max_pool2d(self.conv(x), kernel_size=3, stride=2, padding=1)
        return self.blocks(x)


class ImpalaCNN(nn.Module):
    """The IMPALA ResNet (CleanRL ``ppo_procgen``): uint8 [..., C, H, W] -> features."""

    def __init__(
        self,
        in_shape: Sequence[int],
        channels: Sequence[int] = DEFAULTS["impala"][0],
        num_res_blocks: int = 2,
        features_dim: int = DEFAULTS["impala"][1],
    ) -> None:
        super().__init__()
        c, h, w = (int(x) for x in in_shape)
        self.in_shape = (c, h, w)
        self.features_dim = int(features_dim)
        stages = []
        for out in channels:
            stages.append(ConvSequence(c, int(out), num_res_blocks))
            c, h, w = int(out), (h + 1) // 2, (w + 1) // 2
        self.stages = nn.Sequential(*stages)
        self.linear = nn.Linear(c * h * w, self.features_dim)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        batch = image.shape[:-3]
        x = F.relu(self.stages(scaled(image))).flatten(1)
        return F.relu(self.linear(x)).reshape(*batch, self.features_dim)


#: ``policy.encoder.name`` -> its class (rlexp.config.rules.ENCODERS lists the same names)
ENCODERS: dict[str, type[nn.Module]] = {"nature": NatureCNN, "impala": ImpalaCNN}


def make_encoder(
    cfg: EncoderConfig, in_shape: Sequence[int], ortho_init: bool = True, where: str = ""
) -> nn.Module:
    """The configured encoder for images of CHW shape ``in_shape`` (``where``: the image's key, for
    errors); a size the convs shrink to nothing is one line naming the settings."""
    if cfg.name not in ENCODERS:
        raise ValueError(f"policy.encoder.name={cfg.name!r}; choose from {sorted(ENCODERS)}")
    default_channels, default_features = DEFAULTS[cfg.name]
    channels = tuple(cfg.channels or default_channels)
    features = int(cfg.features_dim or default_features)
    try:
        if cfg.name == "nature":
            kernels = tuple(cfg.kernel_sizes or NATURE_KERNELS)
            strides = tuple(cfg.strides or NATURE_STRIDES)
            if not len(channels) == len(kernels) == len(strides):
                raise ValueError(
                    f"policy.encoder.channels={list(channels)}, kernel_sizes={list(kernels)} and "
                    f"strides={list(strides)} must have one entry per conv layer each"
                )
            encoder: nn.Module = NatureCNN(in_shape, channels, kernels, strides, features)
        else:
            encoder = ImpalaCNN(in_shape, channels, cfg.num_res_blocks, features)
    except RuntimeError as exc:  # the convs shrink the image below one pixel
        raise ValueError(
            f"policy.encoder={cfg.name} cannot encode the image{where} of shape "
            f"{list(in_shape)} (C, H, W): {str(exc).splitlines()[0]}; use smaller "
            "policy.encoder.kernel_sizes / strides or a larger image"
        ) from None
    if ortho_init:
        for module in encoder.modules():
            if isinstance(module, nn.Conv2d | nn.Linear):
                nn.init.orthogonal_(module.weight, gain=math.sqrt(2))
                nn.init.zeros_(module.bias)
    return encoder
