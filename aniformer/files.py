"""File-system guarantees of the jobs: one job per output directory, outputs that never hold an input,
and staging directories that a crash does not leave behind. No Ray, no MLflow.

- ``lock_output(out)``: an exclusive ``fcntl.flock`` on ``OUT/.lock``, held until the job ends (``cli.run``
  releases it; the kernel does if the process dies). A second job on the same ``--out`` is refused in
  one line naming the holder (pid, host, command, start time). The lock file is removed on release.
- ``protect_inputs(out, inputs)``: `UserError` when ``--out`` is, contains or lies inside an input
  (``--overwrite`` replaces ``--out`` as a whole: it must never delete what the job reads).
- ``claim_output(out, overwrite, inputs)``: both, plus ``check_output_dir``: what a job calls once;
  ``@releases_locks`` on the job's ``main`` releases the lock when ``main`` ends however it is called.
- ``staging_dir``/``clean_stale_staging``/``swap_dirs``: the pieces of ``staged_output_dir``.
- ``exclusive(path)``: a short critical section between processes (the first creation of a store).
- ``atomic_path(path)``: write under a temporary name, renamed into place only when the block succeeds.
- ``staged_output_dir(out, overwrite)``: a whole output directory that appears complete or not at all.
- ``natural_key(name)``: the one order of frame and clip files (``frame_2`` before ``frame_10``, case-blind).
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import errno
import fcntl
import functools
import glob
import json
import os
import re
import shlex
import shutil
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from aniformer.errors import UserError

LOCK_NAME = ".lock"
_HELD: dict[Path, OutputLock] = {}
_AT_EXIT = False
_ATOMIC_TMP = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")  # atomic_path's temporary files


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


def holder() -> dict:
    """Who holds a lock: this process."""
    command = " ".join(shlex.join([Path(sys.argv[0]).name if sys.argv else "python", *sys.argv[1:]]).split())
    return {"pid": os.getpid(), "host": socket.gethostname(), "command": command[:300],
            "since": time.strftime("%Y-%m-%d %H:%M:%S %z")}


def _describe(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
        return (f"pid {info.get('pid')} on {info.get('host')} since {info.get('since')}: "
                f"{info.get('command', '?')}")
    except (OSError, ValueError, AttributeError):
        return "a job that has not written its name yet"


def _acquire(path: Path, flag: str, directory: Path) -> int:
    """An fd holding an exclusive flock on `path` (created if need be); `UserError` if another open
    file holds it. Lock files are removed on release, so after locking check that `path` is still
    the file we locked (a releasing holder may have just unlinked it), else try again."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as e:
            raise UserError(f"{flag} {directory}: cannot create {path.name} ({e.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = _describe(fd)
            os.close(fd)
            raise UserError(f"{flag} {directory} is in use by another job ({who}); "
                            f"wait for it to end or choose another {flag}") from None
        except OSError as e:
            os.close(fd)
            raise UserError(f"{flag} {directory}: cannot lock {path} ({e.strerror})") from None
        if _same_file(fd, path):
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, (json.dumps(holder()) + "\n").encode(), 0)
    return fd


def lock_output(out: str | os.PathLike, flag: str = "--out") -> OutputLock:
    """Lock output directory `out` (created if missing) for this process; the same lock again if this
    process holds it already. Stale temporary files of `atomic_path` in `out` are removed (none
    can be in use: the lock is ours)."""
    out = Path(os.path.abspath(os.path.expanduser(out)))
    if out in _HELD:
        return _HELD[out]
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
        atexit.register(release_locks)  # a caller that is not `cli.run` still removes its lock files
        _AT_EXIT = True
    _HELD[out] = lock
    for path in out.iterdir():
        if _ATOMIC_TMP.match(path.name) and path.is_file() and not path.is_symlink():
            path.unlink(missing_ok=True)
    return lock


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
    when it is called directly rather than through `cli.run` (tests do), and an `--out` it created
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


def protect_inputs(out: str | os.PathLike, inputs: Mapping[str, str | os.PathLike | None | list]) -> None:
    """`UserError` if `out` is, contains, or lies inside one of `inputs` ({flag: path or list of paths}; None and
    paths that do not exist, such as an MLflow run id, are skipped; a glob stands for the files it
    matches). Paths are compared after resolving symlinks, so a link cannot hide an input inside `out`."""
    target = Path(os.path.expanduser(out)).resolve()
    given = []
    flat = [(flag, v) for flag, value in inputs.items() for v in (value if isinstance(value, (list, tuple)) else [value])]
    for flag, value in flat:
        if value is None or str(value) == "":
            continue
        path = os.path.expanduser(value)
        if not os.path.exists(path) and glob.has_magic(str(path)):  # a glob (animate --driving 'dir/*.obj')
            given += [(flag, value, Path(match)) for match in sorted(glob.glob(str(path)))]
        elif os.path.exists(path):
            given.append((flag, value, Path(path)))
    for flag, value, path in given:
        real = path.resolve()
        if real == target:
            raise UserError(f"--out {out} is the input {flag} {value}; choose another --out")
        if real.is_relative_to(target):
            raise UserError(f"--out {out} contains the input {flag} {value} (--overwrite would delete it); "
                            "choose another --out")
        if real.is_dir() and target.is_relative_to(real):
            raise UserError(f"--out {out} is inside the input {flag} {value}; write outputs elsewhere")


def claim_output(out: str | os.PathLike, overwrite: bool,
                 inputs: Mapping[str, str | os.PathLike | None | list] = ()) -> OutputLock:
    """What a job does with its `--out` before any work: refuse one that is, holds or lies inside an
    input, lock it (one job per output), then refuse a non-empty one unless `overwrite`."""
    protect_inputs(out, dict(inputs))
    fresh = Path(os.path.abspath(os.path.expanduser(out))) not in _HELD
    lock = lock_output(out)
    try:
        check_output_dir(lock.directory, overwrite)
    except BaseException:
        if fresh:
            lock.release()
        raise
    return lock


# ------------------------------------------------------------------------- staging directories

def staging_dir(out: Path) -> Path:
    """A new private directory beside `out` (`.NAME.PID-XXXXXXXX.tmp`) to build `out` in."""
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}-", suffix=".tmp", dir=out.parent))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale_staging(out: Path) -> list[Path]:
    """Remove what killed jobs left beside `out`: staging directories (`.NAME[.PID-]XXXXXXXX.tmp`) and,
    once `out` holds results, the `.NAME.old-PID` it replaced. All of them when this process holds the
    lock on `out` (no other job can be writing them), else only those of processes that are gone."""
    if not out.parent.is_dir():
        return []
    locked = held_lock(out) is not None
    staged = re.compile(rf"^\.{re.escape(out.name)}\.(?:(\d+)-)?[a-z0-9_]{{8}}\.tmp$")
    old = re.compile(rf"^\.{re.escape(out.name)}\.old-(\d+)$")
    has_results = out.is_dir() and any(p.name != LOCK_NAME for p in out.iterdir())
    removed = []
    for path in out.parent.iterdir():
        match = staged.match(path.name) or (old.match(path.name) if has_results else None)
        if match is None or path.is_symlink() or not path.is_dir():
            continue
        pid = match.group(1)
        if locked or (pid is not None and not _alive(int(pid))):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def swap_dirs(a: Path, b: Path) -> bool:
    """Exchange two directories atomically (Linux renameat2 RENAME_EXCHANGE); False where the system or
    the file system cannot (the caller then renames in two steps)."""
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), str(b))


@contextlib.contextmanager
def exclusive(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive flock on `path` (waiting for other holders) for the block; the file is
    removed afterwards, so nothing is left behind (see `_acquire` for why that is safe)."""
    path = Path(path)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX)
        if _same_file(fd, path):
            break
        os.close(fd)
    try:
        yield
    finally:
        try:
            if _same_file(fd, path):
                os.unlink(path)
        finally:
            os.close(fd)


def natural_key(name: str) -> list:
    """Sort key that orders frame_2 before frame_10, ignoring case."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it into place only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the mode a plain open() would
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def check_output_dir(out: Path, overwrite: bool) -> None:
    """Refuse an `--out` that is a file, or a non-empty directory unless `overwrite` (a job's own lock
    file does not count)."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(p.name != LOCK_NAME for p in out.iterdir()) and not overwrite:
        raise UserError(f"--out {out} exists and is not empty; pass --overwrite to replace it")


@contextlib.contextmanager
def staged_output_dir(out: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary directory beside `out`; when the block succeeds it replaces `out`.

    A failure (or Ctrl-C) leaves `out` as it was and removes the partial directory; what a killed
    job left beside `out` is removed first (`clean_stale_staging`). When this process holds the
    lock on `out` (`lock_output`), the new directory is locked too before it takes `out`'s place,
    and the two are exchanged atomically, so no other job can slip in between.
    """
    check_output_dir(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_staging(out)
    tmp = staging_dir(out)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the results are an ordinary directory
    try:
        yield tmp
        check_output_dir(out, overwrite)  # still true after a long job?
        lock = held_lock(out)
        if lock is not None and lock.directory == Path(os.path.abspath(out)):
            lock.add(tmp)  # the new `out` is locked as it appears
        if out.exists() and swap_dirs(tmp, out):
            shutil.rmtree(tmp, ignore_errors=True)  # now the old `out`
            return
        old = None
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
