"""Run by tests/interop/test_lerobot.py with the LeRobot environment's Python (not midas's): load an exported
dataset with huggingface lerobot's own ``LeRobotDataset`` and print what it gives as one JSON document.

    python lerobot_load.py ROOT [--video]

Prints the dataset's length, fps, episode count and features, every frame's ``timestamp``,
``frame_index``, ``video_frame``, ``t_host_ns``, ``marker``, the ``label.*`` fields and the
``observation.*`` vectors (NaN as null), and, without ``--video``, the ``task`` of the first and last
items and item 5's ``observation.state``. With ``--video`` it instead decodes the video feature at a few
frames (per-channel means, 0-255) or reports why it could not (``video_error``).
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

VIDEO_ROWS = (0, 1, 29, 30, 31, 60)


def _plain(value: Any) -> Any:
    """A tensor, number or string as JSON (NaN as None)."""
    if isinstance(value, str):
        return value
    value = value.tolist() if hasattr(value, "tolist") else value
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return None if isinstance(value, float) and math.isnan(value) else value


def main(root: str, video: bool) -> dict[str, Any]:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset("midas/export", root=root)
    keys = [k for k in dataset.features if not k.startswith("observation.images.")]
    rows = dataset.hf_dataset.with_format(None)[:]
    frames = {k: [_plain(v) for v in rows[k]] for k in keys}
    result: dict[str, Any] = {"len": len(dataset), "fps": dataset.fps, "episodes": dataset.num_episodes,
                              "features": dataset.features, "frames": frames}
    if not video:  # an item of a dataset with a video decodes its frame
        result["tasks"] = [dataset[i]["task"] for i in (0, len(dataset) - 1)]
        result["item_state"] = _plain(dataset[5]["observation.state"])
    else:
        try:
            key = dataset.meta.video_keys[0]
            result["video"] = {str(i): _plain(dataset[i][key].mean(dim=(1, 2)) * 255) for i in VIDEO_ROWS}
        except Exception as exc:  # reported to the test, which decides
            result["video_error"] = f"{type(exc).__name__}: {exc}"
    return result


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], "--video" in sys.argv[2:])))
