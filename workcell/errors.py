"""Errors meant for a person: one line, what is wrong and what to do."""

import argparse
import os
import sys
import threading

# Set by the console command's SIGINT handler (`workcell.cli`) on every Ctrl-C. Python drops a
# KeyboardInterrupt raised inside a garbage-collector callback (JAX has one), so code that is
# about to start something long or physical checks this flag too.
INTERRUPTED = threading.Event()


def stop_if_interrupted() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C was noted in INTERRUPTED: for a long loop that runs
    before anything connects or moves (a plan of thousands of poses), so a Ctrl-C that Python
    dropped stops it at the next step instead of after the whole loop."""
    if INTERRUPTED.is_set():
        raise KeyboardInterrupt


def console_command() -> bool:
    """Whether this process is the `workcell` console command (not a test or a program calling
    `cli.main`): only then may a command end the process itself (`hard_exit`)."""
    return os.path.basename(sys.argv[0]) == "workcell"


def hard_exit(code: int) -> None:
    """Flush stdout and stderr and end the process now (`os._exit`): after an abort, a JAX call
    still running in another thread would hold up, or crash, the interpreter's shutdown."""
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


class UserError(Exception):
    """Bad input or an unusable environment; printed as one line, exit code `exit_code`."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


MCAP_MAGIC = b"\x89MCAP"


def refuse_overwrite(outputs, inputs=(), what: str = "output") -> None:
    """Refuse, before any work, to write an output over one of the command's `inputs` (the same
    file, by any path) or over an existing recording: either would lose data that may not be
    measurable again."""
    import os
    from pathlib import Path

    for o in outputs:
        o = Path(o)
        if o.exists() and not o.is_file() and not o.is_dir():
            # a device, pipe or socket: writing a file there would replace it
            raise UserError(
                f"{what} {o} exists and is not a regular file (a device or pipe); writing there "
                "would replace it; choose a file name"
            )
        if not o.is_file():
            continue
        for i in inputs:
            if i is not None and Path(i).exists() and os.path.samefile(o, i):
                raise UserError(
                    f"{what} {o} is the input {i}; writing there would destroy it; choose "
                    "another name"
                )
        try:
            with open(o, "rb") as f:
                head = f.read(len(MCAP_MAGIC))
        except OSError:
            continue
        if head == MCAP_MAGIC:
            raise UserError(
                f"{what} {o} is an existing recording (MCAP); writing there would destroy it; "
                "choose another name"
            )


REPLACE_REMEDY = "choose another name, or pass --force to replace it"


def replace_or_refuse(
    what: str,
    path,
    earlier: str | None,
    not_what: str,
    *,
    force: bool,
    say,
    remedy: str = REPLACE_REMEDY,
):
    """The one policy for writing over an existing output file: an earlier output of the same
    kind (`earlier` says which, e.g. "an earlier correction table") is replaced, and `say(line)`
    is told; anything else (`not_what`: what it is instead) is refused unless `force`, with
    `remedy` (what to do instead) ending the line."""
    if earlier is None and not force:
        raise UserError(
            f"{what} {path} exists and is {not_what}; writing there would destroy it; {remedy}"
        )
    if say is not None:
        say(f"replacing {path}: {earlier or '(--force)'}")


def folder_problem(folder) -> str | None:
    """Why no file can be written in the existing `folder` (None: it can): not writable, marked
    read-only (no write bit; root could write anyway, and should not), or refusing a test file
    (/proc, /sys, a read-only mount, where os.access says yes to root)."""
    import os
    import stat
    import tempfile
    from pathlib import Path

    folder = Path(folder)
    try:
        if not os.access(folder, os.W_OK):
            return f"{folder} is not writable"
        mode = folder.stat().st_mode
        if not mode & 0o222:
            return f"{folder} is read-only (mode {stat.filemode(mode)})"
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return f"{folder} is not writable (a test file could not be made there)"
    return None


def check_output_path(path, what: str = "output", *, folder: bool = False, inputs=()):
    """Refuse, before any work, an output path that cannot be written: a file where a folder
    is needed (or the reverse), a folder that takes no new file (`folder_problem`), or one of the
    command's `inputs` or an existing recording (`refuse_overwrite`). Missing folders are fine
    (created). Returns the path as a `pathlib.Path`."""
    import os
    from pathlib import Path

    p = Path(path)
    try:  # a name the file system cannot take fails only at the write, after the work
        name_max = os.pathconf(p.parent if p.parent.exists() else "/", "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    for part in p.parts:
        if len(os.fsencode(part)) > name_max:
            raise UserError(
                f"cannot write {what}: the name {part[:40]}... is {len(os.fsencode(part))} bytes "
                f"long, and the file system takes at most {name_max}; choose a shorter name"
            )
    for q in (p, *p.parents):  # open() and mkdir() say only "File exists" for these
        if q.is_symlink() and not q.exists():
            raise UserError(
                f"cannot write {what} {p}: {q} is a symbolic link to {os.readlink(q)}, which "
                "does not exist; give another path, or make the link's target first"
            )
    if not folder:
        refuse_overwrite([p], inputs, what)
    if folder and p.exists() and not p.is_dir():
        raise UserError(f"{what} {p} exists and is a file; give a folder")
    if not folder and p.is_dir():
        raise UserError(f"{what} {p} is a folder; give a file name")
    anc = p if folder else p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise UserError(f"cannot write {what} {p}: {anc} is a file, not a folder")
    why = folder_problem(anc)
    if why is not None:
        raise UserError(f"cannot write {what} {p}: {why}; choose another folder")
    return p


class OneLineParser(argparse.ArgumentParser):
    """An option mistake is one line (what is wrong, where the help is), not the usage block."""

    def error(self, message: str):  # type: ignore[override]
        if message.endswith("expected one argument"):
            # argparse reads "-0.5,..." as an option
            message += " (a value that starts with '-' goes after '=': --volume=-0.5,...)"
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")
