"""Dataset building, splits and the two networks (shapes, masking, the published MS-TCN++ layout)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.gesture_sessions import CLASSES, write_gesture_dataset, write_gesture_session
from midas_cli.errors import ConfigError, SessionError
from midas_cli.models.data import DatasetConfig, Normaliser, build_dataset
from midas_cli.models.mstcn import MSTCN, MSTCNConfig
from midas_cli.models.splits import instances, make_split
from midas_cli.models.transformer import GestureTransformer, TransformerConfig


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> list[Path]:
    return write_gesture_dataset(tmp_path_factory.mktemp("gestures"), n_trials=4, subjects=2, image_dim=6)


def test_features_per_modality_and_set(sessions):
    ds = build_dataset(sessions, DatasetConfig(("emht", "mtm", "image"), ("pos", "ori", "vel", "grasper", "clutch")))
    assert ds.classes == list(CLASSES)
    assert ds.modality_dims == {"emht": 12 + 24 + 12 + 2 + 1, "mtm": 6 + 18 + 6 + 2 + 1, "image": 6}  # ori: 2 rotation matrices
    assert ds.feature_names["mtm"][-1] == "clutch"
    trial = ds.trials[0]
    assert trial.rate_hz == 30.0  # da Vinci: native rate
    assert trial.labels[0] >= 0 and trial.frames[0] == 5  # unlabelled edge frames trimmed
    assert all(v.shape == (len(trial.labels), ds.modality_dims[m]) for m, v in trial.inputs.items())
    # EmHT grasper = thumb-middle distance of the left hand (sensors 2 and 1)
    names = ds.feature_names["emht"]
    pos = trial.inputs["emht"][:, :12].reshape(-1, 4, 3)
    expected = np.linalg.norm(pos[:, 1] - pos[:, 0], axis=1)
    assert np.allclose(trial.inputs["emht"][:, names.index("emht.left_grasper_mm")], expected, atol=1e-3)


def test_raven_resampled_to_10_hz_and_clutch_windows_dropped(tmp_path):
    path = write_gesture_session(tmp_path, "1", 1, n_frames=600, platform="raven-ii")
    full = build_dataset([path], DatasetConfig(("emht",), ("pos",)))
    assert full.trials[0].rate_hz == 10.0
    assert np.all(np.diff(full.trials[0].frames) == 3)
    cut = build_dataset([path], DatasetConfig(("emht",), ("pos",), exclude_clutch=True))
    clutch_frames = {f for f in range(600) if f % 150 >= 140}
    assert not clutch_frames & set(cut.trials[0].frames.tolist())
    assert len(cut.trials[0].frames) < len(full.trials[0].frames)


def test_robot_arm_kinematics_alone_default_to_10_hz(sessions):
    """JIGSAWS-style inputs (mtm/psm only) are resampled to 10 Hz on a da Vinci; with the EmHT beside them
    the aligned 30 Hz stays (the paper's inputs); --model-rate always wins."""
    arms = build_dataset(sessions[:1], DatasetConfig(("mtm",), ("pos", "vel", "grasper")))
    assert arms.trials[0].rate_hz == 10.0 and np.all(np.diff(arms.trials[0].frames) == 3)
    assert build_dataset(sessions[:1], DatasetConfig(("emht", "mtm"), ("pos",))).trials[0].rate_hz == 30.0
    assert build_dataset(sessions[:1], DatasetConfig(("mtm",), ("pos",), rate_hz=30.0)).trials[0].rate_hz == 30.0


def test_missing_feature_sets_are_reported_not_silent(sessions):
    with pytest.raises(ConfigError, match="modality"):
        DatasetConfig(("emht", "kinect"), ("pos",))
    with pytest.raises(SessionError, match="psm"):
        build_dataset(sessions, DatasetConfig(("psm",), ("pos",)))


def test_normaliser_uses_only_the_given_blocks():
    train = [np.array([[0.0, 1.0], [2.0, 1.0]])]
    norm = Normaliser.fit(train)
    assert norm.mean.tolist() == [1.0, 1.0] and norm.std.tolist() == [1.0, 1.0]  # constant column: std 1
    assert np.allclose(norm.apply(np.array([[3.0, 5.0]])), [[2.0, 4.0]])


def test_gesture_split_is_stratified_disjoint_and_seeded(sessions):
    ds = build_dataset(sessions, DatasetConfig(("emht",), ("pos",)))
    split = make_split(ds, "gesture", seed=3)
    parts = {p: set(split.units[p]) for p in ("train", "val", "test")}
    assert not (parts["train"] & parts["test"]) and not (parts["val"] & parts["test"])
    everything = {(t.name, a, b) for t in ds.trials for _, a, b in instances(t.labels)}
    assert parts["train"] | parts["val"] | parts["test"] == everything
    for cls in range(len(ds.classes)):
        counts = {p: sum(1 for n, a, b in split.units[p] if ds.trials[ds.trial_index(n)].labels[a] == cls)
                  for p in parts}
        total = sum(counts.values())
        assert counts["test"] == max(1, round(0.2 * total)) and counts["val"] == max(1, round(0.2 * total))
    assert make_split(ds, "gesture", seed=3).to_json() == split.to_json()
    assert make_split(ds, "gesture", seed=4).to_json() != split.to_json()


def test_group_splits_hold_out_whole_trials_and_users(sessions):
    ds = build_dataset(sessions, DatasetConfig(("emht",), ("pos",)))
    loto = make_split(ds, "loto", seed=0, fold=1)
    assert len(loto.units["test"]) == 1 and loto.units["test"][0][1:] == (0, len(ds.trials[0].labels))
    louo = make_split(ds, "louo", seed=0, fold=0)
    subject = {t.name: t.subject for t in ds.trials}
    assert {subject[n] for n, _, _ in louo.units["test"]} == {"1"}
    assert {subject[n] for n, _, _ in louo.units["train"]} == {"2"}
    with pytest.raises(ConfigError, match="fold"):
        make_split(ds, "louo", seed=0, fold=5)


def test_mstcn_has_the_published_layout():
    model = MSTCN(MSTCNConfig(in_features=10, n_classes=5))
    gen = model.generation
    assert len(gen.layers) == 11 and len(model.refinements) == 3
    assert all(len(r.layers) == 10 for r in model.refinements)
    assert [layer.conv_small.dilation[0] for layer in gen.layers] == [2 ** i for i in range(11)]
    assert [layer.conv_large.dilation[0] for layer in gen.layers] == [2 ** (10 - i) for i in range(11)]
    assert [layer.conv_dilated.dilation[0] for layer in model.refinements[0].layers] == [2 ** i for i in range(10)]
    assert gen.conv_in.out_channels == 64
    stages = model(torch.randn(2, 10, 30), torch.ones(2, 30, dtype=torch.bool))
    assert stages.shape == (4, 2, 5, 30)


def test_mstcn_loss_is_ce_plus_truncated_smoothing():
    torch.manual_seed(0)
    model = MSTCN(MSTCNConfig(in_features=3, n_classes=4, pg_layers=2, refinement_stages=0))
    logits = torch.randn(1, 1, 4, 6) * 10  # (S, B, C, T): large jumps so the clamp at tau^2 = 16 bites
    target = torch.tensor([[0, 1, 2, 3, 0, -1]])
    mask = torch.ones(1, 6, dtype=torch.bool)
    log_p = torch.log_softmax(logits[0], dim=1)
    mse = torch.clamp((log_p[:, :, 1:] - log_p[:, :, :-1]) ** 2, max=16).mean()
    ce = torch.nn.functional.cross_entropy(logits[0].transpose(1, 2).reshape(-1, 4), target.reshape(-1), ignore_index=-1)
    assert float(model.loss(logits, target, mask)) == pytest.approx(float(ce + 0.15 * mse), rel=1e-5)


@pytest.mark.parametrize("make", [
    lambda: MSTCN(MSTCNConfig(in_features=5, n_classes=3, pg_layers=4, refinement_layers=4)),
    lambda: GestureTransformer(TransformerConfig({"a": 2, "b": 3}, n_classes=3, window=16)),
])
def test_padding_and_batch_neighbours_do_not_change_a_sequence(make):
    torch.manual_seed(0)
    model = make().eval()
    x = torch.randn(2, 5, 40)
    mask = torch.ones(2, 40, dtype=torch.bool)
    mask[1, 25:] = False
    with torch.no_grad():
        batched = model(x, mask)[-1]
        alone = model(x[1:, :, :25], mask[1:, :25])[-1]
    assert torch.allclose(batched[1, :, :25], alone[0], atol=1e-5)


def test_transformer_attends_over_time_within_a_window():
    torch.manual_seed(0)
    model = GestureTransformer(TransformerConfig({"a": 2}, n_classes=3, kernel_size=3, window=64)).eval()
    x = torch.randn(1, 2, 64)
    mask = torch.ones(1, 64, dtype=torch.bool)
    changed = x.clone()
    changed[0, :, 60] += 5.0  # far outside the CNN's receptive field (3 convs x kernel 3 -> +-3 frames) of frame 0
    with torch.no_grad():
        delta = (model(x, mask) - model(changed, mask))[0, 0, :, 0].abs().max()
    assert delta > 1e-4


def test_auto_modalities_take_the_emht_where_every_session_has_it_else_the_robot_arms(sessions, monkeypatch):
    """`--modalities auto --features auto` (the defaults): MiDAS sessions train on the EmHT with the
    paper's pos/ori/vel; sessions without it (JIGSAWS-style kinematics) on mtm + psm with position, velocity,
    angular velocity and the grasper (not the orientation: it carries each user's grip as an offset)."""
    import midas_cli.models.data as data

    midas_style = build_dataset(sessions, DatasetConfig(("auto",), ("auto",)))
    assert midas_style.config.modalities == ("emht",) and midas_style.config.features == ("pos", "ori", "vel")
    assert data.resolve_auto(DatasetConfig(("mtm",), ("auto",)), sessions).features == ("pos", "vel", "angvel",
                                                                                         "grasper")
    real = data.read_aligned

    class Jigsaws:  # the same sessions as JIGSAWS gives them: both robot arms, no EmHT
        def __init__(self, path):
            self.columns = [c for c in real(path).columns if not c.startswith("emht.")] + ["psm.left_x_mm"]

    monkeypatch.setattr(data, "read_aligned", Jigsaws)
    jigsaws = data.resolve_auto(DatasetConfig(("auto",), ("auto",)), sessions)
    assert jigsaws.modalities == ("mtm", "psm") and jigsaws.features == ("pos", "vel", "angvel", "grasper")
    monkeypatch.setattr(data, "read_aligned", lambda path: type("T", (), {"columns": ["video.seq", "mtm.left_x_mm"]})())
    assert data.resolve_auto(DatasetConfig(("auto",), ("auto",)), sessions).modalities == ("mtm",)
    monkeypatch.setattr(data, "read_aligned", lambda path: type("T", (), {"columns": ["video.seq"]})())
    with pytest.raises(ConfigError, match="no kinematic stream in common"):
        data.resolve_auto(DatasetConfig(("auto",), ("auto",)), sessions)
