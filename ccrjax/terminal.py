"""What every command does at the terminal: the one way Ctrl-C and SIGTERM stop it, the
progress line, and the announced compilation.

**Stopping.** A command calls :func:`install` as its first statement, before its other
imports, so that a signal is answered from the command's first statement on (this module
imports only the standard library, and ``tqdm`` only when a progress bar is drawn). Only the
interpreter's own start-up comes before it (finding the site packages, compiling the
command's module: tens of milliseconds, longer on a loaded machine), where Python answers
Ctrl-C with its ``KeyboardInterrupt``. From then on SIGINT and SIGTERM never raise inside
the program: the interpreter's C handler
writes the signal's number to a pipe (``signal.set_wakeup_fd``) the moment it arrives, and a
watcher thread reading it acts at once, whatever the main thread is doing (importing,
tracing, or inside XLA, which cannot be interrupted and releases the interpreter's lock).
What it does depends on the command's phase (:attr:`Stop.phase`):

* ``"starting"`` (imports, set-up, tracing, compiling; the whole of an experiment): it
  waits for the checkpoint writes in flight (:func:`on_exit`), prints one line saying what
  was kept (:attr:`Stop.kept`), and ends the process with status 130 at once;
* ``"working"`` (training between checkpoints): the first signal is a request
  (:attr:`Stop.requested`) that the command honours at its next safe point, said in one line
  (:attr:`Stop.when`); a second ends the process as in ``"starting"``, within seconds,
  whatever the evaluation interval;
* ``"done"``: a request the command's :meth:`Stop.closing` reports as status 130.

The process ends through ``os._exit``: XLA would otherwise finish a computation in flight
(minutes on a CPU) before the interpreter could exit. What is kept is on disk by then: run
folders write atomically, and orbax writes a checkpoint into a temporary folder renamed
into place, which the exit waits for.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

INTERRUPTED = 130  # the shell's status for a command stopped by Ctrl-C
_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # the signals that stop a command
# The longest the exit waits for a checkpoint being written.
WRITE_WAIT_S = 120.0

_WAITS: dict[int, Callable[[], None]] = {}
_WAITS_LOCK = threading.Lock()


def on_exit(wait: Callable[[], None]) -> int:
    """Registers ``wait`` (blocks until a checkpoint write in flight is on disk) to run
    before a stop ends the process; returns the token :func:`forget` takes."""
    with _WAITS_LOCK:
        token = max(_WAITS, default=0) + 1
        _WAITS[token] = wait
    return token


def forget(token: int) -> None:
    with _WAITS_LOCK:
        _WAITS.pop(token, None)


def _finish_writes() -> None:
    with _WAITS_LOCK:
        waits = list(_WAITS.values())
    for wait in waits:
        thread = threading.Thread(target=wait, daemon=True)
        thread.start()
        thread.join(WRITE_WAIT_S)


class Stop:
    """The process's stop state, shared by the command and the watcher thread."""

    def __init__(self, prog: str) -> None:
        self.prog = prog
        self.phase = "starting"
        # What a stop keeps, said after "stopped by SIGINT ...; " (a string or a function).
        self.kept: str | Callable[[], str] = "nothing was written"
        # What the first signal while working waits for.
        self.when = "finishing the current chunk, then saving a checkpoint"
        self.signal_name: str | None = None
        self.count = 0

    @property
    def requested(self) -> bool:
        return self.signal_name is not None

    def kept_text(self) -> str:
        return self.kept() if callable(self.kept) else self.kept

    def arrived(self, number: int) -> None:
        """What the watcher does with signal ``number``."""
        self.count += 1
        self.signal_name = self.signal_name or signal.Signals(number).name
        if self.phase == "done":
            return
        if self.phase == "starting" or self.count > 1:
            self.exit_now()
        print(f"\n{self.prog}: {self.signal_name}: {self.when} (press again to stop at once, "
              "losing the work since the last checkpoint)", file=sys.stderr, flush=True)

    def exit_now(self) -> None:
        """Waits for the checkpoint writes in flight, says what is kept, ends the process."""
        _finish_writes()
        try:
            kept = self.kept_text()
        except Exception as error:  # noqa: BLE001 - the exit must happen whatever failed
            kept = f"(what was kept could not be listed: {error})"
        print(f"\n{self.prog}: stopped by {self.signal_name}; {kept}", file=sys.stderr,
              flush=True)
        try:
            sys.stdout.flush()
        finally:
            os._exit(INTERRUPTED)

    def closing(self, status: int) -> int:
        """The command's exit status: a request that came once everything was written
        still ends it with 130, said in one line."""
        if status == 0 and self.requested:
            print(f"{self.prog}: stopped by {self.signal_name} after the work finished; "
                  "everything is written", file=sys.stderr, flush=True)
            return INTERRUPTED
        return status


_CURRENT: Stop | None = None
_WATCHER: dict[str, Any] = {}


def current() -> Stop | None:
    """The installed :class:`Stop`, or ``None`` (a library call, not a command)."""
    return _CURRENT


def install(prog: str) -> Stop:
    """Answers SIGINT and SIGTERM from now on as the module docstring says; returns the
    process's :class:`Stop` (a fresh one on every call, for commands run one after another
    in one process). Outside the main thread nothing is installed."""
    global _CURRENT
    _CURRENT = Stop(prog)
    if threading.current_thread() is not threading.main_thread():
        return _CURRENT
    if not _WATCHER:
        with _held(_SIGNALS):
            read, write = os.pipe()
            os.set_blocking(write, False)
            _WATCHER["fds"] = (read, write)
            _WATCHER["previous_fd"] = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
            thread = threading.Thread(target=_watch, args=(read,), name="stop-watcher",
                                      daemon=True)
            thread.start()
            _WATCHER["thread"] = thread
            _WATCHER["previous"] = {number: signal.signal(number, _note)
                                    for number in _SIGNALS}
    return _CURRENT


@contextlib.contextmanager
def _held(numbers: tuple[int, ...]) -> Iterator[None]:
    """Holds ``numbers`` pending (``pthread_sigmask``) in the block: a signal that comes
    while the handlers, the wakeup pipe and the watcher are half in place is delivered once
    they all are, neither lost nor met by Python's default ``KeyboardInterrupt``. The
    watcher, started inside, keeps them held, so they reach the main thread."""
    if not hasattr(signal, "pthread_sigmask"):  # not on Windows
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, numbers)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)  # as it was (held if it was)


@contextlib.contextmanager
def stopping(prog: str) -> Iterator[Stop]:
    """:func:`install` for the block. Where the process is a command that installed the
    handling at its first statement, it stays after the block; otherwise (a command called
    inside another program, such as a test) the previous handlers come back."""
    installed_before = bool(_WATCHER)
    stop = install(prog)
    try:
        yield stop
    finally:
        if not installed_before:
            uninstall()


def run_command(prog: str, main: Callable[[], int], kept: str) -> int:
    """``main()`` as a command whose every moment is ``"starting"``: a signal ends it at
    once, after the checkpoint writes in flight, with one line saying what was ``kept``
    and status 130 (the experiments' entry point)."""
    with stopping(prog) as stop:
        stop.kept = kept
        return main()


def uninstall() -> None:
    """Gives SIGINT and SIGTERM back to their previous handlers (tests that run a command
    in their own process)."""
    global _CURRENT
    _CURRENT = None
    if not _WATCHER:
        return
    signal.set_wakeup_fd(_WATCHER["previous_fd"])
    for number, handler in _WATCHER["previous"].items():
        signal.signal(number, handler)
    read, write = _WATCHER["fds"]
    os.close(write)  # the watcher reads the end of the pipe and returns
    _WATCHER["thread"].join(timeout=5)
    os.close(read)
    _WATCHER.clear()


def _note(number: int, frame: Any) -> None:
    """The Python-level handler, run in the main thread at its next bytecode: it only marks
    the request, so that a command polling :attr:`Stop.requested` sees it at once (the
    watcher acts on it). Its being set makes the interpreter's C handler write to the
    wakeup pipe."""
    if _CURRENT is not None and _CURRENT.signal_name is None:
        _CURRENT.signal_name = signal.Signals(number).name


def _watch(read: int) -> None:
    while True:
        try:
            numbers = os.read(read, 64)
        except OSError:
            return
        if not numbers:
            return
        for number in numbers:
            if number in (signal.SIGINT, signal.SIGTERM) and _CURRENT is not None:
                _CURRENT.arrived(number)


# ---------------------------------------------------------------------------- progress
class Progress:
    """A progress bar on a terminal, one line per evaluation otherwise."""

    def __init__(self, total_steps: int, seeds: int, done_steps: int, bar: bool) -> None:
        self.seeds = seeds
        self.total = total_steps
        self.bar = None
        self.last_time = time.perf_counter()
        self.last_steps = done_steps
        if bar:
            from tqdm import tqdm  # here: this module loads before anything else

            self.bar = tqdm(total=total_steps, initial=done_steps, unit="step", unit_scale=True,
                            desc=f"training ({seeds} seed{'s' * (seeds > 1)}, steps per seed)",
                            file=sys.stderr, dynamic_ncols=True, smoothing=0.3)

    def update(self, steps: int, success: float, danger: float) -> None:
        now = time.perf_counter()
        rate = (steps - self.last_steps) * self.seeds / max(now - self.last_time, 1e-9)
        self.last_time, self.last_steps = now, steps
        if self.bar is not None:
            self.bar.set_postfix_str(f"{rate:,.0f} env steps/s (all seeds), success "
                                     f"{success:.2f}, danger {danger:.3f}")
            self.bar.update(steps - self.bar.n)
        else:
            print(f"steps {steps:,}/{self.total:,} per seed · {rate:,.0f} env steps/s (all "
                  f"seeds) · success {success:.3f} · danger {danger:.3f}", file=sys.stderr,
                  flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def compile_phase(what: str, function: Any, *examples: Any, ticker: bool) -> Any:
    """Compiles the jitted ``function`` for ``examples`` as its own announced phase (a
    ticking line on a terminal); returns it compiled."""
    print(f"compiling {what}; training starts when it is done ...", file=sys.stderr,
          flush=True)
    start = time.perf_counter()
    done = threading.Event()

    def tick() -> None:
        while not done.wait(1.0):
            print(f"\r  compiling ... {time.perf_counter() - start:4.0f} s", end="",
                  file=sys.stderr, flush=True)

    thread = threading.Thread(target=tick, daemon=True) if ticker else None
    if thread:
        thread.start()
    try:
        compiled = function.lower(*examples).compile()
    finally:
        done.set()
        if thread:
            thread.join()
            print("\r", end="", file=sys.stderr)
    print(f"  compiled in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    return compiled
