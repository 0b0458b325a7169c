"""The CNN image encoders (policies/encoders.py) against plain-torch references written here from
the published networks (SB3's NatureCNN / CleanRL's ppo_atari encoder, CleanRL's ppo_procgen IMPALA
ResNet), with non-default channels, kernels, strides, feature sizes and non-square images; the
config that selects them."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn
from torch.nn import functional as F

from conftest import compose
from rlexp.config.rules import ENCODERS as RULE_ENCODERS
from rlexp.config.schema import EncoderConfig
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.policies.encoders import ENCODERS, ImpalaCNN, NatureCNN, make_encoder


def _images(*shape: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, shape, dtype=torch.uint8, generator=g)


class ReferenceNature(nn.Module):
    """SB3's NatureCNN, generalised to any conv stack: Conv/ReLU..., Flatten, Linear, ReLU on x/255."""

    def __init__(self, c, channels, kernels, strides, flat, features):
        super().__init__()
        layers, last = [], c
        for out, k, s in zip(channels, kernels, strides, strict=True):
            layers += [nn.Conv2d(last, out, k, stride=s, padding=0), nn.ReLU()]
            last = out
        self.cnn = nn.Sequential(*layers, nn.Flatten())
        self.linear = nn.Sequential(nn.Linear(flat, features), nn.ReLU())

    def forward(self, x):
        return self.linear(self.cnn(x.float() / 255.0))


class RefResidualBlock(nn.Module):  # CleanRL ppo_procgen.py, verbatim in structure
    def __init__(self, channels):
        super().__init__()
        self.conv0 = nn.Conv2d(channels, channels, kernel_size=3, padding=1)
        self.conv1 = nn.Conv2d(channels, channels, kernel_size=3, padding=1)

    def forward(self, x):
        inputs = x
        x = F.relu(x)
        x = self.conv0(x)
        x = F.relu(x)
        x = self.conv1(x)
        return x + inputs


class RefConvSequence(nn.Module):
    def __init__(self, in_channels, out_channels, blocks):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1)
        self.res = nn.ModuleList(RefResidualBlock(out_channels) for _ in range(blocks))

    def forward(self, x):
        x = self.conv(x)
        x = F.max_pool2d(x, kernel_size=3, stride=2, padding=1)
        for block in self.res:
            x = block(x)
        return x


class ReferenceImpala(nn.Module):
    def __init__(self, c, channels, blocks, flat, features):
        super().__init__()
        seqs, last = [], c
        for out in channels:
            seqs.append(RefConvSequence(last, out, blocks))
            last = out
        self.network = nn.Sequential(
            *seqs, nn.Flatten(), nn.ReLU(), nn.Linear(flat, features), nn.ReLU()
        )

    def forward(self, x):
        return self.network(x / 255.0)


def _copy_params(src: nn.Module, dst: nn.Module) -> None:
    """Every parameter of ``src`` into ``dst``, in registration order (the same layers)."""
    a, b = list(src.parameters()), list(dst.parameters())
    assert [p.shape for p in a] == [p.shape for p in b]
    with torch.no_grad():
        for p, q in zip(a, b, strict=True):
            q.copy_(p)


def test_nature_cnn_equals_the_plain_torch_network_with_other_settings():
    """Two conv layers 16x5x5/3 and 24x3x3/1, 40 features, 3x50x42 images, two batch dims."""
    cfg = EncoderConfig(
        name="nature", channels=[16, 24], kernel_sizes=[5, 3], strides=[3, 1], features_dim=40
    )
    torch.manual_seed(3)
    enc = make_encoder(cfg, (3, 50, 42))
    assert isinstance(enc, NatureCNN) and enc.features_dim == 40
    # H: (50 - 5) // 3 + 1 = 16, then 14; W: (42 - 5) // 3 + 1 = 13, then 11
    assert enc.linear.in_features == 24 * 14 * 11 == 3696
    ref = ReferenceNature(3, [16, 24], [5, 3], [3, 1], 3696, 40)
    _copy_params(enc, ref)
    x = _images(2, 5, 3, 50, 42)
    out = enc(x)
    assert out.shape == (2, 5, 40) and out.dtype == torch.float32
    want = ref(x.reshape(10, 3, 50, 42)).reshape(2, 5, 40)
    torch.testing.assert_close(out, want, rtol=1e-5, atol=1e-6)
    assert (out > 0).any() and (out >= 0).all()  # ReLU after the Linear


def test_nature_cnn_defaults_are_the_atari_network():
    """84x84x4 Atari frames: 32x8x8/4 -> 20x20, 64x4x4/2 -> 9x9, 64x3x3/1 -> 7x7: 3136 -> 512."""
    enc = make_encoder(EncoderConfig(), (4, 84, 84))
    convs = [m for m in enc.modules() if isinstance(m, nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size[0], c.stride[0]) for c in convs] == [
        (32, 8, 4),
        (64, 4, 2),
        (64, 3, 1),
    ]
    assert (enc.linear.in_features, enc.linear.out_features) == (3136, 512)
    assert sum(p.numel() for p in enc.parameters()) == 1_684_128  # SB3's NatureCNN on 4x84x84


def test_impala_cnn_equals_cleanrls_network_with_other_settings():
    """Stages of 8 and 12 channels, one residual block each, 24 features, 2x30x21 images."""
    cfg = EncoderConfig(name="impala", channels=[8, 12], num_res_blocks=1, features_dim=24)
    torch.manual_seed(5)
    enc = make_encoder(cfg, (2, 30, 21))
    assert isinstance(enc, ImpalaCNN)
    # each stage halves rounding up: 30 -> 15 -> 8, 21 -> 11 -> 6
    assert enc.linear.in_features == 12 * 8 * 6 == 576
    ref = ReferenceImpala(2, [8, 12], 1, 576, 24)
    _copy_params(enc, ref)
    x = _images(7, 2, 30, 21, seed=1)
    out = enc(x)
    assert out.shape == (7, 24)
    torch.testing.assert_close(out, ref(x.float()), rtol=1e-5, atol=1e-6)
    # one image without a batch dim, and a time dim, give the same features
    torch.testing.assert_close(enc(x[0]), out[0])
    torch.testing.assert_close(enc(x.reshape(1, 7, 2, 30, 21))[0], out)


def test_impala_residual_adds_the_blocks_input_not_its_relu():
    """TorchRL's ImpalaNet block applies an in-place ReLU to its input: a negative input then
    differs. Ours is x + f(x) with x as it came (CleanRL / Espeholt)."""
    enc = make_encoder(EncoderConfig(name="impala", channels=[4]), (1, 6, 6))
    block = enc.stages[0].blocks[0]
    x = -torch.ones(1, 4, 3, 3)
    with torch.no_grad():
        for p in block.parameters():
            p.zero_()
    torch.testing.assert_close(block(x), x)  # f(x) = 0: the input comes through, negative


def test_orthogonal_init_with_gain_sqrt2_and_zero_bias():
    enc = make_encoder(EncoderConfig(features_dim=32), (4, 36, 36), ortho_init=True)
    w = enc.linear.weight.detach()  # [32, in]: rows orthogonal, norm sqrt(2)
    torch.testing.assert_close(w @ w.T, 2.0 * torch.eye(32), atol=1e-4, rtol=0)
    conv = next(m for m in enc.modules() if isinstance(m, nn.Conv2d))
    flat = conv.weight.detach().reshape(conv.out_channels, -1)  # [32, 4*8*8]
    torch.testing.assert_close(flat @ flat.T, 2.0 * torch.eye(32), atol=1e-4, rtol=0)
    assert all(not m.bias.any() for m in enc.modules() if isinstance(m, nn.Conv2d | nn.Linear))
    plain = make_encoder(EncoderConfig(features_dim=32), (4, 36, 36), ortho_init=False)
    assert plain.linear.bias.abs().sum() > 0  # torch's default init (uniform bias)
    w = plain.linear.weight.detach()  # uniform(+-1/sqrt(64)): std 1/sqrt(3 * 64), not orthogonal
    assert math.isclose(float(w.std()), 1 / math.sqrt(3 * 64), rel_tol=0.2)


def test_an_image_too_small_for_the_convs_is_one_line():
    with pytest.raises(ValueError) as err:
        make_encoder(EncoderConfig(), (3, 20, 20), where=" 'pixels'")
    msg = str(err.value)
    assert len(msg.splitlines()) == 1
    assert msg.startswith(
        "policy.encoder=nature cannot encode the image 'pixels' of shape [3, 20, 20]"
    )


def test_the_config_lists_the_encoders_that_exist():
    assert sorted(RULE_ENCODERS) == sorted(ENCODERS)


@pytest.mark.parametrize("name", ["cnn", "impala"])
def test_the_shipped_cnn_policies_compose(name):
    cfg = to_root_config(compose([f"policy={name}"]))
    assert cfg.policy.encoder.name == ("nature" if name == "cnn" else name)
    assert cfg.policy.share_encoder and cfg.policy.actor.hidden_sizes == []


@pytest.mark.parametrize(
    ("overrides", "starts"),
    [
        (["policy.encoder.name=resnet"], "policy.encoder.name='resnet' must be one of"),
        (["policy.encoder.channels=[32,0]"], "policy.encoder.channels=[32, 0] must be"),
        (["policy.encoder.features_dim=0"], "policy.encoder.features_dim=0 must be"),
        (
            ["policy.encoder.channels=[32,64]"],
            "policy.encoder.channels=[32, 64], policy.encoder.kernel_sizes=None",
        ),
        (
            ["policy=impala", "policy.encoder.strides=[2,2,2]"],
            "policy.encoder.kernel_sizes / strides are the nature encoder's",
        ),
    ],
)
def test_a_bad_encoder_setting_is_refused_naming_the_key(overrides, starts):
    with pytest.raises(Exception) as err:
        to_root_config(compose(overrides))
    assert str(err.value).startswith(starts) or starts in str(err.value), str(err.value)
    if isinstance(err.value, ConfigError):
        assert len(str(err.value).splitlines()) == 1
