"""Reading ``.pt``/``.pth`` files a user hands midas: tensors only, never pickled Python objects."""

from __future__ import annotations

import pickle
import warnings
from pathlib import Path
from typing import Any

import torch

from midas_cli.errors import SessionError

# What torch.load raises on a file that is not a weights-only PyTorch file: EOFError (empty), pickle
# errors (random bytes, or pickled objects that weights_only refuses), RuntimeError (a damaged zip
# archive), OSError (unreadable), and the odd ValueError/KeyError/AttributeError from foreign pickles.
_LOAD_ERRORS = (OSError, EOFError, RuntimeError, ValueError, KeyError, AttributeError, pickle.UnpicklingError)


def load_weights_only(path: Path, what: str) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU; any file it cannot read safely is a
    SessionError naming ``what`` and the file, in one line."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "Detected pickle protocol 4 ...": the error says it
            return torch.load(path, map_location="cpu", weights_only=True)
    except _LOAD_ERRORS as exc:
        raise SessionError(f"cannot load {what} {path}: {_reason(exc)}") from exc


def _reason(exc: BaseException) -> str:
    if isinstance(exc, EOFError):
        return "the file is empty or truncated"
    if isinstance(exc, pickle.UnpicklingError) and "weights_only" in str(exc):
        return "it holds pickled Python objects, which midas never loads (tensors and plain types only)"
    if isinstance(exc, OSError):
        return exc.strerror or str(exc)
    first = str(exc).strip().splitlines()
    return first[0] if first else type(exc).__name__
