"""The errors a user can fix. Jobs report them as one line with exit status 2 (`aniformer.cli.run`)."""


class UserError(Exception):
    """Bad input the user can fix: reported as one line, exit status 2."""


class MeshError(UserError):
    """A mesh file or array that cannot be used, with the reason in one line."""
