"""How a job ends: every job's `main` raises `UserError` for anything the user can fix; `run` turns it into
one line on stderr and exit status 2 (the convention of argparse itself), Ctrl-C into 130, SIGTERM into 143.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from aniformer.cli.locks import release_locks
from aniformer.errors import UserError

_terminated = False


def _on_sigterm(signum, frame):
    global _terminated
    _terminated = True
    raise SystemExit(143)


def exit_on_sigterm() -> None:
    """(Re)install `run`'s SIGTERM handler: exit 143 with one line. A job calls it again after
    `ray.init`, which installs a handler of its own (it prints a stack and kills the process)."""
    import signal

    signal.signal(signal.SIGTERM, _on_sigterm)


def terminated() -> bool:
    """Whether this process was sent SIGTERM (`ray job stop`, kill) while `run` ran its job."""
    return _terminated


def run(main: Callable[[list[str]], Any], argv: list[str] | None = None) -> None:
    """Call `main(argv)`; a `UserError` becomes one line on stderr and exit status 2, Ctrl-C 130,
    SIGTERM 143 (whatever the stack made of the `SystemExit` it raises), a full disk one line and 1.
    Output locks the job took (`aniformer.cli.locks.lock_output`) are released as it ends."""
    import errno
    import signal

    global _terminated
    _terminated = False
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread
        previous = None
    try:
        main(sys.argv[1:] if argv is None else argv)
    except BaseException as e:
        if _terminated:
            print("terminated (SIGTERM)", file=sys.stderr)
            sys.exit(143)
        if isinstance(e, UserError):
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        if isinstance(e, KeyboardInterrupt):
            print("interrupted", file=sys.stderr)
            sys.exit(130)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            print(f"error: no space left on the device ({e.filename or e}); nothing partial was kept",
                  file=sys.stderr)
            sys.exit(1)
        raise
    finally:
        release_locks()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if _terminated:  # the stack swallowed the SystemExit and returned
        print("terminated (SIGTERM)", file=sys.stderr)
        sys.exit(143)
