"""`midas features image`: per-frame image features from a video with a user-supplied backbone."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

from midas_cli.commands.common import out, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.commands.progress import progress_display

app = typer.Typer(help="Extract learned features from recordings.", no_args_is_help=True)


@app.command()
def image(
    video: Path = typer.Argument(..., help="Video file readable by OpenCV (e.g. the session's video/*.mkv)."),
    backbone: str = typer.Option("resnet50", "--backbone", help="resnet50 or dinov2 (ViT-S/14)."),
    weights: Path = typer.Option(..., "--weights", help="State dict in the official torchvision / dinov2 layout."),
    out_path: Path = typer.Option(..., "--out", help="Output NPZ (e.g. SESSION/derived/image_features.npz)."),
    batch_size: int = typer.Option(32, "--batch-size", min=1, help="Frames per forward pass."),
    every: int = typer.Option(1, "--every", min=1, help="Keep every k-th frame."),
    crop: int = typer.Option(224, "--crop", help="Centre-crop size in pixels (DINOv2: a multiple of 14)."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Encode every frame of VIDEO into an NPZ of image features.

    The NPZ holds frame (N,) and features (N, D); nothing is downloaded.

    Example: midas features image session/video/recording.mkv --backbone resnet50 --weights resnet50-11ad3fa6.pth --out session/derived/image_features.npz
    """
    from midas_cli.models.image_features import ExtractOptions, extract_features  # torch: imported on use

    options = ExtractOptions(backbone=backbone, batch_size=batch_size, every=every, resize=max(256, crop),
                             crop=crop, device=device)
    with progress_display(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                          TimeElapsedColumn()) as progress:
        task = progress.add_task(f"{backbone} frames", total=None)
        summary = extract_features(video, weights, options, out_path,
                                   lambda done, total: progress.update(task, completed=done, total=total or None))
    if as_json:
        print_json(summary)
        return
    out.print(f"{summary['frames']} frames x {summary['dim']} features ({backbone}) -> {summary['out']}", markup=False)
