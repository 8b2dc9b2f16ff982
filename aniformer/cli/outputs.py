"""What a job does with its ``--out``: claim it, and replace it as a whole. No Ray, no MLflow.

- ``protect_inputs(out, inputs)``: `UserError` when ``--out`` is, contains or lies inside an input
  (``--overwrite`` replaces ``--out`` as a whole: it must never delete what the job reads).
- ``claim_output(out, overwrite, inputs)``: that, the lock (`aniformer.cli.locks`), and ``check_output_dir``:
  what a job calls once.
- ``staged_output_dir(out, overwrite)``: a whole output directory that appears complete or not at all;
  ``staging_dir``/``clean_stale_staging``/``swap_dirs`` are its pieces.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import glob
import os
import re
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path

from aniformer.cli.locks import LOCK_NAME, OutputLock, held_lock, lock_on, lock_output
from aniformer.errors import UserError
from aniformer.io.files import plain_mode


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
    fresh = lock_on(out) is None
    lock = lock_output(out)
    try:
        check_output_dir(lock.directory, overwrite)
    except BaseException:
        if fresh:
            lock.release()
        raise
    return lock


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
    os.chmod(tmp, plain_mode(0o777))  # mkdtemp makes it private; the results are an ordinary directory
    try:
        yield tmp
        check_output_dir(out, overwrite)  # still true after a long job?
        if (lock := lock_on(out)) is not None:
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
