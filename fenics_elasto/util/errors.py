"""User-facing errors: one line that names the file, key or group at fault."""


class UserError(Exception):
    """Bad input. The CLI prints ``error: <message>`` and exits with status 2."""


def require(condition: object, message: str) -> None:
    """Raise ``UserError(message)`` unless ``condition`` holds (is truthy)."""
    if not condition:
        raise UserError(message)


def on_root(comm, work):
    """``work()`` on rank 0 only (gmsh, file checks); its value, or its UserError, on
    every rank -- a bad input must end all ranks alike, none left waiting."""
    value, error = None, None
    if comm.rank == 0:
        try:
            value = work()
        except UserError as err:
            error = str(err)
    value, error = comm.bcast((value, error), root=0)
    require(error is None, error)
    return value
