"""`midas extract image-features`: per-frame image features from a video with a user-supplied backbone.

The `extract` group (commands/extract.py) registers ``image``; ``app`` here is its old spelling,
`midas features image`, kept for a release (hidden; commands/root.py's registry warns on use)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from midas_cli.commands import executor as ex
from midas_cli.commands.common import out
from midas_cli.commands.options import JSON_OPTION, accelerator_option
from midas_cli.errors import ConfigError
from midas_cli.jobs.options import BatchOptions

app = typer.Typer(help="Extract learned features from recordings.", no_args_is_help=True)


@app.command()
@ex.batch_command
@accelerator_option  # device: cpu or cuda
def image(
    inputs: list[Path] = typer.Argument(..., help="Video file(s) readable by OpenCV, or session folder(s) with one "
                                        "video in video/."),
    backbone: str = typer.Option("resnet50", "--backbone", help="resnet50 or dinov2 (ViT-S/14)."),
    weights: Path = typer.Option(..., "--weights", help="State dict in the official torchvision / dinov2 layout."),
    out_path: Optional[Path] = typer.Option(None, "--out", help="Output NPZ of one input (default: a session's "
                                            "derived/image_features.npz; <video stem>.image_features.npz beside "
                                            "a bare video)."),
    batch_size: int = typer.Option(32, "--batch-size", min=1, help="Frames per forward pass."),
    every: int = typer.Option(1, "--every", min=1, help="Keep every k-th frame."),
    crop: int = typer.Option(224, "--crop", help="Centre-crop size in pixels (DINOv2: a multiple of 14)."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
    device: str,
) -> None:
    """Encode every frame of VIDEO into an NPZ of image features.

    The NPZ holds frame (N,) and features (N, D); nothing is downloaded.

    Example: midas extract image-features session/video/recording.mkv --backbone resnet50 --weights resnet50-11ad3fa6.pth --out session/derived/image_features.npz

    Example (every session, one SLURM array task with a GPU each): midas extract image-features data/*/ --backbone dinov2 --weights dinov2_vits14.pth --accelerator cuda --executor slurm --run-dir runs/features
    """
    from midas_cli.models.image_features import ExtractOptions  # torch: imported on use
    from midas_cli.models.image_features_units import TASK, plan_units

    choice = batch.choice(gpu=device == "cuda")  # a CUDA unit asks SLURM for a GPU
    if out_path is not None and len(inputs) > 1:
        raise ConfigError("--out names one output file: give one input, or leave --out out")
    options = ExtractOptions(backbone=backbone, batch_size=batch_size, every=every, resize=max(256, crop),
                             crop=crop, device=device)
    outcome = ex.run_plan(TASK, plan_units(inputs, weights, options, out_path), choice, "videos",
                          ex.counted(f"{backbone} frames"))
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    for summary in ex.shown_results(outcome, as_json, single=len(inputs) == 1):
        out.print(f"{summary['frames']} frames x {summary['dim']} features ({backbone}) -> {summary['out']}",
                  markup=False)
    outcome.raise_failed("inputs")
