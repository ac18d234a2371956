"""The rounds' progress lines on stderr, and what an interruption had finished."""
from __future__ import annotations

import sys
import time

import numpy as np
from tqdm.auto import tqdm

from .records import Round

__all__ = ["progress_line", "RoundsInterrupted"]


def progress_line(text: str, enabled: bool = True) -> None:
    """Write one line of progress on stderr, above any progress bar (``tqdm.write``), if ``enabled``.
    Every progress message of the rounds goes through here (``progress=False``, the command
    line's ``--quiet`` or ``--no-progress``: none)."""
    if enabled:
        tqdm.write(text, file=sys.stderr)


def _duration(seconds: float) -> str:
    """``seconds`` as ``"42 s"``, ``"3 min 05 s"`` or ``"1 h 02 min"``."""
    s = int(round(max(float(seconds), 0.0)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


def _gain_text(entry: dict) -> str:
    """A fitted model's evidence (and with ``criterion="cv"`` its cross-validation) against the current model."""
    out = f"evidence {entry['evidence_gain']:+.1f} nats" if np.isfinite(entry["evidence_gain"]) else "evidence n/a"
    if "cv_rmse_px" in entry:
        out += f", CV {entry['cv_rmse_px']:.3f} px"
    return out


class _Progress:
    """The rounds' progress lines (:func:`progress_line`): one as the baseline and as each round
    ends, with the held-out error so far against the spline's, the elapsed time and an upper bound
    of the time left; and, for an interruption, what had finished (:meth:`finished`)."""

    def __init__(self, enabled: bool, max_rounds: int, material: str):
        self.enabled, self.max_rounds, self.material = enabled, max_rounds, material
        self.t0 = time.perf_counter()
        self.rounds_t0 = self.round_t0 = None
        self.rounds_done = 0
        self.model = None                   # (label, held-out RMSE px) of the model so far
        self.spline_px = None

    def say(self, text: str) -> None:
        progress_line(text, self.enabled)

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def _heldout(self, r: "Round") -> str:
        px = float(r.run.metrics["heldout_rmse_px"])
        self.model = (r.variant.label(r.variant.drive), px)
        spline = "" if self.spline_px is None else f" (spline {self.spline_px:.3f} px)"
        return f"held-out error {px:.3f} px{spline}"

    def baseline(self, r: "Round", spline_px: float) -> None:
        self.spline_px = float(spline_px)
        self.rounds_t0 = self.round_t0 = time.perf_counter()
        material = "material fixed" if self.material == "none" else f"{self.material} map"
        self.say(f"baseline ({material}): log p(y) {r.log_evidence:.1f} nats; {self._heldout(r)}; "
                 f"elapsed {_duration(self.elapsed())}")

    def round_end(self, number: int, tried: list, added: list, stop: str | None = None) -> None:
        """Round ``number`` has ended: ``tried`` its fitted candidates and corrections, ``added`` the
        rows it appended (the kept step and its backward steps), ``stop`` why the rounds end here."""
        self.rounds_done = number
        now = time.perf_counter()
        took, self.round_t0 = now - self.round_t0, now
        tried_text = ", ".join(f"{t['effect']} (" + (f"score {t['score']:.1f}, " if t.get("score") is not None else "")
                               + f"{_gain_text(t)})" for t in tried)
        parts = ["tried " + (tried_text or "nothing")]
        for r in added:
            if getattr(r, "removed", None):
                parts.append(f"backward: took out {r.removed}")
            elif r.added is not None:
                parts.append(f"kept {r.added}")
        if stop is not None:
            parts.append(f"stopped: {stop}")
        if added or self.model is None:
            parts.append(self._heldout(added[-1]) if added else "")
        else:
            spline = "" if self.spline_px is None else f" (spline {self.spline_px:.3f} px)"
            parts.append(f"held-out error {self.model[1]:.3f} px{spline}")
        parts.append(f"elapsed {_duration(self.elapsed())}")
        left = self.max_rounds - number
        if stop is None and left > 0:
            mean = (time.perf_counter() - self.rounds_t0) / number
            parts.append(f"at most about {_duration(left * mean)} left (upper bound: {left} round"
                         f"{'s' if left > 1 else ''} left x {_duration(mean)}, the mean round so far)")
        self.say(f"round {number} ({_duration(took)}): " + "; ".join(p for p in parts if p))

    def finished(self) -> str:
        """What had finished when the rounds were interrupted, and that nothing of it is kept."""
        if self.model is None:
            done = "before the baseline fit finished"
        else:
            done = (f"after the baseline" + (f" and {self.rounds_done} round{'s' if self.rounds_done > 1 else ''}"
                                            if self.rounds_done else "")
                    + f" (model so far: {self.model[0]}, held-out error {self.model[1]:.3f} px)")
        return (f"interrupted {done}, {_duration(self.elapsed())} in; nothing is kept (the rounds keep no "
                f"checkpoint): run again to redo them")


class RoundsInterrupted(KeyboardInterrupt):
    """:func:`closing_the_loop` stopped by Ctrl-C (SIGINT): its worker processes are stopped and
    ``message`` says what had finished (:meth:`_Progress.finished`)."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message
