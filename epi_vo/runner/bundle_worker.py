"""The windowed bundle adjustment beside the frame loop: a worker process and the solvers that use it.

Why a process and not a thread: GTSAM's C++ solve releases Python's GIL, but the floor-plane factors
(``ground_plane``) are Python callbacks that need it for every evaluation. In a thread beside a busy
frame loop such a window starved at the GIL's switch interval (a 140-point floor window: 116 ms alone,
1.4 s in a thread). A worker *process* runs ``bundle.adjust`` on the second core instead. It is
started with the interpreter the pipeline runs in (``python -m epi_vo.runner.bundle_worker``), imports
only numpy and GTSAM, and speaks pickle over its stdin / stdout: a :class:`bundle.Window` in, an
:class:`bundle.Adjusted` (or None) out, in order. Its own prints go to stderr, so nothing else ever reaches the pipe.

The result does not depend on where it was computed: the window's arrays cross the pipe bit for bit
and the worker runs the same function (tested: identical trajectories either way). Results are read
from the pipe by a thread of their own as they come, so ``ready`` can say, without waiting, whether the
oldest one is back (``ba_wait: false``: the frame loop never waits for it). A worker that dies
or answers garbage is not an input problem: :class:`ProcessSolver` says why once (``take_failure``) and
solves the window it lost, and every later one, in the calling process. The worker runs below the
pipeline's scheduling priority (``WORKER_NICENESS``): a frame must not wait for a solve that has until
the next keyframe.
"""

from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import weakref
from typing import IO, Any

MODULE = "epi_vo.runner.bundle_worker"
# The worker's scheduling priority below the pipeline's (POSIX nice increment). On two cores the frame
# loop, its KLT thread and the worker compete; at the same priority the worker's solves pushed
# ground_robot's paced frame p95 (ground_plane, window 8, ba_wait false) to 25-32 ms, niced by 10 to
# 20-26 ms, where the same bag without a window gives 21-25 ms; the solves take as long (180-195 ms).
WORKER_NICENESS = 10


def _read_results(out: IO[bytes], results: queue.SimpleQueue[tuple[bool, Any]]) -> None:
    """The reader thread: every result the worker writes, as it comes; at the end (EOF, a dead worker,
    garbage) the exception that ended it, flagged False. It holds no reference to its solver."""
    while True:
        try:
            results.put((True, pickle.load(out)))
        except (OSError, EOFError, ValueError, pickle.UnpicklingError, AttributeError, ImportError) as exc:
            results.put((False, exc))
            return


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """End a worker: EOF on its stdin ends its loop; kill it if it does not."""
    try:
        if proc.stdin is not None:
            proc.stdin.close()
        proc.wait(timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()
    finally:
        if proc.stdout is not None:
            proc.stdout.close()


class ProcessSolver:
    """Solves in a worker process (``ba_solver: process``): ``send`` hands a window over and returns at
    once; ``receive`` waits for the oldest window's result, ``ready`` says whether it is back. Started on
    construction, so its imports (about a second) overlap the first keyframes."""

    def __init__(self) -> None:
        self.failure = ""  # why the worker is no longer used ("" while it is)
        self._failure_said = False
        from epi_vo.core.workers import InlineSolver  # here: the worker process itself needs only bundle

        self._inline = InlineSolver()
        self._sent: list[Any] = []  # windows sent and not yet received (kept to solve here if it dies)
        self._proc: subprocess.Popen[bytes] | None = None
        self._results: queue.SimpleQueue[tuple[bool, Any]] = queue.SimpleQueue()
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", MODULE], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE)
        except OSError as exc:
            self._fail(f"could not start the bundle adjustment worker ({exc})")
            return
        self._finalizer = weakref.finalize(self, _stop, self._proc)
        threading.Thread(target=_read_results, args=(self._proc.stdout, self._results), daemon=True,
                         name="epi_vo_ba_results").start()

    def _fail(self, reason: str) -> None:
        if not self.failure:
            self.failure = f"{reason}: adjusting in the frame loop from now on"
        if self._proc is not None:
            self._finalizer()
            self._proc = None

    def send(self, window: Any) -> None:
        self._sent.append(window)
        if self._proc is None:
            return
        try:
            assert self._proc.stdin is not None
            pickle.dump(window, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
        except (OSError, pickle.PicklingError) as exc:
            self._fail(f"the bundle adjustment worker stopped taking windows ({exc})")

    def ready(self) -> bool:
        """Whether ``receive`` would return without waiting for the worker: the oldest window's result
        (or the news that the worker ended) is back, or the worker is no longer used (``receive`` then
        solves here: the fallback does not pretend to be on time)."""
        return self._proc is None or not self._results.empty()

    def receive(self) -> Any:
        window = self._sent.pop(0)
        if self._proc is not None:
            ok, value = self._results.get()
            if ok:
                return value
            code = self._proc.poll()
            how = f"exited with {code}" if code is not None else "failed"
            self._fail(f"the bundle adjustment worker {how} ({type(value).__name__})")
        self._inline.send(window)
        return self._inline.receive()

    def in_flight(self) -> int:
        """Windows sent and not yet received."""
        return len(self._sent)

    def take_failure(self) -> str:
        """``failure``, the first time it is asked after the worker stopped being used ("" else)."""
        if not self.failure or self._failure_said:
            return ""
        self._failure_said = True
        return self.failure

    def close(self) -> None:
        self._sent.clear()
        if self._proc is not None:
            self._finalizer()
            self._proc = None


def serve(inp: IO[bytes], out: IO[bytes]) -> int:
    """The worker's loop: a window in, its adjustment out, until EOF on ``inp``."""
    from epi_vo.core import bundle

    while True:
        try:
            window = pickle.load(inp)
        except EOFError:
            return 0
        pickle.dump(bundle.adjust(window), out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


def main() -> int:
    try:  # the frame loop comes first: the worker has the stamp interval between keyframes, a frame has not
        os.nice(WORKER_NICENESS)
    except (AttributeError, OSError):  # no os.nice on this platform, or not allowed: run at the parent's
        pass
    # The protocol gets the real stdout; anything printed (by GTSAM or a warning) goes to stderr.
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    try:
        return serve(sys.stdin.buffer, out)
    except KeyboardInterrupt:  # the node's process group got a SIGINT: the parent ends us too
        return 0


if __name__ == "__main__":
    sys.exit(main())
