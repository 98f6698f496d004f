"""`workcell bench NAME [args]`: run a benchmark module; `all` runs every one in turn."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from workcell.bench import BENCHES
from workcell.errors import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help=f"one of: all, {', '.join(BENCHES)}")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="arguments for the benchmark")


def run(args: argparse.Namespace) -> int:
    names = list(BENCHES) if args.name == "all" else [args.name]
    if args.name == "all" and args.rest:
        if args.rest in (["-h"], ["--help"]):
            print(
                f"workcell bench all: runs every benchmark with its defaults: "
                f"{', '.join(BENCHES)}; each has its own options (`workcell bench NAME --help`)"
            )
            return 0
        raise UserError(
            f"`bench all` runs each benchmark with its defaults and takes no options (got "
            f"{' '.join(args.rest)}); give them to one benchmark: `workcell bench NAME ...`"
        )
    rc = 0
    for name in names:
        if name not in BENCHES:
            raise UserError(f"unknown benchmark {name!r}; choose from: all, {', '.join(BENCHES)}")
        try:
            mod = importlib.import_module(BENCHES[name])
        except ModuleNotFoundError as e:
            if args.name == "all" and e.name == BENCHES[name]:
                print(f"[bench {name}] not available in this build")
                continue
            raise
        if args.name == "all":
            default = getattr(mod, "DEFAULT_RECORDING", None)
            if default is not None and not Path(default).is_file():
                print(
                    f"[bench {name}] skipped: its default recording {default} is not here (an "
                    f"installed package, or no ../shared beside the checkout); run `workcell "
                    f"bench {name} --recording PATH`",
                    flush=True,
                )
                continue
            print(f"== workcell bench {name}", flush=True)
        rc = max(rc, int(mod.main(list(args.rest)) or 0))
    return rc
