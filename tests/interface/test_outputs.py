"""Result folders: checked before the work, locked, atomic, and kept whole through signals.

The signal and kill tests drive tests/outputs_child.py (a stand-in command using
fenics_elasto.outputs the way the CLI is meant to) and time their signals on its
output lines, never on fixed sleeps. "Complete" below means: result.json is valid,
lists every other file, each of them is there and from the same run, nothing else is.
"""

import argparse
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from fenics_elasto.util.errors import UserError
from fenics_elasto.util.interrupts import Interrupted, deferred_signals, handle_signals
from conftest import TESTS
from fenics_elasto.files.outputs import LOCK, prepare_file, prepare_folder

CHILD = TESTS / "outputs_child.py"
BIN = Path(sys.executable).parent
sys.path.insert(0, str(CHILD.parent))
import outputs_child  # noqa: E402
from outputs_child import CHUNKS, big_chunk  # noqa: E402

FILES = ["big.bin", "field.bp", "forces.csv"]


# --------------------------------------------------------------------------- helpers


class Child:
    """outputs_child.py as a subprocess; its stdout and stderr collected line by line."""

    def __init__(self, out, hold, *extra, mpi=0, sigint_ignored=True):
        cmd = [sys.executable, str(CHILD), str(out), hold, *map(str, extra)]
        if mpi:
            cmd = [str(BIN / "mpiexec"), "-n", str(mpi), *cmd]
        # A job started in the background of a non-interactive shell inherits SIGINT
        # ignored: the module must install its handler anyway.
        ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if sigint_ignored else None
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, preexec_fn=ignore)
        self.lines = {"out": queue.Queue(), "err": queue.Queue()}
        self.seen = {"out": [], "err": []}
        for key, stream in (("out", self.proc.stdout), ("err", self.proc.stderr)):
            threading.Thread(target=lambda s=stream, q=self.lines[key]: [q.put(line) for line in s],
                             daemon=True).start()

    def wait_for(self, text, stream="out", timeout=60.0):
        """Block until a line containing ``text`` appears (seen lines count too)."""
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.seen[stream]):
            try:
                self.seen[stream].append(self.lines[stream].get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                self.proc.kill()
                raise AssertionError(f"no {text!r} within {timeout} s:\n{self.report()}") from None

    def send(self, sig):
        self.proc.send_signal(sig)

    def go(self):
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()

    def finish(self, timeout=60.0):
        code = self.proc.wait(timeout=timeout)
        time.sleep(0.05)  # let the reader threads drain
        for key in self.lines:
            while not self.lines[key].empty():
                self.seen[key].append(self.lines[key].get())
        return code

    def report(self):
        return "stdout:\n" + "".join(self.seen["out"]) + "stderr:\n" + "".join(self.seen["err"])


def run_child(out, hold="none", *extra, **options):
    child = Child(out, hold, *extra, **options)
    code = child.finish()
    return code, child


def complete_run(out: Path, tag: str, say=None) -> None:
    """In this process, what a child run with HOLD none leaves (saves starting one)."""
    folder = prepare_folder(out, say=say)
    outputs_child.write(folder, [1, 3, 6], False, argparse.Namespace(hold="none", tag=tag))


def assert_complete(out: Path, tag: str) -> dict:
    """The folder is one whole run, ``tag``'s; its result.json."""
    result = json.loads((out / "result.json").read_text())
    assert result["files"] == FILES
    assert sorted(os.listdir(out)) == sorted(FILES + ["result.json"])  # no lock, no temporaries
    rows = (out / "forces.csv").read_text().splitlines()
    assert len(rows) == result["steps"] and all(row.startswith(f"{tag},") for row in rows)
    assert sorted(os.listdir(out / "field.bp")) == [f"rank{r}.txt" for r in range(result["ranks"])]
    assert all((out / "field.bp" / f).read_text() == f"{tag}\n" for f in os.listdir(out / "field.bp"))
    assert (out / "big.bin").read_bytes() == b"".join(big_chunk(tag, i) for i in range(CHUNKS))
    assert result["tag"] == tag
    return result


def lock_file(folder: Path, **fields) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    record = {"pid": 1, "host": socket.gethostname(), "started": time.time(), **fields}
    (folder / LOCK).write_text(json.dumps(record))
    return folder / LOCK


def dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


@pytest.fixture
def tmpfs(tmp_path):
    """A fresh 256 KiB tmpfs; mount(tmpfs, options) remounts it. Skipped where mount is not permitted."""
    where = tmp_path / "mnt"
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(where)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs CAP_SYS_ADMIN): {done.stderr.strip()}")

    def remount(options):
        subprocess.run(["mount", "-o", f"remount,{options}", str(where)], check=True)

    yield where, remount
    subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.fixture
def fallback(tmp_path, monkeypatch):
    """The rescue folder lands under tmp_path (not the real $TMPDIR)."""
    import tempfile

    base = tmp_path / "fallback"
    base.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(base))
    return base / f"fenics-elasto-{os.getpid()}"


def expect_refusal(call, *words):
    start = time.perf_counter()
    with pytest.raises(UserError) as err:
        call()
    assert time.perf_counter() - start < 1.0
    message = str(err.value)
    assert "\n" not in message
    for word in words:
        assert word in message, message
    return message


# --------------------------------------------------------------------------- checks before the work


def test_bad_output_folders_are_refused_at_once(tmp_path):
    a_file = tmp_path / "result"
    a_file.write_text("not a folder")
    expect_refusal(lambda: prepare_folder(a_file), str(a_file), "not a directory")
    expect_refusal(lambda: prepare_folder(a_file / "sub" / "out"), str(a_file), "is not a directory")
    expect_refusal(lambda: prepare_folder("/proc/x"), "/proc/x", "kernel file system")
    expect_refusal(lambda: prepare_folder("/sys/fenics"), "/sys/fenics", "kernel file system")
    expect_refusal(lambda: prepare_folder("/dev/null"), "/dev/null", "kernel file system")
    assert not a_file.is_dir() and not os.path.exists("/sys/fenics")


def test_a_new_folder_is_made_with_its_parents_and_removed_when_nothing_was_written(tmp_path):
    out = tmp_path / "a" / "b" / "out"
    folder = prepare_folder(out)
    assert out.is_dir() and os.listdir(out) == [LOCK]
    assert json.loads((out / LOCK).read_text())["pid"] == os.getpid()
    folder.release()
    assert not (tmp_path / "a").exists()  # no claim to a result: nothing this run made is left
    with pytest.raises(RuntimeError, match="released"):
        folder.writing({}).__enter__()  # unlocked: someone else may be writing there now


def test_read_only_places_are_refused(tmpfs):
    where, remount = tmpfs
    remount("ro")
    expect_refusal(lambda: prepare_folder(where), str(where), "Read-only file system")
    expect_refusal(lambda: prepare_folder(where / "x" / "out"), str(where / "x" / "out"), "Read-only file system")
    expect_refusal(lambda: prepare_file(where / "bases.npz", ".npz"), str(where), "Read-only file system")


def test_a_full_disk_is_refused_before_the_work(tmpfs):
    where, _ = tmpfs
    with pytest.raises(OSError):
        with open(where / "filler", "wb") as f:
            while True:
                f.write(b"\0" * 4096)
                f.flush()
    expect_refusal(lambda: prepare_folder(where / "out"), "No space left on device")


def test_single_output_files(tmp_path):
    assert prepare_file(tmp_path / "bases", ".npz").path == tmp_path / "bases.npz"  # suffix added, caller prints it
    assert prepare_file(tmp_path / "new" / "b.NPZ", ".npz").path == tmp_path / "new" / "b.NPZ"
    expect_refusal(lambda: prepare_file(tmp_path, ".npz"), str(tmp_path), "is a directory")
    expect_refusal(lambda: prepare_file(tmp_path / "picture.jpg", ".png"), "picture.jpg", ".png")
    expect_refusal(lambda: prepare_file("/proc/self/picture.png", ".png"), "kernel file system")
    target = prepare_file(tmp_path / "plot.png", ".png")
    target.write(lambda p: p.write_bytes(b"old"))
    assert target.write(lambda p: p.write_bytes(b"new")) == tmp_path / "plot.png"
    assert (tmp_path / "plot.png").read_bytes() == b"new"
    assert sorted(os.listdir(tmp_path)) == ["new", "plot.png"]  # no temporaries


# --------------------------------------------------------------------------- writing


def test_result_json_comes_last_and_a_folder_never_mixes_runs(tmp_path):
    out = tmp_path / "out"
    folder = prepare_folder(out)
    with folder.writing({"run": 1}):
        folder.write_text("a.txt", "1")
        folder.write_text("b.txt", "1")
        folder.path_for("c.bp").mkdir()
        (folder.path_for("c.bp") / "data").write_text("1")
    (out / "notes.txt").write_text("the user's own file")
    assert json.loads((out / "result.json").read_text()) == {"run": 1, "files": ["a.txt", "b.txt", "c.bp"]}

    folder = prepare_folder(out)
    with folder.writing({"run": 2}):
        assert not (out / "result.json").exists()  # incomplete from the first new byte on
        folder.write_text("a.txt", "2")
        folder.path_for("c.bp").mkdir()  # a directory replaces the old one whole
        (folder.path_for("c.bp") / "other").write_text("2")
        assert (out / "a.txt").read_text() == "1"  # renamed in only at the end
    assert json.loads((out / "result.json").read_text()) == {"run": 2, "files": ["a.txt", "c.bp"]}
    assert sorted(os.listdir(out)) == ["a.txt", "c.bp", "notes.txt", "result.json"]  # run 1's b.txt is gone
    assert (out / "a.txt").read_text() == "2" and os.listdir(out / "c.bp") == ["other"]


def test_a_full_disk_while_writing_names_the_file_and_saves_the_small_results(tmp_path, fallback):
    out = tmp_path / "out"
    folder = prepare_folder(out)
    with pytest.raises(UserError) as err:
        with folder.writing({"E": 51.2}):
            folder.write_text("history.csv", "1,2\n")
            os.symlink("/dev/full", folder.path_for("forces.csv"))  # its writes fail with ENOSPC
            folder.write_text("forces.csv", "0,1,2,3\n")
    message = str(err.value)
    assert message.startswith(f"{out / 'forces.csv'}: cannot write (No space left on device)"), message
    assert str(fallback) in message and "\n" not in message
    assert json.loads((fallback / "result.json").read_text()) == {"E": 51.2, "files": ["forces.csv", "history.csv"]}
    assert (fallback / "forces.csv").read_text() == "0,1,2,3\n"
    assert not out.exists()  # this run made it, and nothing of this run is left in it
    assert Path("/dev/full").is_char_device()  # the clean-up removed the link, not the device


def test_a_disk_filling_up_or_turning_read_only_while_writing(tmpfs, fallback):
    where, remount = tmpfs
    folder = prepare_folder(where / "out")
    with pytest.raises(UserError, match=r"big.bin: cannot write \(No space left on device\).*saved"):
        with folder.writing({"E": 1.0}):
            folder.write_bytes("big.bin", b"\0" * (1 << 20))
    assert os.listdir(where) == []  # the folder this run made is gone again: nothing to claim
    folder = prepare_folder(where / "out")
    with pytest.raises(UserError, match=r"Read-only file system.*saved forces.csv, result.json in"):
        with folder.writing({"E": 2.0}):
            folder.write_text("forces.csv", "1\n")
            remount("ro")
    assert json.loads((fallback / "result.json").read_text())["E"] == 2.0


def test_a_single_file_that_cannot_be_written_goes_to_the_fallback(tmp_path, fallback):
    target = prepare_file(tmp_path / "bases.npz", ".npz")

    def save(path):
        if path.parent == tmp_path:
            raise OSError(5, os.strerror(5))  # EIO
        path.write_bytes(b"bases")

    with pytest.raises(UserError, match=r"bases.npz: cannot write \(Input/output error\); saved bases.npz in"):
        target.write(save)
    assert (fallback / "bases.npz").read_bytes() == b"bases" and os.listdir(tmp_path) == ["fallback"]


# --------------------------------------------------------------------------- locks


def test_stale_and_live_locks(tmp_path):
    sleeper = subprocess.Popen(["sleep", "30"])
    try:
        lock_file(tmp_path / "live", pid=sleeper.pid)
        expect_refusal(lambda: prepare_folder(tmp_path / "live"), "in use by another run", f"pid {sleeper.pid}")
        lock_file(tmp_path / "elsewhere", host="another-host", pid=os.getpid())
        expect_refusal(lambda: prepare_folder(tmp_path / "elsewhere"), "another-host")
        # The pid is alive but started after the lock was written: reused (a reboot, a container).
        lock_file(tmp_path / "reused", pid=sleeper.pid, started=time.time() - 3600)
        notes = []
        prepare_folder(tmp_path / "reused", say=notes.append).release()
        assert len(notes) == 1 and "taking over" in notes[0]
    finally:
        sleeper.kill()
        sleeper.wait()
    notes = []
    lock_file(tmp_path / "dead", pid=dead_pid())
    folder = prepare_folder(tmp_path / "dead", say=notes.append)
    assert "taking over the lock of a run that is gone" in notes[0]
    assert json.loads((tmp_path / "dead" / LOCK).read_text())["pid"] == os.getpid()
    folder.release()
    empty = tmp_path / "empty" / LOCK  # being written by another run this instant ...
    empty.parent.mkdir()
    empty.touch()
    expect_refusal(lambda: prepare_folder(empty.parent), "unreadable")
    os.utime(empty, (time.time() - 60, time.time() - 60))  # ... or left so by a killed one
    prepare_folder(empty.parent, say=notes.append).release()


def test_a_second_run_into_a_busy_folder_refuses_and_a_killed_runs_lock_is_taken_over(tmp_path):
    out = tmp_path / "out"
    first = Child(out, "compute")
    first.wait_for("step 1")
    code, second = run_child(out, "none", "--tag", "B")
    assert code == 2, second.report()
    assert second.seen["err"] == [f"error: {out}: in use by another run (pid {first.proc.pid} on "
                                  f"{socket.gethostname()}, started " + second.seen["err"][0].split("started ")[1]]
    first.proc.kill()  # SIGKILL: no clean-up, the lock stays behind
    first.finish()
    notes = []
    complete_run(out, "C", say=notes.append)
    assert len(notes) == 1 and f"taking over the lock of a run that is gone (pid {first.proc.pid}" in notes[0]
    assert_complete(out, "C")


def test_a_writer_killed_half_way_leaves_the_old_file_whole(tmp_path):
    out = tmp_path / "out"
    complete_run(out, "A")
    child = Child(out, "big", "--tag", "B")
    child.wait_for("holding")  # half of B's big.bin is written, under its temporary name
    child.proc.kill()
    child.finish()
    assert not (out / "result.json").exists()  # the folder says: incomplete
    assert (out / "big.bin").read_bytes() == b"".join(big_chunk("A", i) for i in range(CHUNKS))
    assert any(".part-" in name for name in os.listdir(out))  # B's half-written file, hidden
    complete_run(out, "C", say=print)
    assert_complete(out, "C")  # B's leftovers cleared, its lock taken over


# --------------------------------------------------------------------------- signals


def test_signals_in_process_become_interrupts_and_wait_for_the_writing():
    with handle_signals():
        with pytest.raises(Interrupted, match="SIGTERM"):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
    with handle_signals():
        written = []
        with pytest.raises(Interrupted, match=r"SIGHUP SIGINT \(after finishing the files"):
            with deferred_signals():
                os.kill(os.getpid(), signal.SIGHUP)
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
                written.append("file")
        assert written == ["file"]
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # handlers restored


CASES = [  # signal, where the child holds, how many signals
    (signal.SIGTERM, "first", 1), (signal.SIGINT, "first", 1),
    (signal.SIGTERM, "compute", 1), (signal.SIGINT, "compute", 1), (signal.SIGHUP, "compute", 1),
    (signal.SIGTERM, "writing", 1), (signal.SIGHUP, "writing", 1), (signal.SIGINT, "writing", 2),
    (signal.SIGTERM, "writing", 2),
]
FAST = {(signal.SIGINT, "first", 1), (signal.SIGTERM, "compute", 1), (signal.SIGTERM, "writing", 2)}


@pytest.mark.parametrize("sig, hold, times", [
    pytest.param(*case, id=f"{case[0].name}-{case[1]}-x{case[2]}",
                 marks=() if case in FAST else pytest.mark.slow) for case in CASES])
def test_every_signal_leaves_a_complete_folder_or_none(tmp_path, sig, hold, times):
    out = tmp_path / "out"
    child = Child(out, hold, "--steps", 3)
    child.wait_for({"first": "waiting", "compute": "step 2", "writing": "holding"}[hold])
    for i in range(times):
        child.send(sig)
        if hold == "writing":  # the child has noted each signal before it may go on
            child.wait_for("finishing the files" if i == 0 else "abandons the run", stream="err")
    if hold == "writing":
        child.go()
    code = child.finish()
    assert code == 130, child.report()
    assert "Traceback" not in child.report()
    if hold == "first":
        assert child.seen["err"][-1].strip() == "interrupted: before the first result: nothing written", child.report()
        assert not out.exists() and "writing" not in child.seen["out"]
        return
    result = assert_complete(out, "A")
    assert result["interrupted"] is (hold == "compute")  # writing: the computation had finished
    assert result["steps"] >= 2 and (hold == "compute" or result["steps"] == 3)


def test_an_interrupt_before_the_first_result_keeps_the_earlier_runs_folder(tmp_path):
    out = tmp_path / "out"
    complete_run(out, "A")
    child = Child(out, "first", "--tag", "B")
    child.wait_for("waiting")
    child.send(signal.SIGTERM)
    assert child.finish() == 130, child.report()
    assert_complete(out, "A")


@pytest.mark.slow
def test_a_third_signal_abandons_the_run(tmp_path):
    out = tmp_path / "out"
    child = Child(out, "writing")
    child.wait_for("holding")
    for note in ("finishing the files", "abandons the run", "abandoning"):
        child.send(signal.SIGTERM)
        child.wait_for(note, stream="err")
    assert child.finish() == 130
    assert not (out / "result.json").exists()  # incomplete, and it says so


@pytest.mark.slow
def test_a_closed_terminal_still_gets_its_result(tmp_path):
    """A real hang-up: the child's controlling terminal goes away under it (SIGHUP, then
    EIO on every write to the terminal)."""
    import fcntl
    import termios

    out = tmp_path / "out"
    master, slave = os.openpty()
    proc = subprocess.Popen([sys.executable, str(CHILD), str(out), "compute"], stdin=slave, stdout=slave,
                            stderr=slave, start_new_session=True,
                            preexec_fn=lambda: fcntl.ioctl(0, termios.TIOCSCTTY, 0))
    os.close(slave)
    seen = b""
    deadline = time.monotonic() + 60
    while b"step 2" not in seen and time.monotonic() < deadline:
        seen += os.read(master, 1024)
    assert b"step 2" in seen, seen
    os.close(master)  # hang up
    assert proc.wait(timeout=60) == 130
    assert assert_complete(out, "A")["interrupted"] is True


@pytest.mark.slow
@pytest.mark.parametrize("sig, hold", [(signal.SIGTERM, "compute"), (signal.SIGINT, "writing"),
                                       (signal.SIGTERM, "first")], ids=["TERM-compute", "INT-writing", "TERM-first"])
def test_mpi_ranks_stop_together_with_one_result(tmp_path, sig, hold):
    """mpiexec (hydra) forwards SIGINT and SIGTERM to every rank; they stop at the same
    step (check_interrupt is collective) and leave one complete folder, or none."""
    out = tmp_path / "out"
    child = Child(out, hold, "--steps", 3, mpi=2)
    child.wait_for({"first": "waiting", "compute": "step 2", "writing": "holding"}[hold])
    child.send(sig)
    if hold == "writing":
        child.wait_for("finishing the files", stream="err")
        child.go()
    assert child.finish() == 130, child.report()
    if hold == "first":
        assert not out.exists()
        return
    result = assert_complete(out, "A")
    assert result["ranks"] == 2 and result["interrupted"] is (hold == "compute")
