"""The learner's update, compiled (`compile = auto`): torch.compile of
`tpdeb_core.learner.Update`, the whole update as one graph (forward, targets, loss, its
gradient, clip, Adam, soft target), prepared while the learner trains.

Compiling takes seconds (tens of seconds with no cache), so the learner never waits for it: its
first updates run eagerly while a thread traces and compiles the update on a copy of the learner's
tensors (the same shapes, a batch it already trained on), and the loop switches to the compiled
function between two updates once it is ready. The update reads nothing but its arguments and fixed
settings, so what was traced on the copy runs the learner as it is. Inductor's cache lives under
the user's cache directory (`$XDG_CACHE_HOME/tpdeb/inductor`, else `~/.cache/tpdeb/inductor`), so a
second start of any run on the machine compiles from cache. A compile that fails leaves the update
eager and says why once.

On the CPU inductor fuses the elementwise work of all of it into a few C++ loops around the
matmuls; on CUDA the compiled update runs as CUDA graphs (`mode="reduce-overhead"`), with Adam
capturable and every scalar on the device.
"""

from __future__ import annotations

import copy
import logging
import os
import threading
import time
from pathlib import Path

import torch

from tpdeb.tpdeb_core.learner import Batch, Learner, State

log = logging.getLogger("tpdeb-learner")
COMPILE_THREAD = "compile"  # the thread's name: its trial updates train a copy, alone


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "tpdeb" / "inductor"


def configure_compiler() -> None:
    """Inductor's cache in the user's cache directory (unless TORCHINDUCTOR_CACHE_DIR says
    otherwise) and its C++ compiles in this process: a pool of compile workers would cost
    each learner hundreds of MiB and compete with the actors for the cores."""
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(cache_dir()))
    import torch._inductor.config as inductor

    inductor.compile_threads = 1


def compile_options(learner: Learner) -> dict:
    return {"mode": "reduce-overhead"} if learner.device.type == "cuda" else {}


class BackgroundCompile:
    """Compiles a learner's update on a copy, in a thread; `install` switches the learner."""

    def __init__(self, learner: Learner):
        self.learner = learner
        # made in the thread: importing the compiler (~1.5 s, ~110 MiB) must not hold back
        # the first update
        self.update = None
        self.done = threading.Event()
        self.error: str | None = None
        self.seconds = 0.0
        self.thread: threading.Thread | None = None

    def start(self, batch: Batch, norm: torch.Tensor) -> None:
        """Begin with a batch the learner has trained on (its shapes are every batch's)."""
        shadow = copy.deepcopy(self.learner.state)  # the tensors only: the learner trains on
        self.thread = threading.Thread(target=self._compile, args=(shadow, batch, norm),
                                       daemon=True, name=COMPILE_THREAD)
        self.thread.start()

    def _compile(self, shadow: State, batch: Batch, norm: torch.Tensor) -> None:
        started = time.perf_counter()
        try:
            if self.update is None:
                configure_compiler()
                self.update = torch.compile(self.learner.rules.traced,
                                            **compile_options(self.learner))
            for _ in range(2):  # the second call runs what the first compiled
                self.update(shadow, batch, norm)
        except Exception as exc:  # noqa: BLE001 - reported; the learner stays eager
            self.error = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0][:200]}"
        self.seconds = time.perf_counter() - started
        self.done.set()

    def reset(self) -> None:
        """Compile again on the next `start` (a new batch shape: batch growth). The thread
        has ended: the learner installed what it made."""
        self.thread = None
        self.done.clear()
        self.error = None

    def ready(self) -> bool:
        return self.done.is_set()

    def install(self) -> bool:
        """Switch the learner to the compiled update (True), or say why it stays eager. The
        thread is joined first (it has ended or is ending): a process must not exit with it
        inside the compiler, which aborts the interpreter."""
        self.thread.join()
        if self.error is not None:
            log.warning(f"the compiled update could not be prepared ({self.error}); training "
                        "goes on eager (--set compile=off skips the attempt)")
            return False
        self.learner.use(self.update)
        log.info(f"update compiled in {self.seconds:.1f} s (in the background); the learner "
                 "runs it from here")
        return True
