"""Errors meant for a person: one line, what is wrong and what to do."""


class UserError(Exception):
    """Bad input or an unusable environment; printed as one line, exit code `exit_code`."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def check_output_path(path, what: str = "output", *, folder: bool = False):
    """Refuse, before any work, an output path that cannot be written: a file where a folder
    is needed (or the reverse), or a read-only folder. Missing folders are fine (created).
    Returns the path as a `pathlib.Path`."""
    import os
    from pathlib import Path

    p = Path(path)
    if folder and p.exists() and not p.is_dir():
        raise UserError(f"{what} {p} exists and is a file; give a folder")
    if not folder and p.is_dir():
        raise UserError(f"{what} {p} is a folder; give a file name")
    anc = p if folder else p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise UserError(f"cannot write {what} {p}: {anc} is a file, not a folder")
    if not os.access(anc, os.W_OK):
        raise UserError(f"cannot write {what} {p}: {anc} is not writable")
    return p
