"""User-facing errors: one line that names the file, key or group at fault."""


class UserError(Exception):
    """Bad input. The CLI prints ``error: <message>`` and exits with status 2."""


def require(condition: bool, message: str) -> None:
    if not condition:
        raise UserError(message)
