"""Causal sequence models (issue 28 item 4): with ``causal`` the output at frame t of MS-TCN++ and of the
transformer does not depend on later frames (the dilation shortcut included), and ``train gestures
--causal`` trains, records and re-evaluates such a model through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from helpers.cli import midas
from helpers.gesture_sessions import write_two_users
from midas_cli.errors import ConfigError
from midas_cli.models import cv
from midas_cli.models.train import build_model, saved_structure

DIMS, CLASSES = {"emht": 4, "mtm": 3}, 3
SMALL = {"mstcn": {"pg_layers": 6, "refinement_stages": 2, "refinement_layers": 5, "feature_maps": 8},
         "transformer": {"cnn_channels": 8, "d_model": 16, "n_heads": 2, "ff_dim": 16, "window": 8,
                         "refinement_layers": 5, "refinement_maps": 8}}


def _model(name: str, causal: bool) -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_model(name, DIMS, CLASSES, SMALL[name], causal=causal)[0]
    return model.eval()


def _logits(model: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return model(x, torch.ones(x.shape[0], x.shape[2], dtype=torch.bool))  # (S, B, C, T)


@pytest.mark.parametrize("name", ["mstcn", "transformer"])
def test_a_causal_model_at_frame_t_ignores_later_frames(name):
    x = torch.randn(1, 7, 60, generator=torch.Generator().manual_seed(1))
    later = x.clone()
    later[:, :, 37:] = torch.randn(1, 7, 23, generator=torch.Generator().manual_seed(2))
    causal = _model(name, causal=True)
    assert causal.cfg.causal
    before, after = _logits(causal, x), _logits(causal, later)
    assert torch.allclose(before[..., :37], after[..., :37], atol=1e-6)
    assert not torch.allclose(before[..., 37:], after[..., 37:], atol=1e-3)
    # a prefix alone gives the same outputs: the convolutions whose dilation (up to 32) reaches its length
    # take the shortcut (the tap at t alone), which must equal the padded convolution
    for length in (3, 20, 45):
        assert torch.allclose(_logits(causal, x[..., :length]), before[..., :length], atol=1e-5)
    plain = _model(name, causal=False)  # the check can fail: the offline model sees the future
    assert not torch.allclose(_logits(plain, x)[..., :37], _logits(plain, later)[..., :37], atol=1e-3)


def test_a_per_frame_baseline_has_no_causal_option_and_stays_as_it_is():
    model, config = build_model("baseline", DIMS, CLASSES, {}, causal=True)
    assert "causal" not in config and type(model).__name__ == "FrameBaseline"


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_two_users(tmp_path_factory.mktemp("causal") / "data", n_frames=120)


def test_train_gestures_causal_records_it_and_re_evaluates_the_same(data, tmp_path):
    run = midas("train", "gestures", str(data), "--model", "mstcn", "--causal", "--modalities", "emht", "--features", "pos,vel",
                "--epochs", "1", "--decode-lag", "0.5", "--out", str(tmp_path / "run"), "--json", check=True)
    record = json.loads((tmp_path / "run" / "run.json").read_text(encoding="utf-8"))
    assert record["train_config"]["causal"] is True and record["model_config"]["causal"] is True
    # its clean-up (the defaults' minimum and gesture order) decoded as live, each frame 0.5 s after it
    lag = round(0.5 * record["trials"][0]["rate_hz"])
    assert record["decode_lag_frames"] == lag and record["min_segment_frames"] > 1 and record["switch_scores"]
    test = json.loads((tmp_path / "run" / "metrics.json").read_text(encoding="utf-8"))["test"]
    assert test["decode_lag_frames"] == lag and test["grammar"] and set(test["raw"]) == set(test["summary"])
    saved = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert saved["model_config"]["causal"] is True and saved["train_config"]["causal"] is True
    again = midas("train", "gestures", str(data), "--eval-only", str(tmp_path / "run" / "checkpoint.pt"),
                  "--out", str(tmp_path / "eval"), "--json", check=True)
    assert json.loads(again.stdout)["test"] == json.loads(run.stdout)["test"]  # rebuilt causal, as trained


def test_causal_cross_validation_batched_trains_causal_folds_and_per_frame_baselines(data, tmp_path):
    out = tmp_path / "cv"
    result = midas("train", "gestures", str(data), "--causal", "--delay", "0.3", "--model", "transformer",
                   "--modalities", "emht", "--features", "pos", "--model-rate", "10", "--split", "louo", "--fold", "all",
                   "--epochs", "1", "--fold-batch", "on", "--out", str(out), "--json")
    assert result.returncode == 0, result.stderr
    for k in (0, 1):
        fold = json.loads((out / f"fold-{k}" / "run.json").read_text(encoding="utf-8"))
        assert fold["model_config"]["causal"] is True and fold["train_config"]["causal"] is True
        assert fold["model_config"]["delay"] == 3  # delayed too, batched
        baseline = json.loads((out / "baseline" / f"fold-{k}" / "run.json").read_text(encoding="utf-8"))
        assert baseline["train_config"]["causal"] is True and "causal" not in baseline["model_config"]
        # as with causal: the training asked for is recorded, the per-frame network has no delay (frame t at t)
        assert baseline["train_config"]["delay_s"] == 0.3 and "delay" not in baseline["model_config"]
    assert "decoded frame by frame as live, each frame 0 frame(s) after it" in (out / "cv.md").read_text(encoding="utf-8")
    # a fold written before --causal existed has no such key, which meant "not causal"
    _set_causal(out / "fold-0" / "run.json", None)
    with pytest.raises(ConfigError, match="trained differently"):
        cv.summarise(out)  # not the same training as the causal fold 1
    _set_causal(out / "fold-1" / "run.json", False)
    assert cv.summarise(out)["n_folds"] == 2  # an old fold and a new non-causal one: one cross-validation


def _set_causal(run_json: Path, causal: bool | None) -> None:
    """Rewrite a run.json's train_config.causal (None: leave the key out, as runs before it did)."""
    record = json.loads(run_json.read_text(encoding="utf-8"))
    record["train_config"] = {k: v for k, v in record["train_config"].items() if k != "causal"}
    if causal is not None:
        record["train_config"]["causal"] = causal
    run_json.write_text(json.dumps(record), encoding="utf-8")


def test_causal_with_per_trial_normalisation_is_refused_in_one_line(data, tmp_path):
    result = midas("train", "gestures", str(data), "--causal", "--normalise", "trial", "--out", str(tmp_path / "x"))
    assert result.returncode == 2 and result.stderr.strip().count("\n") == 0
    assert "--causal" in result.stderr and "--normalise trial" in result.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("name", ["mstcn", "transformer"])
def test_a_delayed_model_labels_frame_t_from_frames_up_to_t_plus_delay_and_batches_as_alone(name):
    delay = 5
    torch.manual_seed(0)
    model = build_model(name, DIMS, CLASSES, SMALL[name], causal=True, delay=delay)[0].eval()
    assert model.cfg.delay == delay
    x = torch.randn(1, 7, 60, generator=torch.Generator().manual_seed(1))
    later = x.clone()
    later[:, :, 37:] = torch.randn(1, 7, 23, generator=torch.Generator().manual_seed(2))
    before, after = _logits(model, x), _logits(model, later)
    assert before.shape[-1] == 60  # a label per frame, the last ones from the zeros after the end
    assert torch.allclose(before[..., :37 - delay], after[..., :37 - delay], atol=1e-6)
    assert not torch.allclose(before[..., 37 - delay:37], after[..., 37 - delay:37], atol=1e-3)  # frames it sees
    # the same network without the delay: its output at t + delay is the delayed one's at t
    undelayed = build_model(name, DIMS, CLASSES, SMALL[name], causal=True)[0].eval()
    undelayed.load_state_dict(model.state_dict())
    appended = torch.cat([x, torch.zeros(1, 7, delay)], dim=2)
    assert torch.allclose(_logits(undelayed, appended)[..., delay:], before, atol=1e-5)
    # a batch of a shorter and a longer sequence: each row as that sequence alone
    short = x[..., :41]
    batch = torch.zeros(2, 7, 60)
    batch[0], batch[1, :, :41] = x[0], short[0]
    mask = torch.zeros(2, 60, dtype=torch.bool)
    mask[0], mask[1, :41] = True, True
    with torch.no_grad():
        both = model(batch, mask)
    assert torch.allclose(both[:, 0], before[:, 0], atol=1e-5)
    assert torch.allclose(both[:, 1, :, :41], _logits(model, short)[:, 0], atol=1e-5)


def test_delay_is_refused_without_causal_and_recorded_in_frames_of_the_model_rate(data, tmp_path):
    refused = midas("train", "gestures", str(data), "--delay", "1", "--out", str(tmp_path / "x"))
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0 and "--causal" in refused.stderr
    assert not (tmp_path / "x").exists()
    run = midas("train", "gestures", str(data), "--causal", "--delay", "0.5", "--modalities", "emht", "--features",
                "pos", "--model-rate", "10", "--epochs", "1", "--out", str(tmp_path / "run"), "--json", check=True)
    record = json.loads((tmp_path / "run" / "run.json").read_text(encoding="utf-8"))
    assert record["train_config"]["delay_s"] == 0.5 and record["model_config"]["delay"] == 5  # 0.5 s at 10 Hz
    saved = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert saved_structure(saved) == (True, 5)  # what --eval-only and --live-model rebuild it with
    again = midas("train", "gestures", str(data), "--eval-only", str(tmp_path / "run" / "checkpoint.pt"),
                  "--out", str(tmp_path / "eval"), "--json", check=True)
    assert json.loads(again.stdout)["test"] == json.loads(run.stdout)["test"]
    tiny = midas("train", "gestures", str(data), "--causal", "--delay", "0.01", "--modalities", "emht", "--features",
                 "pos", "--model-rate", "10", "--epochs", "1", "--out", str(tmp_path / "tiny"), check=True)
    assert "no delay" in tiny.stderr  # under half a frame: said, not silently ignored
    assert json.loads((tmp_path / "tiny" / "run.json").read_text(encoding="utf-8"))["model_config"]["delay"] == 0
