"""The errors a user can fix, and the root cause of any error. Jobs report a `UserError` as one line with exit
status 2 (`aniformer.cli.exits.run`); the one line of an error from Ray, MLflow or the network names its `root_cause`."""


class UserError(Exception):
    """Bad input the user can fix: reported as one line, exit status 2."""


class MeshError(UserError):
    """A mesh file or array that cannot be used, with the reason in one line."""


def root_cause(error: BaseException) -> BaseException:
    """The exception at the bottom of `error`'s wrappers, the one that went wrong first. Each step takes the
    first of: Ray Train's worker group error's lowest failed rank (`worker_failures`), its controller's
    failure (`controller_failure`), a Ray task error's `cause`, the explicit `__cause__`, the implicit
    `__context__` (unless `raise ... from None` suppressed it), and urllib3's `reason` (requests' connection
    errors). Attributes that are not exceptions are skipped; a cycle ends the walk."""
    seen = set()
    while id(error) not in seen:
        seen.add(id(error))
        failures = getattr(error, "worker_failures", None)
        links = (failures[min(failures)] if isinstance(failures, dict) and failures else None,
                 getattr(error, "controller_failure", None), getattr(error, "cause", None), error.__cause__,
                 None if error.__suppress_context__ else error.__context__, getattr(error, "reason", None))
        inner = next((link for link in links if isinstance(link, BaseException)), None)
        if inner is None:
            break
        error = inner
    return error
