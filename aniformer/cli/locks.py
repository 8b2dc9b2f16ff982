"""One job per output directory: an exclusive ``fcntl.flock`` on ``OUT/.lock``, held until the job ends
(`aniformer.cli.exits.run` releases it; the kernel does if the process dies). A second job on the same ``--out``
is refused in one line naming the holder (pid, host, command, start time). Lock files are removed on release.

- ``lock_output(out)``: take the lock (``claim_output`` in `aniformer.cli.outputs` is what a job calls);
  ``@releases_locks`` on the job's ``main`` releases it when ``main`` ends however it is called.
- ``exclusive(path)``: a short critical section between processes (the first creation of a store).
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import functools
import json
import os
import shlex
import socket
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from aniformer.errors import UserError
from aniformer.io.files import ATOMIC_TMP

LOCK_NAME = ".lock"
_HELD: dict[Path, OutputLock] = {}
_AT_EXIT = False


class OutputLock:
    """The held lock of one output directory (see `lock_output`)."""

    def __init__(self, directory: Path, created: bool):
        self.directory, self.created = directory, created
        self._files: list[tuple[Path, int]] = []  # (where the lock file is, or will be; its fd)

    def add(self, directory: Path, flag: str = "--out") -> None:
        """Also lock ``directory/.lock``: a staging directory about to take ``self.directory``'s place,
        where its lock file will then be (released files are told apart by inode)."""
        fd = _acquire(directory / LOCK_NAME, flag, directory)
        self._files.append((self.directory / LOCK_NAME, fd))

    def release(self) -> None:
        """Remove the lock files (only those that are still ours) and unlock; remove the directory
        too if this lock created it and nothing else was put there."""
        for path, fd in reversed(self._files):
            try:
                if _same_file(fd, path):
                    os.unlink(path)
            except OSError:
                pass
            os.close(fd)
        self._files.clear()
        _HELD.pop(self.directory, None)
        if self.created:
            try:
                self.directory.rmdir()  # only if empty
            except OSError:
                pass


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _flock(path: Path, wait: bool) -> int:
    """An fd holding an exclusive flock on `path` (created if need be); `BlockingIOError` if another open
    file holds it and not `wait`. Lock files are removed on release, so after locking check that `path`
    is still the file we locked (a releasing holder may have just unlinked it), else try again."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BaseException:
            os.close(fd)
            raise
        if _same_file(fd, path):
            return fd
        os.close(fd)


def holder() -> dict:
    """Who holds a lock: this process."""
    command = " ".join(shlex.join([Path(sys.argv[0]).name if sys.argv else "python", *sys.argv[1:]]).split())
    return {"pid": os.getpid(), "host": socket.gethostname(), "command": command[:300],
            "since": time.strftime("%Y-%m-%d %H:%M:%S %z")}


def _describe(path: Path) -> str:
    try:
        info = json.loads(path.read_text()[:4096] or "{}")
        return (f"pid {info.get('pid')} on {info.get('host')} since {info.get('since')}: "
                f"{info.get('command', '?')}")
    except (OSError, ValueError, AttributeError):
        return "a job that has not written its name yet"


def _acquire(path: Path, flag: str, directory: Path) -> int:
    """An fd holding the lock of `directory` at `path`, our name written in it; `UserError` if another job holds it."""
    try:
        fd = _flock(path, wait=False)
    except BlockingIOError:
        raise UserError(f"{flag} {directory} is in use by another job ({_describe(path)}); "
                        f"wait for it to end or choose another {flag}") from None
    except OSError as e:
        raise UserError(f"{flag} {directory}: cannot lock {path.name} ({e.strerror})") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, (json.dumps(holder()) + "\n").encode(), 0)
    return fd


def lock_output(out: str | os.PathLike, flag: str = "--out") -> OutputLock:
    """Lock output directory `out` (created if missing) for this process; the same lock again if this
    process holds it already. Stale temporary files of `atomic_path` in `out` are removed (none
    can be in use: the lock is ours)."""
    if (held := lock_on(out)) is not None:
        return held
    out = Path(os.path.abspath(os.path.expanduser(out)))
    if out.exists() and not out.is_dir():
        raise UserError(f"{flag} {out} exists and is not a directory")
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"{flag} {out}: cannot create it ({e.strerror})") from None
    lock = OutputLock(out, created)
    try:
        lock.add(out, flag)
    except BaseException:
        lock.release()
        raise
    global _AT_EXIT
    if not _AT_EXIT:
        atexit.register(release_locks)  # a caller that is not `exits.run` still removes its lock files
        _AT_EXIT = True
    _HELD[out] = lock
    for path in out.iterdir():
        if ATOMIC_TMP.match(path.name) and path.is_file() and not path.is_symlink():
            path.unlink(missing_ok=True)
    return lock


def lock_on(directory: str | os.PathLike) -> OutputLock | None:
    """The lock this process holds on exactly `directory`, if any."""
    return _HELD.get(Path(os.path.abspath(os.path.expanduser(directory))))


def held_lock(path: str | os.PathLike) -> OutputLock | None:
    """The lock this process holds on `path` or on a directory above it, if any."""
    path = Path(os.path.abspath(path))
    for directory, lock in _HELD.items():
        if path == directory or path.is_relative_to(directory):
            return lock
    return None


def release_locks() -> None:
    """Release every lock this process holds (the end of a job)."""
    for lock in list(_HELD.values()):
        lock.release()


def releases_locks(main: Callable) -> Callable:
    """Decorate a job's `main`: the output locks it takes are released when it returns or raises, also
    when it is called directly rather than through `aniformer.cli.exits.run` (tests do), and an `--out` it created
    only to hold its lock is removed again."""

    @functools.wraps(main)
    def job(*args, **kwargs):
        before = set(_HELD)
        try:
            return main(*args, **kwargs)
        finally:
            for directory in [d for d in _HELD if d not in before]:
                _HELD[directory].release()

    return job


@contextlib.contextmanager
def exclusive(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive flock on `path` (waiting for other holders) for the block; the file is
    removed afterwards, so nothing is left behind (see `_flock` for why that is safe)."""
    path = Path(path)
    fd = _flock(path, wait=True)
    try:
        yield
    finally:
        try:
            if _same_file(fd, path):
                os.unlink(path)
        finally:
            os.close(fd)
