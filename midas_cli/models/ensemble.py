"""Several gesture networks as one model: each frame's class probabilities averaged over the members.

Networks of different families make different mistakes: on the JIGSAWS development tasks (all LOUO
folds, BENCHMARKS.md) MS-TCN++ breaks its segments in other places than the MTRSAP-style transformer,
and two draws of either (other initial weights, batch orders, dropout) disagree on the hard users. The
average of their probabilities is right more often than any one of them. ``--model ensemble`` is
two MS-TCN++ and one transformer (two of each until 2026-11-28): the second transformer took 11 % of
the training CPU time (benchmarks/bench_members.py) and moved accuracy by under half a point on the
development tasks (the four-member runs re-scored without it, three seeds each: Knot Tying mean 81.0
either way, Needle Passing 76.6 against 76.8; BENCHMARKS.md, ``@0,1,2`` rows).

Each member trains alone, one after another, with its own recipe (models/registry.py: epochs, batch
size, learning rate, which epoch's weights are kept) unless the run overrides a field for all of them
(``--epochs`` ...), and its own seed (the run's seed + its index, so two members of one family differ);
the ensemble's inputs, normaliser and shift augmentation are the run's, shared by all (models/train.py
``fit``, models/fold_batch.py ``fit_stacked``). A checkpoint holds every member's weights; the network
is rebuilt from ``EnsembleConfig`` alone (each member through the registry, as ``--model`` builds it).
``causal`` / ``delay`` go to every member, so a causal ensemble runs live (models/streaming.py averages
its members' steps).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import torch
from torch import nn

from midas_cli.errors import ConfigError

if TYPE_CHECKING:
    from midas_cli.models.train import ProgressFn, TrainConfig

MEMBERS = ("mstcn", "transformer", "mstcn")
TINY = 1e-12  # log of an averaged probability: never log(0)


@dataclass
class EnsembleConfig:
    modality_dims: dict[str, int]
    n_classes: int
    members: tuple[str, ...] = field(default=MEMBERS)  # model names (models/registry.py), in training order
    member_options: dict[str, dict] = field(default_factory=dict)  # per model name: its config's overrides
    causal: bool = False
    delay: int = 0

    def __post_init__(self) -> None:
        self.members = tuple(self.members)  # a list when read back from run.json
        if not self.members:
            raise ConfigError("an ensemble needs at least one member")
        if "ensemble" in self.members:
            raise ConfigError("ensemble member 'ensemble' is not a single model")
        stray = set(self.member_options) - set(self.members)
        if stray:
            raise ConfigError(f"ensemble member_options for {', '.join(sorted(stray))}: not a member")


class Ensemble(nn.Module):
    """``forward`` gives log of the members' mean frame probabilities (B, C, T); it has no loss of its
    own: its members are trained one by one. ``entry`` is the registry's ``model_entry`` (a member is
    built as ``--model`` would build it; passed in, as models/registry.py imports this module)."""

    def __init__(self, cfg: EnsembleConfig, entry: Callable[[str], Any]) -> None:
        super().__init__()
        self.cfg = cfg
        nets = []
        for name in cfg.members:
            try:
                cls, member_cfg = entry(name).build(cfg.modality_dims, cfg.n_classes)
            except ConfigError as exc:
                raise ConfigError(f"ensemble member {name!r} is not a single model: {exc}") from None
            fields = asdict(member_cfg)
            options = {**cfg.member_options.get(name, {}),
                       **{k: getattr(cfg, k) for k in ("causal", "delay") if k in fields}}
            unknown = set(options) - set(fields)
            if unknown:
                raise ConfigError(f"model options {', '.join(sorted(unknown))} do not exist for ensemble member "
                                  f"{name} (known: {', '.join(fields)})")
            nets.append(cls(replace(member_cfg, **options)))
        self.members = nn.ModuleList(nets)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        logits = [m.frame_logits(m(x, mask)) for m in self.members]  # float16 under autocast: averaged in float32
        probs = [torch.softmax(z.to(torch.promote_types(z.dtype, torch.float32)), dim=1) for z in logits]
        return torch.log(torch.stack(probs).mean(dim=0).clamp_min(TINY))

    @staticmethod
    def frame_logits(out: torch.Tensor) -> torch.Tensor:
        """``forward``'s output is already per-frame (log-probabilities)."""
        return out

    def loss(self, out: torch.Tensor, y: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        raise TypeError("an ensemble is trained member by member (models/train.py fit), not as one network")


def member_configs(config: "TrainConfig", members: Sequence[str]) -> list["TrainConfig"]:
    """Each ensemble member's training config: the run's, with the member's model, the member's recipe
    wherever the run leaves a field to the recipe (an ensemble's recipe leaves epochs, batch size, lr and
    selection to its members), and seed + the member's index (two members of one family differ)."""
    return [replace(config, model=name, seed=config.seed + i, model_options={}).resolved()
            for i, name in enumerate(members)]


def each_member(config: "TrainConfig", members: Sequence[str],
                progress: "ProgressFn | None") -> Iterator[tuple[int, "TrainConfig", "ProgressFn"]]:
    """(index, ``member_configs``' config, its progress callback) per ensemble member: one progress count
    over all the members' epochs."""
    configs = member_configs(config, members)
    total, done = sum(c.epochs for c in configs), 0
    for i, member_config in enumerate(configs):
        def member_progress(epoch: int, _: int, record: dict, offset: int = done) -> None:
            if progress:
                progress(offset + epoch, total, record)

        yield i, member_config, member_progress
        done += member_config.epochs


def member_records(i: int, member_config: "TrainConfig", records: list[dict]) -> list[dict]:
    """A member's history records, each with the member's index and model."""
    return [{"member": i, "model": member_config.model, **record} for record in records]
