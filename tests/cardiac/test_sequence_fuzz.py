"""Malformed sequence files: a clear error naming the file, CLI exit 2 (issue 6)."""
import contextlib
import io

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.cardiac.sequence import load_sequence
from sfem_filters.cli import main


# --------------------------------------------------------------------- fuzzed sequence files
def _mutated_file(path, kind, data, rng):
    """Write a malformed variant of a valid sequence file (a dict of arrays) to ``path``."""
    d = dict(data)
    if kind == "truncate":
        buf = io.BytesIO()
        np.savez(buf, **d)
        raw = buf.getvalue()
        path.write_bytes(raw[: int(rng.integers(0, len(raw) - 1))])
        return
    if kind == "flip_bytes":
        buf = io.BytesIO()
        np.savez_compressed(buf, **d)
        raw = bytearray(buf.getvalue())
        for i in rng.integers(0, len(raw), size=8):
            raw[i] ^= 0xFF
        path.write_bytes(bytes(raw))
        return
    key = ["points", "displacement"][int(rng.integers(0, 2))]
    if kind == "drop_key":
        d.pop(key)
    elif kind == "string_dtype":
        d[key] = d[key].astype(str)
    elif kind == "bool_dtype":
        d[key] = d[key] > 0
    elif kind == "nan_everywhere":
        d["displacement"] = np.full_like(d["displacement"], np.nan)
    elif kind == "inf_value":
        d[key] = d[key].copy()
        d[key].flat[int(rng.integers(0, d[key].size))] = np.inf
    elif kind == "wrong_shape":
        d[key] = d[key].reshape(-1)
    elif kind == "one_frame":
        d["displacement"] = d["displacement"][:1]
    elif kind == "bad_optional":
        d[["frame_interval", "pixel_spacing", "confidence", "sigma"][int(rng.integers(0, 4))]] = -np.ones(3)
    np.savez(path, **d)


@settings(max_examples=40, deadline=None)
@given(kind=st.sampled_from(["truncate", "flip_bytes", "drop_key", "string_dtype", "bool_dtype", "nan_everywhere",
                             "inf_value", "wrong_shape", "one_frame", "bad_optional"]),
       seed=st.integers(0, 2 ** 31 - 1))
def test_fuzzed_sequence_files_give_a_clear_error_and_cli_exit_2(tmp_path_factory, kind, seed):
    """Malformed sequence files: the loader raises ValueError naming the file (never another
    exception, never a partial sequence), and the CLI exits with 2 and a one-line error."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([np.arange(6.0), np.arange(6.0) % 2])
    data = {"points": pts, "displacement": rng.standard_normal((4, 6, 2)), "frame_interval": np.array(0.03)}
    path = tmp_path_factory.mktemp("fuzz") / "seq.npz"
    _mutated_file(path, kind, data, rng)
    try:
        load_sequence(path)
    except ValueError as exc:
        assert str(path) in str(exc)
    else:
        # only a byte flip can land where it changes nothing (a valid file); every other
        # mutation must be refused
        assert kind == "flip_bytes", f"{kind}: a malformed file was accepted"
        return
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["dense", str(path), "--no-progress"])
    assert code == 2
    text = err.getvalue()
    assert text.startswith("sfem-filters dense: error:") and "Traceback" not in text
