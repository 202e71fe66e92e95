"""ResNet-50 (He et al. 2016, torchvision's "v1.5": stride on the 3x3 convolution) in plain torch.

Parameter and buffer names match torchvision's ``resnet50`` state dict (``conv1``, ``bn1``,
``layer{1-4}.{i}.conv{1-3}``/``bn{1-3}``/``downsample.{0,1}``, ``fc``), so an official checkpoint
(e.g. ``resnet50-11ad3fa6.pth``) loads with ``load_state_dict(strict=True)``. ``features`` returns the
2048-d global-average-pooled embedding used as per-frame image features.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class ResNetConfig:
    layers: tuple[int, ...] = (3, 4, 6, 3)
    width: int = 64
    n_classes: int = 1000


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, in_planes: int, planes: int, stride: int) -> None:
        super().__init__()
        out_planes = planes * self.expansion
        self.conv1 = nn.Conv2d(in_planes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, out_planes, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out_planes)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = None
        if stride != 1 or in_planes != out_planes:
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, out_planes, 1, stride=stride, bias=False),
                                            nn.BatchNorm2d(out_planes))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        h = self.relu(self.bn1(self.conv1(x)))
        h = self.relu(self.bn2(self.conv2(h)))
        return self.relu(self.bn3(self.conv3(h)) + identity)


class ResNet(nn.Module):
    """Input (B, 3, H, W) ImageNet-normalised RGB; ``forward`` -> logits (B, n_classes)."""

    def __init__(self, cfg: ResNetConfig = ResNetConfig()) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, cfg.width, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(cfg.width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        in_planes = cfg.width
        for index, blocks in enumerate(cfg.layers):
            planes = cfg.width * 2 ** index
            stage = [Bottleneck(in_planes, planes, 1 if index == 0 else 2)]
            stage += [Bottleneck(planes * 4, planes, 1) for _ in range(blocks - 1)]
            setattr(self, f"layer{index + 1}", nn.Sequential(*stage))
            in_planes = planes * 4
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(in_planes, cfg.n_classes)
        self.feature_dim = in_planes

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, 2048) pooled embedding."""
        h = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        for index in range(1, 5):
            h = getattr(self, f"layer{index}")(h)
        return torch.flatten(self.avgpool(h), 1)  # (B, C, 1, 1) -> (B, C)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.features(x))
