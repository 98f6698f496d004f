"""Benchmarks: `workcell bench NAME`. Each module exposes `main(argv: list[str]) -> int`."""

BENCHES: dict[str, str] = {
    "dh": "workcell.bench.dh_fit",
    "lddmm-pendulum": "workcell.bench.lddmm_pendulum",
    "lddmm": "workcell.bench.lddmm_perf",
    "ekf-ann": "workcell.bench.ekf_ann",
    "design": "workcell.bench.design",
    "design-real": "workcell.bench.design_real",
    "discovery": "workcell.bench.discovery",
}


def check_ranges(ap, checks) -> None:
    """`ap.error` (one line, exit 2) for the first option outside its range: `checks` is
    (option, value, lo, hi) with inclusive bounds; a count far beyond any sensible run gave
    numpy's own words ("Maximum allowed dimension exceeded") or ran for days."""

    def num(x) -> str:
        return f"{x:,}".replace(",", "_") if isinstance(x, int) else f"{x:g}"

    for opt, v, lo, hi in checks:
        if not lo <= v <= hi:
            got = num(v) if len(str(v)) <= 20 else f"{v:.3g}"
            ap.error(f"{opt} must be {num(lo)}..{num(hi)}, got {got}")


def environment() -> dict:
    """What a benchmark figure was measured with, for its JSON (`environment`): a figure that
    moves between runs of the same commit moved with these (library versions change numerics,
    a loaded machine changes rates)."""
    import os
    import platform
    import subprocess
    from importlib import metadata
    from pathlib import Path

    versions = {}
    for dist in ("workcell", "numpy", "scipy", "jax", "jaxlib", "filterpy", "mcap"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    commit = None
    here = Path(__file__).resolve().parent
    try:

        def git(*cmd: str) -> str:
            return subprocess.run(
                ["git", *cmd], cwd=here, capture_output=True, text=True, timeout=5
            ).stdout.strip()

        # workcell's own checkout only: an installed package inside some other repository
        # (a venv in a project folder) would report that repository's commit
        top = git("rev-parse", "--show-toplevel")
        if top and Path(top).resolve() == here.parents[1]:
            commit = git("describe", "--always", "--dirty", "--abbrev=7") or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    try:
        load = round(os.getloadavg()[0], 2)
    except OSError:
        load = None
    return {
        "commit": commit,
        "python": platform.python_version(),
        "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPUs",
        "load_avg_1min": load,
        "versions": versions,
    }


# keys that mark a result written before results carried their bench's name
_OLD_RESULT_KEYS = {
    "discovery": {"master_seed", "cases", "environment"},
    "lddmm-pendulum": {"scenarios", "heatmap_png", "environment"},
}


def result_of(path) -> str | None:
    """Which bench wrote the JSON file at `path` (its `bench` key, or the keys of an older
    result), or None: not a bench result, missing, or unreadable."""
    import json
    from pathlib import Path

    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError, RecursionError):
        return None
    if not isinstance(d, dict):
        return None
    if isinstance(d.get("bench"), str):
        return d["bench"]
    return next((b for b, keys in _OLD_RESULT_KEYS.items() if keys <= d.keys()), None)


def check_bench_outputs(paths, bench: str, result, *, force: bool, say) -> None:
    """Refuse, before any work, to write a bench's output files (`paths`) over existing files
    that are not an earlier run of the same bench: `result` is the JSON result among `paths`,
    whose `bench` key tells. An earlier run's files are replaced (`say` is told); anything else
    only with `force`."""
    from pathlib import Path

    from workcell.errors import replace_or_refuse

    earlier = f"an earlier `workcell bench {bench}` result" if result_of(result) == bench else None
    for p in paths:
        if Path(p).exists():
            replace_or_refuse(
                "bench output",
                p,
                earlier,
                f"not a result of `workcell bench {bench}`",
                force=force,
                say=say,
            )
