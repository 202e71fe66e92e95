"""A calibration that maps a sensing modality into a robot frame, its files, and applying it.

Model (paper Appendix A.2, DESIGN.md section 7): p_target = s R p_source + t + f(p_source; phi), with
R, t (and s, for PSM targets where motion scaling applies) from a least-squares fit and f the residual
MLP. Orientations by composition of rotations: R_target = R @ mean(R_thumb @ O_thumb, R_middle @ O_middle)
where O are fixed per-sensor mounting offsets and mean is the chordal mean of the two corrected sensor
rotations (the grip opens symmetrically, so the mean follows the hand, not the finger). For HandKP
(Appendix A.3) the "mlp" model is the direct camera -> robot MLP instead of a residual.

Files (in a session's ``calib/`` or anywhere with ``--out``): ``<source>_to_<target>.json`` (readable
description: transform, lag, offsets, training sessions, cross-validation) and, when an MLP was
trained, ``<source>_to_<target>.pt`` (a state dict, loadable with ``torch.load(weights_only=True)``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli import __version__
from midas_cli.errors import ConfigError, SessionError
from midas_cli.geometry import apply_similarity
from midas_cli.session.outputs import replacing, write_json

SOURCES = ("emht", "handkp")
TARGETS = ("mtm", "psm")
MODELS = ("rigid", "mlp")
MODEL_CHOICES = ("best", "rigid", "mlp")  # what align/eval use; best = the held-out comparison's winner
FORMAT = "midas-calibration-v1"


@dataclass
class Calibration:
    """source -> target mapping. ``rotation`` (3, 3), ``translation`` (3,) mm, ``scale``; ``mlp`` is a
    residual (emht) or a direct mapping (handkp) or None; ``lag_ms``: how late the source stream is on
    the host clock (applied by ``align``); ``orientation_offsets`` "<hand>_thumb"/"<hand>_middle" ->
    (3, 3) sensor mounting offsets (emht only)."""

    source: str
    target: str
    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0
    mlp: Any = None
    lag_ms: float = 0.0
    orientation_offsets: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def stem(self) -> str:
        return f"{self.source}_to_{self.target}"

    @property
    def models(self) -> list[str]:
        return ["rigid", "mlp"] if self.mlp is not None else ["rigid"]

    @property
    def selection(self) -> dict[str, Any]:
        """The held-out comparison of the models made at calibrate time (``info["selection"]``); a file
        without one (older midas) counts as uncompared, best = the MLP when fitted."""
        return self.info.get("selection") or {"best": self.models[-1], "compared": False,
                                              "reason": "calibration file has no held-out comparison"}

    def choose_model(self, wanted: str = "best") -> str:
        """``wanted`` best|rigid|mlp -> the model to use: best = the held-out winner; mlp falls back to
        rigid when no MLP was fitted."""
        if wanted not in MODEL_CHOICES:
            raise ConfigError(f"--calibration-model {wanted!r} is unknown (expected one of {', '.join(MODEL_CHOICES)})")
        if wanted == "best":
            return self.selection["best"] if self.selection["best"] in self.models else "rigid"
        return wanted if wanted in self.models else "rigid"

    def positions(self, points: np.ndarray, model: str) -> np.ndarray:
        """Source points (N, 3) mm -> target frame (N, 3) mm with ``model`` rigid|mlp."""
        rigid = apply_similarity(self.rotation, self.translation, self.scale, points)
        if model == "rigid":
            return rigid
        if self.mlp is None:
            raise SessionError(f"calibration {self.stem} has no MLP (it was fitted with --rigid-only)")
        predicted = self.mlp.predict(points)
        return predicted if self.source == "handkp" else rigid + predicted

    def has_orientation(self, hand: str) -> bool:
        return f"{hand}_thumb" in self.orientation_offsets and f"{hand}_middle" in self.orientation_offsets

    def orientations(self, thumb: np.ndarray, middle: np.ndarray, hand: str) -> np.ndarray:
        """Thumb and middle sensor rotations (N, 3, 3), source frame -> hand rotations (N, 3, 3), target frame."""
        corrected = thumb @ self.orientation_offsets[f"{hand}_thumb"] + middle @ self.orientation_offsets[f"{hand}_middle"]
        return self.rotation @ project_to_rotations(corrected)


def project_to_rotations(matrices: np.ndarray) -> np.ndarray:
    """Nearest rotations (N, 3, 3) to matrices (N, 3, 3) (chordal mean when given a sum); NaN stays NaN."""
    out = np.full(matrices.shape, np.nan)
    ok = np.isfinite(matrices).all(axis=(1, 2))
    u, _, vt = np.linalg.svd(matrices[ok])
    det = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= det[:, None]
    out[ok] = u @ vt
    return out


def save_calibration(calibration: Calibration, json_path: Path) -> list[Path]:
    """Write the JSON description (and the MLP weights beside it); returns the files written."""
    json_path = Path(json_path)
    written = []
    description = _describe(calibration)
    if calibration.mlp is not None:
        from midas_cli.models.residual_mlp import save_mlp

        weights = json_path.with_suffix(".pt")
        with replacing(weights) as tmp:
            save_mlp(calibration.mlp, tmp)
        description["mlp"] = {"weights": weights.name, **calibration.mlp.describe()}
        written.append(weights)
    write_json(json_path, description)
    return [json_path, *written]


def load_calibration(json_path: Path) -> Calibration:
    """Read a calibration JSON (and its weights); SessionError when malformed."""
    json_path = Path(json_path)
    try:
        data = json.loads(json_path.read_text(encoding="utf-8"))
        if data.get("format") != FORMAT:
            raise SessionError(f"{json_path} is not a midas calibration (format {data.get('format')!r})")
        rigid = data["rigid"]
        calibration = Calibration(
            data["source"], data["target"], np.asarray(rigid["R"], dtype=float), np.asarray(rigid["t_mm"], dtype=float),
            float(rigid.get("scale", 1.0)), None, float(data.get("lag_ms", 0.0)),
            {h: np.asarray(r, dtype=float) for h, r in data.get("orientation_offsets", {}).items()},
            data.get("info", {}))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SessionError(f"cannot read calibration {json_path}: {exc}") from exc
    if data.get("mlp"):
        from midas_cli.models.residual_mlp import load_mlp

        calibration.mlp = load_mlp(json_path.parent / data["mlp"]["weights"], data["mlp"])
    return calibration


def _describe(calibration: Calibration) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "source": calibration.source,
        "target": calibration.target,
        "model": "p_target = s R p_source + t" + (" + f(p_source)" if calibration.mlp is not None and
                                                   calibration.source == "emht" else ""),
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "midas_version": __version__,
        "rigid": {"R": calibration.rotation.tolist(), "t_mm": calibration.translation.tolist(),
                  "scale": calibration.scale},
        "lag_ms": calibration.lag_ms,
        "orientation_offsets": {h: r.tolist() for h, r in calibration.orientation_offsets.items()},
        "info": calibration.info,
    }
