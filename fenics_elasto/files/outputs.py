"""Result folders that never lie: checked before the work, locked, written atomically.

A result folder is complete exactly when it holds ``result.json``. That file is written
last and lists every other file of the run (``"files"``); it is removed before a new run
writes anything, so a folder never mixes two runs. Every file -- and every directory,
such as the VTX ``.bp`` output -- is written under a temporary name in the same folder
(``.<stem>.part-<pid><suffix>``) and renamed into place, so a writer killed half-way
leaves the old file or none, never half of one. A lock file keeps a second run out.

    folder = prepare_folder(out, comm)                  # before any work: refuses a bad --out, locks
    ...                                                 # the long computation
    with folder.writing(result):                        # signals wait; result.json last; unlocks
        folder.write_text("forces.csv", text)           # small files: rank 0
        write_displacement(u, folder.path_for("displacement.bp"))  # collective: every rank

A full disk or an I/O error while writing is a ``UserError`` naming the file; the small
results (``result.json`` and what ``write_text`` got) are first saved to a fallback
folder, ``$TMPDIR/fenics-elasto-<pid>``, named in the message. Single output files
(``train``'s bases, ``render``'s picture) go through ``prepare_file(...).write(writer)``.
Under MPI rank 0 checks, locks and renames; every rank gets the same verdict.
"""

from __future__ import annotations

import atexit
import errno
import json
import os
import shutil
import socket
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from mpi4py import MPI

from fenics_elasto.util.errors import UserError, on_root, require
from fenics_elasto.util.interrupts import deferred_signals

MARKER = "result.json"
LOCK = ".fenics-elasto.lock"
PART = ".part-"
PSEUDO_ROOTS = ("/proc", "/sys", "/dev")  # kernel file systems: never a place for results ...
SCRATCH = ("/dev/shm",)  # ... except the shared-memory tmpfs
EMPTY_LOCK_STALE_S = 10.0  # a lock file is written right after it is created: still empty by now = abandoned


# --------------------------------------------------------------------------- checks before the work


def prepare_folder(path, comm=None, say=None) -> OutputFolder:
    """Check ``path`` as a result folder before any work, and lock it.

    Creates it (and its parents) or verifies that it is a writable directory: a probe
    file is created, written, fsynced and removed. One-line ``UserError`` (the path and
    the cause) for an existing non-directory, a path under /proc, /sys or /dev, a
    read-only or full place, a parent that cannot be created, or a folder another run is
    using. A lock left by a run that is gone is taken over, with a note to ``say``
    (default: stderr). Collective: rank 0 checks, every rank gets its verdict.
    """
    comm = comm or MPI.COMM_WORLD
    path = Path(path)
    with deferred_signals(comm):  # the lock is taken whole and recorded for release
        created, note = on_root(comm, lambda: _check_and_lock(path))
        folder = OutputFolder(path, comm, comm.bcast(os.getpid(), root=0), created)
        atexit.register(folder.release)
    if note and comm.rank == 0:
        (say or _stderr)(note)
    return folder


def prepare_file(path, suffix: str, comm=None) -> OutputFile:
    """Check ``path`` as a single output file (``train --out BASES.npz``, ``render --out PNG``).

    The path is taken literally, except that a missing suffix is added (``bases`` ->
    ``bases.npz``): print ``.path``, the name actually written. Another suffix is
    refused, as are an existing directory, an existing non-regular file and the kernel
    file systems. Its directory is created if missing and probed as in ``prepare_folder``.
    """
    comm = comm or MPI.COMM_WORLD
    given = Path(path)
    path = given if given.suffix else given.with_name(given.name + suffix)

    def check():
        _refuse_kernel_place(given)
        require(not given.is_dir(), f"{given}: is a directory; give a file name ending in {suffix}")
        require(path.suffix.lower() == suffix, f"{given}: the output must be a {suffix} file")
        require(not os.path.lexists(path) or path.is_file(), f"{path}: exists and is not a regular file")
        _check_directory(path.parent)

    on_root(comm, check)
    return OutputFile(path, comm, comm.bcast(os.getpid(), root=0))


def _check_and_lock(path: Path):
    created = _check_directory(path)
    note = _take_lock(path)
    for leftover in path.glob(f".*{PART}*"):  # temporaries of a killed run (we hold the lock: no one writes)
        _remove(leftover, quiet=True)
    return created, note


def _check_directory(path: Path) -> list[Path]:
    """Make ``path`` a writable directory; return the directories created (outermost first)."""
    _refuse_kernel_place(path)
    require(not os.path.lexists(path) or path.is_dir(), f"{path}: exists and is not a directory")
    missing, ancestor = [], path
    while not os.path.lexists(ancestor):
        missing.append(ancestor)
        ancestor = ancestor.parent
    require(ancestor.is_dir(), f"{path}: cannot create it, {ancestor} is not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UserError(f"{path}: cannot create it ({_cause(err)})") from None
    probe = path / f".fenics-elasto-probe{PART}{os.getpid()}"  # a killed run's is swept like a temporary
    try:
        _write_synced(probe, b"\0" * 4096)
    except OSError as err:
        raise UserError(f"{path}: cannot write there ({_cause(err)})") from None
    finally:
        _remove(probe, quiet=True)
    return missing[::-1]


def _refuse_kernel_place(path: Path) -> None:
    real = Path(os.path.realpath(path))
    for root in PSEUDO_ROOTS:
        if real.is_relative_to(root) and not any(real.is_relative_to(s) for s in SCRATCH):
            raise UserError(f"{path}: under {root}, a kernel file system, not a place for results")


# --------------------------------------------------------------------------- the lock


def _take_lock(folder: Path) -> str | None:
    """Create the lock file (O_CREAT | O_EXCL); a note when a stale lock was taken over."""
    lock, note = folder / LOCK, None
    for attempt in range(2):
        try:
            fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder = _read_lock(lock)
            require(attempt == 0 and not _holder_alive(holder, lock), _busy(folder, holder))
            _remove_stale_lock(lock, holder)
            note = f"{folder}: taking over the lock of a run that is gone ({_describe_holder(holder)})"
            continue
        except OSError as err:
            raise UserError(f"{lock}: cannot create the lock file ({_cause(err)})") from None
        with os.fdopen(fd, "w") as f:
            now = time.time()
            json.dump({"pid": os.getpid(), "host": socket.gethostname(), "started": now,
                       "start_time": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(now)),
                       "command": " ".join(sys.argv)}, f)
        return note
    raise AssertionError("unreachable: the second attempt returns or raises")


def _read_lock(lock: Path) -> dict | None:
    try:
        holder = json.loads(lock.read_text())
    except (OSError, ValueError):
        return None
    return holder if isinstance(holder, dict) and {"pid", "host", "started"} <= holder.keys() else None


def _holder_alive(holder: dict | None, lock: Path) -> bool:
    """Whether the run that wrote the lock may still be running (when unsure: yes)."""
    if holder is None:  # being written this instant, or left empty by a run killed right then
        try:
            return time.time() - lock.stat().st_mtime < EMPTY_LOCK_STALE_S
        except OSError:
            return False
    pid = holder["pid"]
    if holder["host"] != socket.gethostname():
        return True  # its pid means nothing here
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # alive, another user's
    started = _process_start(pid)
    # A process that started after the lock was written only reused the pid (after a
    # reboot, or a container's pid 1 again).
    return started is None or started <= holder["started"] + 2.0


def _process_start(pid: int) -> float | None:
    """When process ``pid`` started (seconds since the epoch, ~1 s), from /proc; None if unknown."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        with open("/proc/stat") as f:
            boot = next(float(line.split()[1]) for line in f if line.startswith("btime"))
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: start, in ticks since boot
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def _remove_stale_lock(lock: Path, holder: dict | None) -> None:
    """Move the stale lock aside (atomic: of two runs taking over, one moves it), and put
    it back if what was moved is not the stale lock but a faster run's fresh one."""
    aside = lock.with_name(f"{LOCK}.stale-{os.getpid()}")
    try:
        os.replace(lock, aside)
    except FileNotFoundError:
        return  # another run took it over first; our O_EXCL retry tells who won
    if _read_lock(aside) != holder:
        try:
            os.link(aside, lock)
        except OSError:
            pass
    _remove(aside, quiet=True)


def _busy(folder: Path, holder: dict | None) -> str:
    return (f"{folder}: in use by another run ({_describe_holder(holder)}); choose another output "
            f"folder, or remove {folder / LOCK} if that run is gone")


def _describe_holder(holder: dict | None) -> str:
    if holder is None:
        return "its lock file is unreadable"
    return f"pid {holder['pid']} on {holder['host']}, started {holder.get('start_time', holder['started'])}"


# --------------------------------------------------------------------------- writing


class OutputFolder:
    """A checked and locked result folder (``prepare_folder``); filled by ``writing()``."""

    def __init__(self, path: Path, comm, token: int, created: list[Path]):
        self.path, self.comm = path, comm
        self.written: list[str] = []  # names committed by writing(), as listed in result.json
        self._token = token  # rank 0's pid: the same temporary names on every rank
        self._created = created  # directories prepare_folder made: removed again if nothing is written
        self._parts: dict[str, Path] = {}  # name -> temporary path, renamed in at the end of writing()
        self._small: dict[str, bytes] = {}  # what write_bytes got, kept for the fallback
        self._old: set[str] = set()  # files listed by the earlier run's result.json
        self._locked = comm.rank == 0
        self._released = False

    def __enter__(self) -> OutputFolder:
        return self

    def __exit__(self, *exc) -> None:
        self.release()  # also when the work failed: the lock goes, an empty new folder too

    def path_for(self, name: str) -> Path:
        """The temporary path to write ``name`` (a file or a directory) to, inside ``writing()``.
        Same on every rank (for collective writers); renamed to ``name`` at the end."""
        if name == MARKER or not _plain_name(name):
            raise ValueError(f"{name!r}: not a file name for path_for (result.json is written by writing())")
        stem, suffix = os.path.splitext(name)  # the suffix stays last: writers choose formats by it
        self._parts[name] = self.path / f".{stem}{PART}{self._token}{suffix}"
        return self._parts[name]

    def write_bytes(self, name: str, data: bytes) -> None:
        """A small file, from rank 0 (a no-op on the others); kept for the fallback too."""
        if self.comm.rank == 0:
            self._small[name] = data
            _write_synced(self.path_for(name), data)

    def write_text(self, name: str, text: str) -> None:
        self.write_bytes(name, text.encode())

    def write_json(self, name: str, data) -> None:
        self.write_text(name, to_json(data))

    @contextmanager
    def writing(self, result: dict):
        """Write the folder: the files of the block, then ``result.json`` (``result`` plus
        ``"files"``, the sorted names), then release the lock.

        Signals wait for the end (then ``Interrupted``). Every rank must enter the block.
        ``OSError`` inside it or while renaming: ``UserError`` naming the file, after the
        small files and ``result.json`` went to a fallback folder (named in the message).
        """
        if self._released:
            raise RuntimeError(f"{self.path}: released already; prepare_folder it again")
        with deferred_signals(self.comm):
            failure = self.comm.bcast(self._attempt(self._begin), root=0)
            if failure is None:
                try:
                    yield self
                except OSError as err:
                    failure = self._describe(err)
                except BaseException:
                    self._discard()
                    self.release()
                    raise
            self._finish(result, failure)

    def release(self) -> None:
        """Give up the lock (idempotent; also run at exit). A folder this run created and
        wrote nothing into is removed again: no claim to a result."""
        self._released = True
        if not self._locked:
            return
        self._locked = False
        _remove(self.path / LOCK, quiet=True)
        if not self.written:
            for directory in reversed(self._created):
                try:
                    directory.rmdir()
                except OSError:
                    break

    def _begin(self) -> None:
        """Make the folder incomplete before new files go in: the earlier result.json goes first."""
        self._old = _listed_files(self.path / MARKER)
        (self.path / MARKER).unlink(missing_ok=True)
        _sync_directory(self.path)

    def _attempt(self, work) -> str | None:
        """``work()`` on rank 0: None, or the one-line description of its OSError."""
        if self.comm.rank == 0:
            try:
                work()
            except OSError as err:
                return self._describe(err)
        return None

    def _finish(self, result: dict, failure: str | None) -> None:
        """Collective: agree on failures (the gather also waits for the collective writers),
        then rank 0 renames everything in and writes result.json -- or rescues what it can."""
        problem = next((p for p in self.comm.allgather(failure) if p), None)
        if self.comm.rank == 0:
            problem = problem or self._attempt(lambda: self._commit(result))
            if problem is not None:
                self._discard()
                small = {**self._small, MARKER: to_json({**result, "files": sorted(self._small)}).encode()}
                problem += _rescue(lambda place: _write_files(place, small), sorted(small))
        problem = self.comm.bcast(problem, root=0)
        self.release()
        require(problem is None, problem)

    def _commit(self, result: dict) -> None:
        for name, part in self._parts.items():
            if os.path.lexists(part):  # asked for but never written: not a file of this run
                _sync_tree(part)
                _move_into_place(part, self.path / name)
                self.written.append(name)
        for name in self._old - set(self.written):  # the earlier run's, not rewritten: out
            _remove(self.path / name)
        marker = self.path / f".result{PART}{self._token}.json"
        _write_synced(marker, to_json({**result, "files": sorted(self.written)}).encode())
        os.replace(marker, self.path / MARKER)
        _sync_directory(self.path)

    def _discard(self) -> None:
        if self.comm.rank == 0:
            for part in self._parts.values():
                _remove(part, quiet=True)
            _remove(self.path / f".result{PART}{self._token}.json", quiet=True)

    def _describe(self, err: OSError) -> str:
        culprit = str(err.filename or self.path)
        for name, part in self._parts.items():  # a temporary name means its final name to the user
            if culprit.startswith(str(part)):
                culprit = str(self.path / name)
        return f"{culprit}: cannot write ({_cause(err)})"


class OutputFile:
    """A checked single output file (``prepare_file``)."""

    def __init__(self, path: Path, comm, token: int):
        self.path, self.comm, self._token = path, comm, token

    def write(self, writer) -> Path:
        """``writer(temporary path)`` on rank 0, then renamed to ``self.path``; signals wait.
        Every rank calls it. ``OSError``: ``UserError`` naming the file, after ``writer``
        ran once more into a fallback folder (named in the message)."""
        with deferred_signals(self.comm):
            problem = None
            if self.comm.rank == 0:
                part = self.path.with_name(f".{self.path.stem}{PART}{self._token}{self.path.suffix}")
                try:
                    writer(part)
                    _sync_tree(part)
                    os.replace(part, self.path)
                    _sync_directory(self.path.parent)
                except OSError as err:
                    name = self.path.name
                    problem = f"{self.path}: cannot write ({_cause(err)})" + _rescue(lambda place: writer(place / name), [name])
                finally:
                    _remove(part, quiet=True)
            problem = self.comm.bcast(problem, root=0)
            require(problem is None, problem)
        return self.path


# --------------------------------------------------------------------------- helpers


def to_json(data) -> str:
    """JSON text (indented, numpy scalars and arrays as plain numbers and lists)."""
    return json.dumps(data, indent=2, default=_json_default) + "\n"


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON: {type(value).__name__}")


def _rescue(save, names: list[str]) -> str:
    """``save(place)`` into a fallback folder ($TMPDIR, else home); the message's tail."""
    cause = None
    for base in (tempfile.gettempdir(), Path.home()):
        place = Path(base) / f"fenics-elasto-{os.getpid()}"
        try:
            place.mkdir(exist_ok=True)
            save(place)
            return f"; saved {', '.join(names)} in {place} instead"
        except OSError as err:
            cause = f"{place}: {_cause(err)}"
    return f"; could not save the results elsewhere either ({cause})"


def _write_synced(path: Path, data: bytes) -> None:
    try:
        with open(path, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())  # a full disk may only show here (delayed allocation, NFS)
    except OSError as err:
        raise OSError(err.errno, err.strerror, str(path)) from None  # write() errors name no file


def _write_files(folder: Path, files: dict[str, bytes]) -> None:
    for name, data in files.items():
        _write_synced(folder / name, data)


def _sync_tree(path: Path) -> None:
    """fsync a file, or every file under a directory, before it is renamed into place."""
    for file in [path] if not path.is_dir() else [p for p in path.rglob("*") if p.is_file()]:
        _fsync(file)


def _sync_directory(path: Path) -> None:
    """Make renames in ``path`` durable (file systems that cannot fsync a directory are skipped)."""
    try:
        _fsync(path)
    except OSError as err:
        if err.errno not in (errno.EINVAL, errno.EOPNOTSUPP):
            raise


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as err:
        raise OSError(err.errno, err.strerror, str(path)) from None
    finally:
        os.close(fd)


def _move_into_place(part: Path, final: Path) -> None:
    """Rename ``part`` to ``final``. A directory cannot be renamed over (nor onto) an
    existing one: the old one is renamed aside first and deleted after."""
    aside = None
    if os.path.lexists(final) and (part.is_dir() or final.is_dir()):
        aside = final.with_name(f".{final.name}{PART}old-{os.getpid()}")
        os.replace(final, aside)
    os.replace(part, final)
    if aside is not None:
        _remove(aside)


def _remove(path: Path, quiet: bool = False) -> None:
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        if not quiet:
            raise


def _listed_files(marker: Path) -> set[str]:
    """The files an earlier result.json lists (plain names only: it is read from disk)."""
    try:
        files = json.loads(marker.read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return set()
    return {f for f in files if isinstance(f, str) and _plain_name(f) and f != LOCK}


def _plain_name(name: str) -> bool:
    return name not in ("", ".", "..") and os.sep not in name and "\0" not in name


def _cause(err: OSError) -> str:
    return os.strerror(err.errno) if err.errno else str(err)


def _stderr(text: str) -> None:
    print(f"note: {text}", file=sys.stderr, flush=True)
