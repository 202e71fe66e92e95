"""Image backbones in plain torch: official checkpoint key layouts, and `midas extract image-features`."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from helpers.cli import midas
from midas_cli.errors import ConfigError
from midas_cli.models.dinov2 import DinoV2
from midas_cli.models.image_features import MEAN, ExtractOptions, extract_features, preprocess
from midas_cli.models.resnet import ResNet

# Entries of torchvision's resnet50().state_dict() and of dinov2_vits14_pretrain.pth, with shapes.
RESNET_KEYS = {"conv1.weight": (64, 3, 7, 7), "bn1.running_var": (64,), "layer1.0.downsample.0.weight": (256, 64, 1, 1),
               "layer1.0.downsample.1.num_batches_tracked": (), "layer2.0.conv2.weight": (128, 128, 3, 3),
               "layer3.5.bn3.weight": (1024,), "layer4.2.conv3.weight": (2048, 512, 1, 1), "fc.weight": (1000, 2048)}
DINO_KEYS = {"cls_token": (1, 1, 384), "pos_embed": (1, 1370, 384), "mask_token": (1, 384),
             "patch_embed.proj.weight": (384, 3, 14, 14), "blocks.0.attn.qkv.weight": (1152, 384),
             "blocks.11.ls2.gamma": (384,), "blocks.5.mlp.fc1.weight": (1536, 384), "norm.bias": (384,)}


def test_resnet50_matches_torchvision_layout():
    state = ResNet().state_dict()
    assert len(state) == 320
    assert sum(p.numel() for p in ResNet().parameters()) == 25_557_032
    assert {k: tuple(state[k].shape) for k in RESNET_KEYS} == RESNET_KEYS
    assert "layer1.0.downsample.0.weight" in state and "layer1.1.downsample.0.weight" not in state


def test_dinov2_vits14_matches_official_layout_and_resizes_positions():
    model = DinoV2().eval()
    state = model.state_dict()
    assert {k: tuple(state[k].shape) for k in DINO_KEYS} == DINO_KEYS
    assert sum(p.numel() for p in model.parameters()) == 22_056_576
    assert model.positions(2, 3).shape == (1, 7, 384)
    with torch.no_grad():
        assert model.features(torch.zeros(2, 3, 28, 42)).shape == (2, 384)


def test_preprocess_normalises_like_imagenet():
    grey = np.zeros((120, 160, 3), np.uint8)
    grey[:] = np.round(MEAN[::-1] * 255).astype(np.uint8)  # BGR of the ImageNet mean colour
    x = preprocess(grey, resize=64, crop=56)
    assert x.shape == (3, 56, 56) and np.abs(x).max() < 0.02


def write_video(path: Path, n: int = 5) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (96, 72))
    for i in range(n):
        writer.write(np.full((72, 96, 3), 40 * i, np.uint8))
    writer.release()
    return path


def test_cli_extracts_resnet_features_from_user_weights(tmp_path):
    torch.manual_seed(0)
    weights = tmp_path / "resnet50-random.pth"
    torch.save(ResNet().state_dict(), weights)
    video = write_video(tmp_path / "clip.avi")
    out = tmp_path / "derived" / "image_features.npz"
    result = midas("extract", "image-features", str(video), "--backbone", "resnet50", "--weights", str(weights),
                   "--out", str(out), "--crop", "64", "--batch-size", "2", "--accelerator", "cpu", "--json",
                   check=True)
    assert json.loads(result.stdout)["frames"] == 5
    with np.load(out) as data:
        assert data["frame"].tolist() == [0, 1, 2, 3, 4]
        assert data["features"].shape == (5, 2048) and data["features"].dtype == np.float32
        assert not np.allclose(data["features"][0], data["features"][4])  # different frames, different features
    wrong = midas("features", "image", str(video), "--backbone", "dinov2", "--weights", str(weights), "--out", str(out))
    assert wrong.returncode == 2 and "dinov2" in wrong.stderr  # the old spelling runs the same command, and warns
    assert wrong.stderr.startswith("midas: warning: `midas features` is now `midas extract image-features`")
    again = midas("extract", "image-features", str(video), "--backbone", "resnet50", "--weights", str(weights),
                  "--out", str(tmp_path / "again.npz"), "--crop", "64", "--device", "cpu", check=True)  # the old name
    assert "midas: warning: --device is now --accelerator" in again.stderr
    with np.load(out) as first, np.load(tmp_path / "again.npz") as second:
        assert np.allclose(first["features"], second["features"], rtol=1e-4, atol=1e-6)  # same weights, frames


def test_dinov2_extraction_every_other_frame(tmp_path):
    torch.manual_seed(0)
    weights = tmp_path / "dino.pth"
    torch.save(DinoV2().state_dict(), weights)
    video = write_video(tmp_path / "clip.avi")
    summary = extract_features(video, weights, ExtractOptions("dinov2", batch_size=4, every=2, resize=42, crop=28),
                               tmp_path / "f.npz")
    with np.load(tmp_path / "f.npz") as data:
        assert data["frame"].tolist() == [0, 2, 4] and data["features"].shape == (3, 384)
    assert summary["dim"] == 384
    with pytest.raises(ConfigError, match="multiple of 14"):
        ExtractOptions("dinov2", crop=30)
