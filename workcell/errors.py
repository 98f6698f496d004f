"""Errors meant for a person: one line, what is wrong and what to do."""


class UserError(Exception):
    """Bad input or an unusable environment; printed as one line, exit code `exit_code`."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code
