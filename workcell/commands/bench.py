"""`workcell bench NAME [args]`: run a benchmark module; `all` runs every one in turn."""

from __future__ import annotations

import argparse
import importlib

from workcell.bench import BENCHES
from workcell.errors import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help=f"one of: all, {', '.join(BENCHES)}")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="arguments for the benchmark")


def run(args: argparse.Namespace) -> int:
    names = list(BENCHES) if args.name == "all" else [args.name]
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
            print(f"== workcell bench {name}", flush=True)
        rc = max(rc, int(mod.main(list(args.rest)) or 0))
    return rc
