"""`midas extract image-features`: per-frame image features from a video with a user-supplied backbone.

The `extract` group (commands/extract.py) registers ``image``; ``app`` here is its old spelling,
`midas features image`, kept for a release (hidden; commands/root.py's registry warns on use)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from midas_cli.commands import executor as ex
from midas_cli.commands.common import out, print_json
from midas_cli.commands.options import ACCELERATOR_OPTION, JSON_OPTION, OLD_ACCELERATOR_OPTION, accelerator
from midas_cli.errors import ConfigError

app = typer.Typer(help="Extract learned features from recordings.", no_args_is_help=True)


@app.command()
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
    accelerator_name: Optional[str] = ACCELERATOR_OPTION,
    old_device: Optional[str] = OLD_ACCELERATOR_OPTION,
    as_json: bool = JSON_OPTION,
    executor: str = ex.EXECUTOR_OPT,
    jobs: int = ex.JOBS_OPT,
    run_dir: Optional[Path] = ex.RUN_DIR_OPT,
    no_wait: bool = ex.NO_WAIT_OPT,
    slurm_partition: Optional[str] = ex.PARTITION_OPT,
    slurm_time: Optional[str] = ex.TIME_OPT,
    slurm_mem: Optional[str] = ex.MEM_OPT,
    slurm_gpus: Optional[int] = ex.GPUS_OPT,
    slurm_array_parallelism: Optional[int] = ex.PARALLEL_OPT,
) -> None:
    """Encode every frame of VIDEO into an NPZ of image features.

    The NPZ holds frame (N,) and features (N, D); nothing is downloaded.

    Example: midas extract image-features session/video/recording.mkv --backbone resnet50 --weights resnet50-11ad3fa6.pth --out session/derived/image_features.npz

    Example (every session, one SLURM array task with a GPU each): midas extract image-features data/*/ --backbone dinov2 --weights dinov2_vits14.pth --accelerator cuda --executor slurm --run-dir runs/features
    """
    from midas_cli.models.image_features import ExtractOptions  # torch: imported on use
    from midas_cli.models.image_features_units import TASK, plan_units

    device = accelerator(accelerator_name, old_device)  # torch's word for it
    if device == "cuda" and executor == "slurm" and slurm_gpus is None:
        from midas_cli.config import section

        slurm_gpus = section("slurm").get("gpus") or 1
    choice = ex.executor_choice(executor, jobs, run_dir, no_wait, slurm_partition, slurm_time, slurm_mem, slurm_gpus,
                                slurm_array_parallelism)
    if out_path is not None and len(inputs) > 1:
        raise ConfigError("--out names one output file: give one input, or leave --out out")
    options = ExtractOptions(backbone=backbone, batch_size=batch_size, every=every, resize=max(256, crop),
                             crop=crop, device=device)
    with ex.unit_progress() as progress:
        frames = progress.add_task(f"{backbone} frames", total=None, info="")
        extra = {"progress": lambda done, total: progress.update(frames, completed=done, total=total or None)} \
            if choice.executor == "local" and choice.jobs == 1 else None
        outcome = ex.run_plan(TASK, plan_units(inputs, weights, options, out_path), choice, "videos", extra, progress)
    if outcome.submitted:
        ex.submitted_line(outcome)
        return
    results = [r for r in outcome.results if r is not None]
    if as_json:
        print_json(results[0] if len(inputs) == 1 and results else results)
    else:
        for summary in results:
            out.print(f"{summary['frames']} frames x {summary['dim']} features ({backbone}) -> {summary['out']}",
                      markup=False)
    ex.raise_failed(outcome, "inputs")
