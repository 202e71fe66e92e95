"""Per-frame image features from a video with a ResNet-50 or DINOv2 ViT-S/14 backbone.

The weights come from a file the user supplies (nothing is downloaded): a state dict in the official
torchvision (ResNet-50) or facebookresearch/dinov2 (ViT-S/14) key layout, loaded with
``weights_only=True``. Frames are read with OpenCV in order (frame i = video frame index i, i.e. the
``seq`` of the session's video stream), converted BGR -> RGB, resized (shorter side to ``resize``,
then a centre crop of ``crop`` pixels), normalised with the ImageNet mean/std and encoded in batches.
Output NPZ like ``derived/image_features.npz``: ``frame`` (N,) int64, ``features`` (N, D) float32,
``backbone``, ``weights_sha256``, ``note``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
import torch

from midas_cli.errors import ConfigError, SessionError
from midas_cli.models.dinov2 import DinoV2
from midas_cli.models.resnet import ResNet
from midas_cli.models.torch_io import load_weights_only
from midas_cli.session.outputs import out_target, replacing
from midas_cli.session.streamfile import file_sha256

BACKBONES = ("resnet50", "dinov2")
MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


@dataclass(frozen=True)
class ExtractOptions:
    backbone: str = "resnet50"
    batch_size: int = 32
    every: int = 1  # keep every k-th frame
    resize: int = 256
    crop: int = 224
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise ConfigError(f"--backbone {self.backbone!r} is unknown (expected one of {', '.join(BACKBONES)})")
        if self.batch_size < 1 or self.every < 1 or not 0 < self.crop <= self.resize:
            raise ConfigError("batch size and --every must be >= 1, and 0 < crop <= resize")
        if self.backbone == "dinov2" and self.crop % 14:
            raise ConfigError(f"DINOv2 needs a crop that is a multiple of 14 pixels, got {self.crop}")


def load_backbone(backbone: str, weights: Path) -> torch.nn.Module:
    """The network with the user's weights (strict key match), in eval mode."""
    state = load_weights_only(weights, "weights")
    state = state.get("state_dict", state) if isinstance(state, dict) else state
    model = ResNet() if backbone == "resnet50" else DinoV2()
    try:
        model.load_state_dict(state, strict=True)
    except (RuntimeError, TypeError) as exc:  # other keys or shapes, or not a dict at all
        raise ConfigError(f"{weights} is not a {backbone} state dict in the official key layout: "
                          f"{str(exc).splitlines()[0]}") from exc
    return model.eval()


def extract_features(video: Path, weights: Path, options: ExtractOptions, out: Path,
                     progress: Callable[[int, int], None] | None = None) -> dict:
    """Encode every ``options.every``-th frame of ``video``; write the NPZ ``out``; return a summary."""
    if options.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--accelerator cuda asked for, but torch sees no CUDA GPU (use --accelerator cpu)")
    out = out_target(out, inputs=(video, weights))  # checked before the (long) encoding: never a session's own file
    model = load_backbone(options.backbone, weights).to(options.device)
    frames, chunks = [], []
    total = _frame_count(video)
    with torch.no_grad():
        for indices, batch in _batches(video, options):
            x = torch.from_numpy(batch).to(options.device)  # (B, 3, crop, crop)
            chunks.append(model.features(x).float().cpu().numpy())
            frames += indices
            if progress:
                progress(indices[-1] + 1, total)
    if not frames:
        raise SessionError(f"{video}: no frame could be decoded")
    features = np.concatenate(chunks).astype(np.float32)
    with replacing(out) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, frame=np.asarray(frames, dtype=np.int64), features=features, backbone=options.backbone,
                 weights_sha256=file_sha256(weights), note=f"{options.backbone} features of {Path(video).name}")
    return {"out": str(out), "frames": len(frames), "dim": int(features.shape[1]), "backbone": options.backbone}


def preprocess(frame_bgr: np.ndarray, resize: int, crop: int) -> np.ndarray:
    """(H, W, 3) uint8 BGR -> (3, crop, crop) float32 ImageNet-normalised RGB."""
    h, w = frame_bgr.shape[:2]
    scale = resize / min(h, w)
    image = cv2.resize(frame_bgr, (max(crop, round(w * scale)), max(crop, round(h * scale))), interpolation=cv2.INTER_AREA)
    top, left = (image.shape[0] - crop) // 2, (image.shape[1] - crop) // 2
    rgb = image[top:top + crop, left:left + crop, ::-1].astype(np.float32) / 255.0
    return ((rgb - MEAN) / STD).transpose(2, 0, 1)  # (crop, crop, 3) -> (3, crop, crop)


def _batches(video: Path, options: ExtractOptions) -> Iterator[tuple[list[int], np.ndarray]]:
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise SessionError(f"cannot open video {video} (missing file or codec OpenCV cannot read)")
    indices, images, index = [], [], 0
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if index % options.every == 0:
                indices.append(index)
                images.append(preprocess(frame, options.resize, options.crop))
            if len(images) == options.batch_size:
                yield indices, np.stack(images)
                indices, images = [], []
            index += 1
    finally:
        capture.release()
    if images:
        yield indices, np.stack(images)


def _frame_count(video: Path) -> int:
    capture = cv2.VideoCapture(str(video))
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
    capture.release()
    return count
