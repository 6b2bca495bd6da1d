"""The dual-branch refinement network of Stage II (no torchvision dependency).

- Image encoder: ResNet-50 (or ResNet-18 for CPU) whose parameter names match
  torchvision's `resnet50` / `resnet18`, so a local ImageNet checkpoint loads with
  `load_imagenet_weights`; random initialisation otherwise.
- Mask encoder: a light convolutional branch over the coarse label render (C soft channels:
  the composited weight of every label).
- Fusion: channel attention (squeeze-and-excitation) on each branch's features at every scale,
  then concatenation and a 1x1 projection.
- Decoder: U-Net style, upsampling from stride 32 with skip connections to full resolution.
- Output: C logits per pixel, plus `prior_scale * log(coarse)` so that an untrained student
  already answers with the coarse mask and training learns the corrections.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from sagonline.scene.io.checkpoints import load_user_checkpoint


def _conv_bn(cin: int, cout: int, k: int = 3, stride: int = 1) -> list[nn.Module]:
    return [
        nn.Conv2d(cin, cout, k, stride, k // 2, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    ]


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(
        self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None
    ):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        return self.relu(self.bn2(self.conv2(out)) + identity)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(
        self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None
    ):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        return self.relu(self.bn3(self.conv3(out)) + identity)


ARCHS: dict[str, tuple[type[BasicBlock] | type[Bottleneck], tuple[int, ...]]] = {
    "resnet18": (BasicBlock, (2, 2, 2, 2)),
    "resnet34": (BasicBlock, (3, 4, 6, 3)),
    "resnet50": (Bottleneck, (3, 4, 6, 3)),
}


class ResNetEncoder(nn.Module):
    """torchvision-compatible ResNet trunk returning features at strides 2, 4, 8, 16, 32."""

    def __init__(self, arch: str = "resnet50"):
        super().__init__()
        if arch not in ARCHS:
            raise ValueError(f"refine encoder {arch!r} is not one of {sorted(ARCHS)}")
        block, layers = ARCHS[arch]
        self.inplanes = 64
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = self._make(block, 64, layers[0])
        self.layer2 = self._make(block, 128, layers[1], 2)
        self.layer3 = self._make(block, 256, layers[2], 2)
        self.layer4 = self._make(block, 512, layers[3], 2)
        self.channels = [
            64,
            64 * block.expansion,
            128 * block.expansion,
            256 * block.expansion,
            512 * block.expansion,
        ]
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def _make(self, block, planes: int, blocks: int, stride: int = 1) -> nn.Sequential:
        down = None
        if stride != 1 or self.inplanes != planes * block.expansion:
            down = nn.Sequential(
                nn.Conv2d(self.inplanes, planes * block.expansion, 1, stride, bias=False),
                nn.BatchNorm2d(planes * block.expansion),
            )
        layers = [block(self.inplanes, planes, stride, down)]
        self.inplanes = planes * block.expansion
        layers += [block(self.inplanes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def forward(
        self,
        x,
    ) -> list[torch.Tensor]:  # 4 x [B, C_i, H / 2^(i+2), W / 2^(i+2)] features
        c1 = self.relu(self.bn1(self.conv1(x)))
        c2 = self.layer1(self.maxpool(c1))
        c3 = self.layer2(c2)
        c4 = self.layer3(c3)
        c5 = self.layer4(c4)
        return [c1, c2, c3, c4, c5]


def load_imagenet_weights(encoder: ResNetEncoder, path: str | Path) -> None:
    """Load a torchvision-format ResNet state dict (the classifier `fc.*` is ignored)."""
    path = Path(path)
    state = load_user_checkpoint(path, "refine.pretrained")
    state = state.get("state_dict", state) if isinstance(state, dict) else state
    if not isinstance(state, dict):
        raise ValueError(
            f"refine.pretrained={path}: holds a {type(state).__name__}, not a state dict"
        )
    state = {k.removeprefix("module."): v for k, v in state.items() if not k.startswith("fc.")}
    try:
        missing, unexpected = encoder.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches raise even when not strict
        raise RuntimeError(f"refine.pretrained={path} does not fit the encoder: {exc}") from exc
    if missing or unexpected:
        raise RuntimeError(
            f"refine.pretrained={path} does not fit the encoder: "
            f"{len(missing)} missing, {len(unexpected)} unexpected keys "
            f"(e.g. {(missing or unexpected)[:3]})"
        )


class ChannelAttention(nn.Module):
    """Squeeze-and-excitation: x * sigmoid(MLP(mean over pixels))."""

    def __init__(self, channels: int, reduction: int = 8):
        super().__init__()
        hidden = max(channels // reduction, 4)
        self.mlp = nn.Sequential(
            nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, channels)
        )

    def forward(self, x):
        w = torch.sigmoid(self.mlp(x.mean(dim=(2, 3))))
        return x * w[:, :, None, None]


class MaskEncoder(nn.Module):
    """Coarse mask (B, C, H, W) -> features at strides 2, 4, 8, 16, 32."""

    def __init__(self, num_classes: int, widths=(16, 32, 48, 64, 96)):
        super().__init__()
        stages, cin = [], num_classes
        for w in widths:
            stages.append(nn.Sequential(*_conv_bn(cin, w, 3, 2), *_conv_bn(w, w)))
            cin = w
        self.stages = nn.ModuleList(stages)
        self.channels = list(widths)

    def forward(
        self,
        m,
    ) -> list[torch.Tensor]:  # features per scale [B, C_i, H_i, W_i]
        feats = []
        for stage in self.stages:
            m = stage(m)
            feats.append(m)
        return feats


class DualBranchRefiner(nn.Module):
    """(rgb (B, 3, H, W) in [0, 1], coarse (B, C, H, W) label weights) -> logits (B, C, H, W)."""

    def __init__(
        self,
        num_classes: int,
        encoder: str = "resnet18",
        pretrained: str | Path | None = None,
        decoder_width: int = 32,
        prior_scale: float = 1.0,
    ):
        super().__init__()
        self.num_classes, self.prior_scale = num_classes, prior_scale
        self.image = ResNetEncoder(encoder)
        if pretrained:
            load_imagenet_weights(self.image, pretrained)
        self.mask = MaskEncoder(num_classes)
        self.att_img = nn.ModuleList(ChannelAttention(c) for c in self.image.channels)
        self.att_mask = nn.ModuleList(ChannelAttention(c) for c in self.mask.channels)
        self.fuse = nn.ModuleList(
            nn.Sequential(*_conv_bn(ci + cm, decoder_width, 1))
            for ci, cm in zip(self.image.channels, self.mask.channels, strict=True)
        )
        self.up = nn.ModuleList(
            nn.Sequential(*_conv_bn(2 * decoder_width, decoder_width)) for _ in range(4)
        )
        self.head = nn.Sequential(
            *_conv_bn(decoder_width + num_classes + 3, decoder_width),
            nn.Conv2d(decoder_width, num_classes, 1),
        )
        # Zero-initialised output: the untrained student answers exactly with the coarse mask.
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406])[None, :, None, None])
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225])[None, :, None, None])

    def forward(
        self,
        rgb: torch.Tensor,  # [B, 3, H, W]
        coarse: torch.Tensor,  # [B, C, H, W] smoothed one-hot
    ) -> torch.Tensor:  # [B, C, H, W] logits
        H, W = rgb.shape[-2:]
        ph, pw = (-H) % 32, (-W) % 32
        x = F.pad((rgb - self.mean) / self.std, (0, pw, 0, ph), mode="replicate")
        m = F.pad(coarse, (0, pw, 0, ph), mode="replicate")
        img_f, mask_f = self.image(x), self.mask(m)
        fused = [
            f(torch.cat([ai(a), am(b)], 1))
            for f, ai, am, a, b in zip(
                self.fuse, self.att_img, self.att_mask, img_f, mask_f, strict=True
            )
        ]
        y = fused[-1]
        for level in range(3, -1, -1):
            y = F.interpolate(y, size=fused[level].shape[-2:], mode="bilinear", align_corners=False)
            y = self.up[level](torch.cat([y, fused[level]], 1))
        y = F.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)
        logits = self.head(torch.cat([y, m, (x * self.std + self.mean)], 1))
        logits = logits + self.prior_scale * torch.log(m.clamp_min(1e-3))
        return logits[..., :H, :W]
