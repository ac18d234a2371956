"""Checkpoints of long runs: atomic npz files carrying a fingerprint of the run they belong to.

A checkpoint is written after every loop (or iteration) and read back to resume a run so that
it ends exactly as an uninterrupted run would; a truncated file, a file of another format
version or one whose fingerprint differs (another model, other data, other settings) is a
``ValueError``, never silently reused.
"""
from __future__ import annotations

import hashlib
import os

import numpy as np

from .history import History
from .protocol import model_fingerprint

__all__ = ["CHECKPOINT_FORMAT", "run_fingerprint", "save_checkpoint", "load_checkpoint"]

#: Version of the checkpoint layout; files of another version are refused.
CHECKPOINT_FORMAT = 3


def run_fingerprint(model, observations, settings: dict) -> str:
    """Hash of everything that determines a run: the model (its own fingerprint when it has one,
    see :class:`sfem_filters.filtering.protocol.Fingerprinted`), its x0, P0, Q, R and H, the
    observations (NaN kept distinct) and the ``settings`` that shape the trajectory (a dict of
    plain values, from the method's settings dataclass)."""
    h = hashlib.sha256()
    h.update(model_fingerprint(model).encode())
    for a in (model.x0, model.P0, model.Q, model.R, np.nan_to_num(np.asarray(observations, float), nan=1e300),
              model.H_jacobian(model.x0, 0)):
        h.update(np.ascontiguousarray(np.asarray(a, float)).tobytes())
    h.update(f"{model.dim_state},{model.n_frames},{sorted(settings.items())!r}".encode())
    return h.hexdigest()


def save_checkpoint(path, fingerprint, theta, P_theta, rel_changes, history, loops_done, **extra):
    """Write a resumable checkpoint atomically (npz): a temporary file, then a rename.

    ``extra`` arrays (for example an iterated smoother's trajectory) are stored beside the
    standard keys.
    """
    tmp = f"{path}.tmp.npz"
    np.savez(tmp, format_version=CHECKPOINT_FORMAT, fingerprint=fingerprint, theta=theta,
             P_theta=P_theta, rel_changes=np.asarray(rel_changes, float), loops_done=loops_done,
             **history.as_arrays(), **extra)
    os.replace(tmp, path)


def load_checkpoint(path, fingerprint=None) -> dict:
    """Read a checkpoint; a truncated or foreign file raises ``ValueError``."""
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except Exception as exc:  # zipfile / format errors differ between numpy versions
        raise ValueError(f"checkpoint: {path} is not a readable checkpoint ({exc})") from None
    need = {"format_version", "fingerprint", "theta", "P_theta", "rel_changes", "loops_done",
            *History.KEYS}
    missing = need - set(data)
    if missing:
        raise ValueError(f"checkpoint: {path} lacks {sorted(missing)}")
    if int(data["format_version"]) != CHECKPOINT_FORMAT:
        raise ValueError(f"checkpoint: {path} has format {int(data['format_version'])}, "
                         f"expected {CHECKPOINT_FORMAT}")
    if fingerprint is not None and str(data["fingerprint"]) != fingerprint:
        raise ValueError(f"checkpoint: {path} belongs to a different model or data set")
    return data
