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
