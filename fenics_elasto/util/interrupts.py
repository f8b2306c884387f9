"""Signals as interrupts: SIGINT, SIGTERM and SIGHUP all mean "stop, keep the best so far".

Ctrl-C sends SIGINT, batch schedulers and ``timeout`` send SIGTERM, a closed terminal
sends SIGHUP. Inside ``handle_signals()`` all three become an ``Interrupted`` (a
``KeyboardInterrupt``), so the one existing path -- ``except KeyboardInterrupt``: write
the best result so far -- serves them all. SIGINT is installed explicitly: a job started
in the background of a non-interactive shell inherits SIGINT *ignored*.

Only the first signal interrupts. Later ones are noted and wait, so that the best result
still gets written (two quick Ctrl-C used to lose it); the third abandons the run at once.
``deferred_signals()`` holds signals off while files are written: a signal inside is
noted, the writing finishes, and ``Interrupted`` is raised after the block.

After a hang-up the terminal is gone and every write to it fails (EIO): output that went
to a terminal goes to /dev/null from then on, so a progress line cannot lose the result.

Under MPI a signal must not stop the ranks at different places (each would then wait
forever in a different collective call). There the handler only notes it, and
``check_interrupt(comm)``, called by every rank at the same safe points (one per
objective evaluation, say), raises on all ranks together.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
import threading
from contextlib import contextmanager

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
ABANDON_AT = 3  # the third signal ends the process at once, writing nothing more


class Interrupted(KeyboardInterrupt):
    """A ``KeyboardInterrupt`` whose ``str`` is a one-line reason; the CLI exits 130.

    Raise ``Interrupted("before the first evaluation: nothing written")`` when there is
    nothing to keep, so the CLI can say so instead of claiming to write a result.
    """


def _is_terminal(stream_or_fd) -> bool:
    try:
        return os.isatty(stream_or_fd if isinstance(stream_or_fd, int) else stream_or_fd.fileno())
    except (AttributeError, OSError, ValueError):
        return False


class _State:
    def __init__(self, comm=None):
        self.comm = comm
        self.collective = comm is not None and comm.size > 1
        self.received: list[str] = []  # names of the signals seen, in order
        self.delivered = False  # an Interrupted has been raised for them already
        self.deferring = 0  # depth of deferred_signals()
        self.terminals = [fd for fd in (1, 2) if _is_terminal(fd)]  # known now: a hung-up tty is no tty

    @property
    def pending(self) -> bool:
        return bool(self.received) and not self.delivered


_state = _State()


@contextmanager
def python_interrupts(comm=None):
    """Ctrl-C raises KeyboardInterrupt inside the block where no Python handler is set
    (serial, main thread): ``gmsh.initialize()`` resets SIGINT to the default, which ends
    the process at once -- a script that meshed with gmsh lost its estimate's best result
    so far (a user's bar, 2026-12-07). A handler of the caller's (the command line's
    ``handle_signals``) is left alone, and on several ranks too, where a signal must stop
    them together. The previous handler comes back at the end."""
    previous = signal.getsignal(signal.SIGINT)
    if (threading.current_thread() is not threading.main_thread() or callable(previous)
            or (comm is not None and comm.size > 1)):
        yield
        return
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)


@contextmanager
def handle_signals(comm=None):
    """Turn SIGINT, SIGTERM and SIGHUP into ``Interrupted`` inside the block (main thread only).

    ``comm`` with more than one rank: signals are only noted; ``check_interrupt(comm)``
    raises them on every rank together. The previous handlers come back at the end.
    """
    global _state
    if threading.current_thread() is not threading.main_thread():  # signal.signal would refuse
        yield
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    streams = sys.stdout, sys.stderr
    saved, _state = _state, _State(comm)
    for s in SIGNALS:
        signal.signal(s, _on_signal)
    sys.stdout, sys.stderr = (_QuietAfterHangup(s) if _is_terminal(s) else s for s in streams)
    try:
        yield
    finally:
        for s, handler in previous.items():
            if handler is not None:  # None: set outside Python, cannot be restored from here
                signal.signal(s, handler)
        sys.stdout, sys.stderr = streams
        _state = saved


def restore_handlers() -> None:
    """Install Python's handlers of SIGINT, SIGTERM and SIGHUP again at the C level,
    after a library reset them behind Python's back: ``gmsh.initialize`` sets SIGTERM
    and SIGHUP to their default (the process dies at once, nothing written) while
    ``signal.getsignal`` still shows our handler. Main thread only; a no-op elsewhere."""
    if threading.current_thread() is not threading.main_thread():
        return
    for s in SIGNALS:
        handler = signal.getsignal(s)
        if handler is not None:
            signal.signal(s, handler)


def check_interrupt(comm=None, context: str = "") -> None:
    """Raise ``Interrupted`` (the signals' names, then ``context``) if a signal arrived
    and has not interrupted yet.

    With ``comm`` of several ranks this is collective: every rank must call it at the
    same point, and then all raise or none does.
    """
    state = _state
    pending = state.pending
    if comm is not None and comm.size > 1:
        pending = comm.allreduce(int(pending)) > 0
    if pending:
        state.delivered = True
        raise Interrupted((" ".join(state.received) or "a signal on another rank") + context)


@contextmanager
def deferred_signals(comm=None):
    """Hold signals off inside the block; afterwards raise ``Interrupted`` if one came.

    If the block raises, its exception goes on and the signal stays pending. With
    ``comm`` of several ranks every rank must run the block (the check after it is
    collective).
    """
    _state.deferring += 1
    try:
        yield
    finally:
        _state.deferring -= 1
    if not _state.deferring:
        check_interrupt(comm, " (after finishing the files being written)")


def _on_signal(signum, frame) -> None:
    state = _state
    name = signal.Signals(signum).name
    state.received.append(name)
    if signum == signal.SIGHUP:
        _leave_terminal()
    count = len(state.received)
    if count >= ABANDON_AT:
        _note(f"{name} ({count} signals): abandoning the run, nothing more is written")
        _abandon(state)
    if not (state.delivered or state.deferring or state.collective):
        state.delivered = True
        raise Interrupted(name)
    doing = ("still writing the best result so far" if state.delivered
             else "finishing the files being written first" if state.deferring else "stopping at the next step")
    _note(f"{name}: {doing}" + (" (one more signal abandons the run)" if count == ABANDON_AT - 1 else ""))


def _leave_terminal() -> None:
    """Output that went to the (now gone) terminal goes to /dev/null from here on."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for fd in _state.terminals:
        os.dup2(devnull, fd)
    os.close(devnull)


class _QuietAfterHangup:
    """A terminal stream that goes quiet instead of raising EIO once the terminal is gone
    (a print can run between the hang-up and the SIGHUP handler)."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        try:
            return self._stream.write(text)
        except OSError as err:
            self._hung_up(err)
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except OSError as err:
            self._hung_up(err)

    def _hung_up(self, err: OSError) -> None:
        if err.errno != errno.EIO:
            raise err
        _leave_terminal()

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _note(text: str) -> None:
    """One line on stderr from rank 0; raw os.write, since the handler may run while
    Python is inside a print to the same stream."""
    if _state.comm is None or _state.comm.rank == 0:
        try:
            os.write(2, f"{text}\n".encode())
        except OSError:
            pass


def _abandon(state: _State) -> None:
    if state.collective:
        state.comm.Abort(130)  # every rank, at once: none is left waiting in a collective
    os._exit(130)
