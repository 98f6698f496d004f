"""`workcell` command line. Thin: every subcommand lives in `workcell/commands/<name>.py` with

    def add_arguments(parser: argparse.ArgumentParser) -> None
    def run(args: argparse.Namespace) -> int

User errors raise `workcell.errors.UserError` (or ValueError/OSError from validation) and are
printed as one line `workcell <cmd>: error: ...` with exit code 2, never a traceback.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
import warnings

from workcell.errors import INTERRUPTED, console_command

# Ctrl-C is noted in INTERRUPTED as well as raised (see there). While modules load it is only
# noted (raised there, inside jaxlib's start-up, it can abort or crash the process) and acted on
# once they are loaded.
_RAISE = False


def _on_sigint(signum, frame) -> None:
    INTERRUPTED.set()
    if _RAISE:
        raise KeyboardInterrupt


def _unraisable(u) -> None:
    """The Ctrl-C that Python drops in a callback is noted in INTERRUPTED: no traceback for it."""
    if not isinstance(u.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(u)


if console_command() or __name__ == "__main__":
    signal.signal(signal.SIGINT, _on_sigint)  # the console command only, not when imported
    sys.unraisablehook = _unraisable

import argparse  # noqa: E402
import importlib  # noqa: E402
from pathlib import Path  # noqa: E402

from workcell.drivers.protocols import DeviceError  # noqa: E402
from workcell.errors import OneLineParser, UserError, hard_exit  # noqa: E402

# name -> (module, one-line help). Modules are imported lazily (JAX start-up is slow).
COMMANDS: dict[str, tuple[str, str]] = {
    "info": ("workcell.commands.info", "summarise a recording"),
    "campaign": ("workcell.commands.campaign", "run a measurement campaign and record it"),
    "fit": ("workcell.commands.fit", "fit a calibrated model to a recording"),
    "demo": ("workcell.commands.demo", "simulated campaign, fits and correction end to end"),
    "sim": ("workcell.commands.sim", "start the protocol-level simulators (UR + tracker)"),
    "replay": ("workcell.commands.replay", "replay a recording through an online estimator"),
    "diagnose": ("workcell.commands.diagnose", "find the physics the nominal model left out"),
    "export": ("workcell.commands.export", "write a correction for the robot controller"),
    "validate": ("workcell.commands.validate", "closed-loop check of an exported correction"),
    "envelope": ("workcell.commands.envelope", "write or check a safety envelope file"),
    "tui": ("workcell.commands.tui", "the shop-floor terminal UI"),
    "bench": ("workcell.commands.bench", "benchmarks that print their figures"),
}


def _load(name: str):
    module, _ = COMMANDS[name]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name == module:
            return None
        raise


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="workcell",
        description="Robot calibration with a laser tracker: campaign, fit, diagnose, export.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    return parser, sub


FP_NOTES = r"(overflow|invalid value|divide by zero|underflow) encountered"


# options that name a file or folder (their dest, their flag): an empty one is a slip of the
# shell (`--out "$DIR"` with DIR unset), which some commands read as "not given" and wrote
# their default, `demo --out ''` into the working directory
_PATH_OPTIONS = (
    ("out", "--out"), ("save", "--save"), ("report", "--report"), ("table", "--table"),
    ("envelope", "--envelope"), ("resume", "--resume"), ("check", "--check"),
    ("targets_in", "--in"),
)  # fmt: skip


# what to give instead, where a generic "give a value" says less
_EMPTY_SAYS = {
    "--bounds": "give a JSON file of bounds or 'default' (leave --bounds out, or give 'none', "
    "for the unbounded fit)",
    "--smr-offset": "give X,Y,Z in metres on the flange (or leave --smr-offset out)",
    "--payload": "give KG or KG,CX,CY,CZ (or leave --payload out)",
}


def _refuse_empty_values(argv: list[str], args: argparse.Namespace) -> None:
    """An empty value typed on the command line (`--volume ''`, `fit ''`) is refused in one
    line: read as "not given", it ran the default (a table over the default volume, the
    controller's payload for `--payload ''`). Options whose value is '' by default are not
    affected: only what was typed is looked at."""
    paths = {flag: dest for dest, flag in _PATH_OPTIONS}
    for j, a in enumerate(argv):
        if a.startswith("--") and "=" in a:
            flag, value = a.split("=", 1)
        elif not a.strip():
            flag, value = (argv[j - 1] if j else ""), a
        else:
            continue
        if value.strip():
            continue
        dest = paths.get(flag) or flag[2:].replace("-", "_")
        # a flag's own value (a sub-command's, as bench's, is not in `args`); after a switch
        # (`--json ''`) the empty string is a positional argument
        if flag.startswith("--") and not isinstance(getattr(args, dest, None), bool):
            what = _EMPTY_SAYS.get(flag) or (
                f"give {'a path' if flag in paths else 'a value'} (or leave {flag} out)"
            )
            raise UserError(f"{flag} is empty: {what}")
        raise UserError(
            "an empty argument ('') on the command line, where a file or name goes: give it"
        )


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit code. As the console entry point (argv None), a Ctrl-C
    at any moment (loading modules included) is one line and exit 130: the process ends at once
    (`os._exit`), as a half-finished JAX call can crash the interpreter's shutdown."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        name = next((a for a in (argv or sys.argv[1:]) if not a.startswith("-")), "")
        print(f"workcell {name}: interrupted".replace("  ", " "), file=sys.stderr)
        if argv is None:
            hard_exit(130)
        return 130


# a write that found no room, and what to do (file-size limits: `ulimit -f`, FAT's 4 GiB)
NO_ROOM = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is used up",
    errno.EFBIG: "the file grew beyond what this system allows (a file-size limit, `ulimit -f`?)",
}


def _after_no_room(command: str, e: OSError) -> str:
    """What the user does after a write that found no room: a campaign's recording keeps what
    was measured (`run_campaign` notes it on the error) and is resumed; a campaign that
    recorded nothing left no file; any other command's earlier outputs are as they were (each
    is replaced whole or not at all)."""
    rec = getattr(e, "recording", None)
    if rec is not None and Path(rec[0]).is_file():
        from workcell.campaign.run import resume_hint

        return f"make room and continue: {resume_hint(*rec)}"
    if command in ("campaign", "demo"):
        return "make room and run it again (nothing was measured, no recording was left)"
    return "make room and run it again (earlier outputs are left as they were)"


def _debug_traceback() -> None:
    """With WORKCELL_DEBUG set, the traceback of the error being handled, before its one line."""
    if os.environ.get("WORKCELL_DEBUG"):
        import traceback

        traceback.print_exc()


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, sub = build_parser()
    # Only import the module of the command asked for (keeps `workcell --help` fast).
    name = next((a for a in argv if not a.startswith("-")), None)
    for cmd, (_, help_) in COMMANDS.items():
        p = sub.add_parser(cmd, help=help_, description=help_)
        if cmd == name:
            mod = _load(cmd)
            if mod is None:
                print(f"workcell {cmd}: error: not available in this build", file=sys.stderr)
                return 2
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
    args, extra = parser.parse_known_args(argv)
    if extra:  # said by the command's own parser: its name, and the help that lists its options
        command = getattr(args, "command", None)
        (sub.choices[command] if command in sub.choices else parser).error(
            f"unrecognized arguments: {' '.join(extra)}"
        )
    global _RAISE
    _RAISE = True  # modules loaded: from here a Ctrl-C raises where it lands
    if INTERRUPTED.is_set():
        raise KeyboardInterrupt
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        _refuse_empty_values(argv, args)
        with warnings.catch_warnings():
            if not os.environ.get("WORKCELL_DEBUG"):
                # numpy's floating-point notes ("overflow encountered in dot") printed before a
                # one-line refusal of the same bad value (a hand-edited file's 1e308): results
                # are checked for finiteness where they are used; WORKCELL_DEBUG shows them
                warnings.filterwarnings("ignore", category=RuntimeWarning, message=FP_NOTES)
            return int(args._run(args) or 0)
    except UserError as e:
        _debug_traceback()
        print(f"workcell {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except DeviceError as e:
        _debug_traceback()
        print(f"workcell {args.command}: error: {e}", file=sys.stderr)
        return 3
    except BrokenPipeError:
        # whoever read our output went away (`workcell info X | head`): nothing to report;
        # stdout goes to /dev/null so the interpreter's final flush does not fail again
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except OSError:
            pass
        return 141  # 128 + SIGPIPE, what a shell reports for a writer killed by a closed pipe
    except (ValueError, OSError) as e:
        if os.environ.get("WORKCELL_DEBUG"):
            raise
        msg = str(e)
        if isinstance(e, OSError) and e.filename and e.strerror:
            msg = f"cannot use {e.filename}: {e.strerror}"
        if isinstance(e, OSError) and e.errno in NO_ROOM:
            msg += f"; {NO_ROOM[e.errno]}: {_after_no_room(args.command, e)}"
        print(f"workcell {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except RecursionError:
        print(
            f"workcell {args.command}: error: an input file is nested too deeply to read (a "
            "JSON file that is not a workcell file?); check the files given",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
