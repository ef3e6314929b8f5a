"""Preemption: SIGTERM and a warning signal stop training at the next optimizer-step boundary.

Cluster schedulers stop a job with SIGTERM and, after a grace period, SIGKILL; SLURM can send a
warning signal first (`#SBATCH --signal=USR1@90`). The handler only records the signal. The loop asks
`should_stop` at every step boundary; under torchrun that is an all-reduce (MAX) of the flag, so all
ranks stop after the same step even when only one of them got the signal, and none waits in a
collective the others never enter. Rank 0 then writes `last.pt` and the command exits with
`EXIT_PREEMPTED`; `--resume` continues as after Ctrl-C (docs/training.md, "Preemption").
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType

from fastocc import dist as D

__all__ = ["EXIT_INTERRUPTED", "EXIT_PREEMPTED", "StopRequest", "stop_signals"]

EXIT_PREEMPTED = 143  # 128 + SIGTERM: last.pt was written, resume with --resume (also after the warning signal)
EXIT_INTERRUPTED = 130  # 128 + SIGINT: Ctrl-C, last.pt was written


def stop_signals(warn_signal: str) -> tuple[signal.Signals, ...]:
    """SIGTERM plus the configured warning signal ("USR1", "USR2" or "none")."""
    extra = () if warn_signal == "none" else (signal.Signals[f"SIG{warn_signal}"],)
    return (signal.SIGTERM, *extra)


class StopRequest:
    """Context manager: while active, the given signals set `received` instead of killing the process."""

    def __init__(self, signals: tuple[signal.Signals, ...]) -> None:
        self.signals = signals
        self.received: signal.Signals | None = None
        self._old: dict[signal.Signals, object] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is None:
            self.received = signal.Signals(signum)

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():  # handlers can only be set there
            for s in self.signals:
                self._old[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        for s, old in self._old.items():
            signal.signal(s, old)  # type: ignore[arg-type]
        self._old.clear()

    def should_stop(self, info: D.DistInfo) -> bool:
        """Whether any rank received a stop signal; a collective under torchrun (call at step boundaries)."""
        return D.any_rank(self.received is not None, info)
