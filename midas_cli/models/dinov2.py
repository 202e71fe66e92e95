"""DINOv2 ViT-S/14 (Oquab et al. 2023) image encoder in plain torch.

Parameter names match the facebookresearch/dinov2 checkpoints (``dinov2_vits14_pretrain.pth``):
``cls_token``, ``pos_embed`` (1, 1 + 37*37, 384), ``mask_token``, ``patch_embed.proj``,
``blocks.{i}.norm1``, ``blocks.{i}.attn.qkv``/``attn.proj``, ``blocks.{i}.ls1.gamma``, ``blocks.{i}.norm2``,
``blocks.{i}.mlp.fc1``/``mlp.fc2``, ``blocks.{i}.ls2.gamma``, ``norm``. ``features`` returns the
normalised CLS token (``x_norm_clstoken`` in the original), 384-d. The position code, learned for a
37x37 patch grid (518 px), is resized bicubically to the input's grid (the original adds a small
0.1 offset to the scale factor; resizing to the exact grid size differs from it by well under a
pixel of position).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class ViTConfig:
    patch: int = 14
    dim: int = 384
    depth: int = 12
    heads: int = 6
    mlp_ratio: float = 4.0
    grid: int = 37  # patches per side the position code was learned for


class PatchEmbed(nn.Module):
    def __init__(self, cfg: ViTConfig) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, cfg.dim, cfg.patch, stride=cfg.patch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)  # (B, D, h, w) -> (B, D, h*w) -> (B, h*w, D)


class Attention(nn.Module):
    def __init__(self, cfg: ViTConfig) -> None:
        super().__init__()
        self.heads = cfg.heads
        self.qkv = nn.Linear(cfg.dim, 3 * cfg.dim)
        self.proj = nn.Linear(cfg.dim, cfg.dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)  # (3, B, H, N, d_h)
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])  # (B, H, N, d_h)
        return self.proj(out.transpose(1, 2).reshape(b, n, d))  # (B, H, N, d_h) -> (B, N, D)


class Mlp(nn.Module):
    def __init__(self, cfg: ViTConfig) -> None:
        super().__init__()
        hidden = int(cfg.dim * cfg.mlp_ratio)
        self.fc1 = nn.Linear(cfg.dim, hidden)
        self.fc2 = nn.Linear(hidden, cfg.dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), 1e-5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    def __init__(self, cfg: ViTConfig) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(cfg.dim, eps=1e-6)
        self.attn = Attention(cfg)
        self.ls1 = LayerScale(cfg.dim)
        self.norm2 = nn.LayerNorm(cfg.dim, eps=1e-6)
        self.mlp = Mlp(cfg)
        self.ls2 = LayerScale(cfg.dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoV2(nn.Module):
    """Input (B, 3, H, W) ImageNet-normalised RGB, H and W multiples of the patch size."""

    def __init__(self, cfg: ViTConfig = ViTConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.patch_embed = PatchEmbed(cfg)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, cfg.dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.grid * cfg.grid, cfg.dim))
        self.mask_token = nn.Parameter(torch.zeros(1, cfg.dim))  # used only in pre-training; kept for loading
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(cfg.dim, eps=1e-6)
        self.feature_dim = cfg.dim

    def positions(self, h: int, w: int) -> torch.Tensor:
        """(1, 1 + h*w, D) position code for an h x w patch grid."""
        cls_pos, grid_pos = self.pos_embed[:, :1], self.pos_embed[:, 1:]
        if (h, w) == (self.cfg.grid, self.cfg.grid):
            return self.pos_embed
        side = int(math.sqrt(grid_pos.shape[1]))
        grid = grid_pos.reshape(1, side, side, -1).permute(0, 3, 1, 2)  # (1, N, D) -> (1, D, s, s)
        grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
        return torch.cat([cls_pos, grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)], dim=1)  # (1, 1+h*w, D)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, D) normalised CLS token."""
        h, w = x.shape[2] // self.cfg.patch, x.shape[3] // self.cfg.patch
        tokens = self.patch_embed(x)  # (B, h*w, D)
        tokens = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), tokens], dim=1) + self.positions(h, w)
        for block in self.blocks:
            tokens = block(tokens)
        return self.norm(tokens)[:, 0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)
